"""configs/data/horizonnet_folder.yaml and configs/data/noncentral_indoor.yaml (issue 15 item 1): rooms with
different corner counts collate (``corners_cam`` padded as :mod:`omnidl.data.layout_sample` pads it), the split
folders of each format, and ``train.py`` -> ``evaluate.py`` end to end on datasets written by the synth CLI."""

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from omnidl.data.collate import collate_samples
from omnidl.data.horizonnet_format import HorizonNetFolderDataset, write_label_cor
from omnidl.data.noncentral_indoor import NonCentralIndoorDataset
from tests.zygote import run_python

sys.path.insert(0, str(Path(__file__).resolve().parent))
from adapter_fixtures import ROOMS, instantiate_split, paint_room  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
W, H = 128, 64


def write_horizonnet(root: Path, rooms: dict, camera_height: float = 1.6, ceiling: float = 1.2) -> None:
    """``root/img/<room>.png`` + ``root/label_cor/<room>.txt`` written from top-view polygons (layout order)."""
    import cv2
    from omnidl.metrics.layout_protocol import corner_pixels
    (root / "img").mkdir(parents=True, exist_ok=True)
    for i, (name, poly) in enumerate(rooms.items()):
        cv2.imwrite(str(root / "img" / f"{name}.png"), paint_room(poly, camera_height, ceiling, W, H, i)[..., ::-1])
        write_label_cor(root / "label_cor" / f"{name}.txt",
                        corner_pixels(poly, (-camera_height, ceiling), W, H).reshape(-1, 2) - 0.5)


def synth(fmt: str, out: Path, split: str, n: int) -> None:
    """``python -m omnidl.apps.synth --format <fmt>`` (its ``main``, in this process: no interpreter start-up)."""
    from omnidl.apps.synth import main
    camera = "noncentral_pano" if fmt == "noncentral" else "equirect"
    args = ["--camera", camera, "--format", fmt, "--width", str(W), "--height", str(H), "--n", str(n),
            "--split", split, "--out", str(out), "--no-furniture", "--contact-sheet", "0"]
    assert main(args + (["--rc", "1.0"] if fmt == "noncentral" else [])) == 0


@pytest.fixture(scope="module")
def synth_roots(tmp_path_factory):
    """HorizonNet's ``{train,valid,test}/`` and the non-central dataset's ``{train,val,test}/`` folders."""
    base = tmp_path_factory.mktemp("synth")
    for fmt, dirs in (("horizonnet", ("train", "valid", "test")), ("noncentral", ("train", "val", "test"))):
        for split, d in zip(("train", "val", "test"), dirs):
            synth(fmt, base / fmt / d, split, 2)
    return base / "horizonnet", base / "noncentral"


def _loader(ds, bs=2):
    return torch.utils.data.DataLoader(ds, batch_size=bs, collate_fn=collate_samples)


def test_horizonnet_rooms_with_different_corner_counts_collate(tmp_path):
    write_horizonnet(tmp_path, {"box": ROOMS["box"], "ell": ROOMS["ell"]})
    ds = HorizonNetFolderDataset(tmp_path, width=W, height=H, max_walls=8)
    batch = next(iter(_loader(ds)))
    assert batch["corners_cam"].shape == (2, 8, 2, 3) and batch["num_walls"].tolist() == [4, 6]
    assert (batch["corners_cam"][0, 4:] == 0).all() and (batch["corners_cam"][1, 6:] == 0).all()
    assert batch["camera_height"].tolist() == pytest.approx([1.6, 1.6])
    from omnidl.metrics.layout import corners_to_layout
    poly, h_c, h_f = corners_to_layout(batch["corners_cam"][1, :6].double().numpy())
    gap = np.linalg.norm(poly[:, None] - ROOMS["ell"][None], axis=-1).min(0)        # every true corner recovered
    assert gap.max() < 0.05 and h_f == pytest.approx(-1.6) and h_c == pytest.approx(1.2, 0.02)
    with pytest.raises(ValueError, match=r"ell\.txt: room polygon has 6 corners, more than max_walls=5"):
        HorizonNetFolderDataset(tmp_path, max_walls=5)[1]


def test_noncentral_rooms_with_different_corner_counts_collate(synth_roots):
    root = synth_roots[1]
    for kw in ({}, {"label_cor_only": True}, {"boundary_source": "corners", "depth": False}):
        ds = NonCentralIndoorDataset(root, split="train", width=W, height=H, **kw)
        batch = next(iter(_loader(ds)))
        n = batch["num_walls"].tolist()
        assert batch["corners_cam"].shape == (2, 32, 2, 3) and n[0] != n[1], kw
        for b in range(2):
            assert (batch["corners_cam"][b, n[b]:] == 0).all() and (batch["corners_cam"][b, :n[b]] != 0).any(-1).all()


def test_horizonnet_split_folders(synth_roots, tmp_path):
    root = synth_roots[0]
    for split in ("train", "val", "test"):
        ds = HorizonNetFolderDataset(root, split=split, width=W, height=H)
        assert len(ds) == 2 and ds.root.name == {"val": "valid"}.get(split, split)
    write_horizonnet(tmp_path / "val", {"box": ROOMS["box"]})                # val/ works as well as valid/
    assert len(HorizonNetFolderDataset(tmp_path, split="val")) == 1
    assert len(HorizonNetFolderDataset(tmp_path / "val", split=None)) == 1
    with pytest.raises(FileNotFoundError, match=r"no folder for split 'test' .*looked for .*test"):
        HorizonNetFolderDataset(tmp_path, split="test")
    with pytest.raises(ValueError, match=r"unknown split 'valid'; expected one of train, val, test"):
        HorizonNetFolderDataset(tmp_path, split="valid")
    assert len(HorizonNetFolderDataset(root, split="train", max_samples=1)) == 1


@pytest.mark.parametrize("data, idx", [("horizonnet_folder", 0), ("noncentral_indoor", 1)])
@pytest.mark.parametrize("split", ["train", "val", "test"])
def test_config(synth_roots, tmp_path, data, idx, split):
    ds = instantiate_split(tmp_path, data, synth_roots[idx], split, [f"data.height={H}", f"data.width={W}"])
    assert len(ds) == 2
    s = ds[0]
    assert s["image"].shape == (3, H, W) and s["boundary"].shape == (2, W) and s["corners_cam"].shape == (32, 2, 3)


def test_noncentral_config_modes(synth_roots, tmp_path):
    ds = instantiate_split(tmp_path, "noncentral_indoor", synth_roots[1] / "test", "test",
                           [f"data.height={H}", f"data.width={W}", "data.label_cor_only=true", "data.test_split=null",
                            "data.sample_rc=null"])
    assert len(ds) == 2 and ds.label_cor_only and ds[0]["meta"]["rig_radius"] == 1.0
    with pytest.raises(ValueError, match=r"img/SYN00000_R10000\.png: image is 128x64, expected 256x128"):
        instantiate_split(tmp_path, "noncentral_indoor", synth_roots[1], "val",
                          ["data.height=128", "data.width=256"])[0]


# ----------------------------------------------------------------------------------------------------------
# train.py -> evaluate.py end to end (the acceptance command of issue 15)
# ----------------------------------------------------------------------------------------------------------

def _run(args):
    """``python *args`` from the repository root, in a new process (a child of tests/zygote.py's zygote)."""
    r = run_python(args, ROOT, timeout=900)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]


def train_and_evaluate(model: str, data: str, root: Path, out: Path, evaluate=()) -> dict:
    common = [f"model={model}", f"data={data}", f"data.root={root}", f"data.height={H}", f"data.width={W}",
              "trainer.num_threads=1", "trainer.progress=false"]
    _run(["train.py", "trainer=debug", "trainer.max_steps=1", "trainer.val_max_batches=1",
          f"paths.output_dir={out / 'train'}", *common])
    best = out / "train" / "checkpoints" / "best.pt"
    assert best.is_file()
    _run(["evaluate.py", f"checkpoint={best}", f"paths.output_dir={out / 'eval'}", "eval.batch_size=2",
          *common, *evaluate])
    return json.loads((out / "eval" / "metrics.json").read_text())


@pytest.mark.slow
def test_horizonnet_folder_train_and_evaluate(synth_roots, tmp_path):
    res = train_and_evaluate("horizonnet", "horizonnet_folder", synth_roots[0], tmp_path,
                             ["metrics=layout_protocol", "metrics.protocol=horizonnet"])
    assert res["num_images"] == 2 and {"iou_2d", "iou_3d", "boundary_px"} <= set(res["metrics"])
    assert all(math.isfinite(v) for v in res["metrics"].values())


@pytest.mark.slow
def test_noncentral_indoor_train_and_evaluate(synth_roots, tmp_path):
    res = train_and_evaluate("horizonnet_nc", "noncentral_indoor", synth_roots[1], tmp_path)
    assert res["num_images"] == 2 and "boundary_px" in res["metrics"]
    assert all(math.isfinite(v) for v in res["metrics"].values())
    # the image + label_cor-only mode of the same dataset (issue 15): the other folders are not read
    _run(["evaluate.py", f"checkpoint={tmp_path / 'train' / 'checkpoints' / 'best.pt'}", "model=horizonnet_nc",
          "data=noncentral_indoor", f"data.root={synth_roots[1]}", f"data.height={H}", f"data.width={W}",
          "data.label_cor_only=true", "trainer.num_threads=1", f"paths.output_dir={tmp_path / 'eval_lco'}"])
    lco = json.loads((tmp_path / "eval_lco" / "metrics.json").read_text())
    assert lco["num_images"] == 2 and math.isfinite(lco["metrics"]["boundary_px"])
