import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from omnidl.data.collate import collate_samples
from omnidl.data.horizonnet_format import HorizonNetFolderDataset, write_label_cor
from omnidl.data.pano_annotator import PanoAnnotatorLayout, read_pano_annotator_json
from omnidl.metrics.layout import corners_to_layout
from tests.zygote import run_python

sys.path.insert(0, str(Path(__file__).resolve().parent))
from adapter_fixtures import ROOMS, pano_annotator_label, write_pano_annotator  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


def test_reads_rooms_heights_and_targets(tmp_path):
    truth = write_pano_annotator(tmp_path)
    ds = PanoAnnotatorLayout(tmp_path, split="train", height=32, width=64)
    assert len(ds) == 3 and ds.camera.width == 64
    for i in range(len(ds)):
        s = ds[i]
        poly0, ch, ceil = truth[s["meta"]["name"]]
        n = int(s["num_walls"])
        poly, h_c, h_f = corners_to_layout(s["corners_cam"][:n].double().numpy())
        assert np.allclose(poly, poly0, atol=1e-6) and h_c == pytest.approx(ceil, abs=1e-6)
        assert h_f == pytest.approx(-ch, abs=1e-6) and float(s["camera_height"]) == pytest.approx(ch)
        assert s["image"].shape == (3, 32, 64) and s["boundary"].shape == (2, 64) and s["boundary_valid"].all()
        assert s["corners_cam"].shape == (32, 2, 3) and (s["corners_cam"][n:] == 0).all()
        assert s["corner_heat"].shape == (1, 64) and s["corner_heat"].max() > 0.9
    batch = collate_samples([ds[0], ds[1]])
    assert batch["corners_cam"].shape == (2, 32, 2, 3) and batch["num_walls"].tolist() == [4, 6]


def test_axes_follow_the_panoannotator_coords(tmp_path):
    """The file's own ``coords`` (PanoAnnotator's pixel fractions) are where omnidl projects the floor corners."""
    from omnidl.cameras import Equirectangular
    write_pano_annotator(tmp_path)
    ds = PanoAnnotatorLayout(tmp_path, split=None, height=32, width=64)
    for i, (name, _, lab) in enumerate(ds.items):
        data = json.loads(lab.read_text())
        s = ds[i]
        n = int(s["num_walls"])
        uv, _ = Equirectangular(width=64, height=32).project(s["corners_cam"][:n, 1].double())
        coords = np.array([p["coords"] for p in data["layoutPoints"]["points"]])
        assert np.allclose(uv.numpy() / [64, 32], coords, atol=1e-6)


def test_matches_the_label_cor_adapter(tmp_path):
    """The same room written as HorizonNet label_cor gives the same boundary targets (to label rounding)."""
    from omnidl.metrics.layout_protocol import corner_pixels
    truth = write_pano_annotator(tmp_path / "pa", w=256, h=128, rooms={"box": ROOMS["box"]}, splits={})
    poly, ch, ceil = truth["scene0_box"]
    (tmp_path / "hn" / "img").mkdir(parents=True)
    (tmp_path / "hn" / "img" / "a.png").write_bytes((tmp_path / "pa" / "image" / "scene0_box.png").read_bytes())
    c = corner_pixels(poly, (-ch, ceil), 256, 128).reshape(-1, 2) - 0.5       # label_cor: x = u - 0.5
    write_label_cor(tmp_path / "hn" / "label_cor" / "a.txt", c)
    a = PanoAnnotatorLayout(tmp_path / "pa", split=None, height=128, width=256)[0]
    b = HorizonNetFolderDataset(tmp_path / "hn", camera_height=ch)[0]
    assert (a["boundary"] - b["boundary"]).abs().max() < 0.1
    assert (a["corner_heat"] - b["corner_heat"]).abs().max() < 0.05


def test_split_files_and_release_names(tmp_path):
    write_pano_annotator(tmp_path, splits={})
    names = sorted(p.stem for p in (tmp_path / "image").iterdir())
    (tmp_path / "mp3d_val.txt").write_text(" ".join(names[0].split("_", 1)) + "\n\n# comment\n")
    lab = tmp_path / "label" / f"{names[0]}.json"
    lab.rename(tmp_path / "label" / f"{names[0]}_label.json")               # the release's file name
    ds = PanoAnnotatorLayout(tmp_path, split="val", height=32, width=64)
    assert [n for n, _, _ in ds.items] == [names[0]] and ds[0]["meta"]["label_file"].endswith("_label.json")
    assert len(PanoAnnotatorLayout(tmp_path, split=None, height=None, width=None)) == 3
    one = tmp_path / "one.txt"
    one.write_text(names[2] + "\n")
    assert len(PanoAnnotatorLayout(tmp_path, split="train", split_file=one)) == 1


def test_layout_height_fallback(tmp_path):
    d = pano_annotator_label(ROOMS["slant"], 1.5, 1.3)
    del d["cameraCeilingHeight"]
    p = tmp_path / "x.json"
    p.write_text(json.dumps(d))
    lab = read_pano_annotator_json(p)
    assert lab.ceiling_height == pytest.approx(1.3) and lab.camera_height == 1.5
    assert np.allclose(lab.polygon, ROOMS["slant"])


def _run(args, cwd):
    """``python *args`` in ``cwd``, in a new process (a child of tests/zygote.py's zygote)."""
    r = run_python(args, cwd, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return r


def train_and_evaluate(data: str, root: Path, out: Path) -> dict:
    """``train.py model=horizonnet data=<data> trainer=debug`` then ``evaluate.py`` with its best checkpoint."""
    common = [f"data={data}", f"data.root={root}", "data.height=64", "data.width=128", "trainer.num_threads=1",
              "trainer.progress=false"]
    _run(["train.py", "model=horizonnet", "trainer=debug", "trainer.max_steps=1", "trainer.val_max_batches=1",
          f"paths.output_dir={out / 'train'}", *common], ROOT)
    best = out / "train" / "checkpoints" / "best.pt"
    assert best.is_file()
    _run(["evaluate.py", "model=horizonnet", f"checkpoint={best}", f"paths.output_dir={out / 'eval'}",
          "metrics=layout_protocol", "metrics.protocol=lgtnet", *common], ROOT)
    return json.loads((out / "eval" / "metrics.json").read_text())


@pytest.mark.slow
def test_train_and_evaluate_end_to_end(tmp_path):
    write_pano_annotator(tmp_path / "data", w=128, h=64)
    res = train_and_evaluate("pano_annotator", tmp_path / "data", tmp_path)
    assert res["num_images"] == 2 and "boundary_px" in res["metrics"]
    assert {"gt_skipped", "iou_2d", "iou_3d", "layout_fail_rate"} <= set(res["metrics"])    # the lgtnet protocol ran
    assert all(math.isfinite(v) for v in res["metrics"].values())


@pytest.mark.parametrize("split, n", [("train", 3), ("val", 2), ("test", 2)])
def test_config(tmp_path, split, n):
    from adapter_fixtures import instantiate_split
    write_pano_annotator(tmp_path / "d")
    ds = instantiate_split(tmp_path, "pano_annotator", tmp_path / "d", split, ["data.height=16", "data.width=32"])
    assert len(ds) == n and ds[0]["image"].shape == (3, 16, 32)
