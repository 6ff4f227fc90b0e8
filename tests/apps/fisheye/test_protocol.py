"""The §7.4 protocol (``python -m omnidl.apps.fisheye.protocol``) end to end on a tiny stand-in (closed-form
panoramas, 36x32 images, a few steps), its stages trained by omnidl.engine.train."""
import csv
import json
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from omnidl.apps.fisheye import protocol

from tests.data.panorama_standin import StandInPanoramas

CONFIG = Path(__file__).resolve().parents[3] / "configs" / "fisheye" / "small_cpu.yaml"


def tiny_cfg():
    return protocol.load_config(str(CONFIG), [
        "image.width=36", "image.height=32", "views_per_panorama=2", "model.base_channels=2", "model.levels=2",
        "train.steps=2", "train.batch_size=2", "finetune.steps=1", "eval.batch_size=4", "radial.num_bins=4", "plots=false"])


@pytest.mark.slow
def test_protocol_end_to_end(tmp_path):
    pan = {"train": StandInPanoramas(2, 64, 32), "test": StandInPanoramas(1, 64, 32)}
    res = protocol.run(tiny_cfg(), tmp_path, panoramas=pan)
    rows = list(csv.DictReader(open(tmp_path / "results.csv")))
    keys = {(r["stage"], r["dataset"], r["kernel"]) for r in rows}
    expect = {("BL", "Pers", "Std"), ("BL", "Pers", "Calib")}
    for f in ("F165", "F195"):
        expect |= {(s, f, k) for s in ("BL", "FT") for k in ("Std", "Calib")} | {(s, f + "-R", "Std") for s in ("BL", "FT")}
    assert keys == expect
    for r in rows:
        assert 0 <= float(r["mre"]) < 100 and 0 <= float(r["miou"]) <= 100
    md = (tmp_path / "tables.md").read_text()
    assert "Table 7.1" in md and "Table 7.2" in md and "F195-R" in md and "cannot be rectified" in md
    assert res["coverage"]["F195"]["unrectifiable"] > 0.1 and res["coverage"]["F165"]["unrectifiable"] == 0
    assert not list(tmp_path.glob("*.png"))      # plots=false (plot_radial is tested in tests/metrics)
    for f in ("F165", "F195"):
        radial = list(csv.DictReader(open(tmp_path / "radial" / f"{f}_FT-Calib.csv")))
        assert len(radial) == 4 and "mre_std" in radial[0]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert set(summary["comparison"]) == {"F165", "F195"}
    # one unit everywhere: segmentation scores are fractions in results.csv, summary.json rows and comparison
    assert all(0 <= float(r["miou"]) <= 1 and 0 <= float(r["macc"]) <= 1 for r in rows)
    assert [r["miou"] for r in summary["rows"]] == [float(r["miou"]) for r in rows]
    for per in summary["comparison"].values():
        for key in ("miou_all", "macc_all"):
            if key in per["metrics"]:
                assert 0 <= per["metrics"][key]["std"] <= 1
    assert "fractions" in summary["units"] and "mIoU (%)" in md
    # a re-run loads the stage checkpoints instead of training again
    ck = tmp_path / "checkpoints" / "pers_bl.pt"
    mtime = ck.stat().st_mtime
    protocol.run(tiny_cfg(), tmp_path, panoramas=pan)
    assert ck.stat().st_mtime == mtime


def test_config_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        protocol.load_config(str(tmp_path / "nope.yaml"), [])
    bad = tmp_path / "bad.yaml"
    OmegaConf.save(OmegaConf.create({"image": {"width": 8}}), bad)
    with pytest.raises(KeyError, match="no 'panoramas' section"):
        protocol.load_config(str(bad), [])
    assert protocol.main(["--config", str(tmp_path / "nope.yaml")]) == 2
