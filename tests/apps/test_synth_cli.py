"""Writer CLI (``python -m omnidl.apps.synth``) and on-disk formats: resumability, label files, Stanford loader."""
import json

import cv2
import numpy as np
import pytest
import torch

from omnidl.apps.synth import main
from omnidl.cameras import resolve_camera
from omnidl.synth import render_sample
from omnidl.synth.export import decode_depth_24bit, heading_frame


@pytest.fixture(autouse=True)
def _threads():
    torch.set_num_threads(1)


def test_noncentral_export_roundtrip_and_resume(tmp_path):
    out = tmp_path / "nc"
    args = ["--camera", "noncentral_pano", "--n", "2", "--out", str(out), "--width", "64", "--height", "32",
            "--rc", "0.5", "--contact-sheet", "2"]
    assert main(args) == 0
    names = sorted(p.stem for p in (out / "img").glob("*.png"))
    assert names == ["SYN00000_R05000", "SYN00001_R05000"]
    assert (out / "contact_sheet.png").exists() and not list(out.rglob("*.tmp"))
    cam = resolve_camera("noncentral_pano", 64, 32, rc=0.5)
    sample = render_sample(cam, 0, "train", 1)
    name = names[1]
    bgr = cv2.imread(str(out / "depth_coded" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
    depth = decode_depth_24bit(bgr[..., ::-1])
    ref = sample["depth"][0].numpy().astype(np.float64)
    m = ref < 10.0
    assert np.abs(depth - ref)[m].max() < 1e-3
    img = cv2.imread(str(out / "img" / f"{name}.png"))[..., ::-1]
    assert np.abs(img.astype(float) / 255 - sample["image"].permute(1, 2, 0).numpy()).max() <= 0.5 / 255 + 1e-6
    # 3D_gt / cam_pose in the heading frame: the same corners relative to the camera, rotated
    n = int(sample["num_walls"])
    gt = np.load(out / "DataPython" / "3D_gt" / f"{name}.npy")
    cam_pose = np.load(out / "DataPython" / "cam_pose" / f"{name}.npy")
    assert gt.shape == (2 * n, 3) and cam_pose.shape == (1, 3)
    pose = sample["pose"].double().numpy()
    A = heading_frame(pose)
    rel = (gt - cam_pose) @ A  # back to world axes
    cw = sample["corners_world"][:n].double().numpy()
    assert np.allclose(rel[:n], cw[:, 0] - pose[:3, 3], atol=1e-4)
    assert np.allclose(rel[n:], cw[:, 1] - pose[:3, 3], atol=1e-4)
    # the dataset's azimuth: column x looks along theta = pi - 2 pi (x + .5) / W in the exported frame
    ang = np.load(out / "DataPython" / "label_ang" / f"{name}.npy")
    rays = cam.unproject_grid(torch.float64)
    d = rays.direction[16].numpy() @ pose[:3, :3].T @ A.T
    assert np.allclose(np.arctan2(d[:, 1], d[:, 0]), np.angle(np.exp(1j * ang[0])), atol=1e-6)
    assert np.allclose(ang[1], np.pi / 2 - np.pi * sample["boundary"][0].double().numpy() / 32, atol=1e-5)
    cor = np.loadtxt(out / "DataPython" / "label_cor" / f"{name}.txt").reshape(-1, 2)
    assert len(cor) % 2 == 0 and np.all(np.diff(cor[::2, 0]) >= 0) and np.all(cor[0::2, 1] < cor[1::2, 1])
    em = cv2.imread(str(out / "EM_gt" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
    assert em.shape == (32, 64) and set(np.unique(em)) <= {0, 255}
    # resume: nothing is rewritten; a deleted file is written again
    stamp = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file() and p.name != "contact_sheet.png"}
    assert main(args[:-2] + ["--contact-sheet", "0"]) == 0
    assert all(p.stat().st_mtime_ns == t for p, t in stamp.items())
    (out / "EM_gt" / f"{name}.png").unlink()
    assert main(args[:-2] + ["--contact-sheet", "0"]) == 0
    assert (out / "EM_gt" / f"{name}.png").exists()


def test_stanford_export_reads_back_through_the_loader(tmp_path):
    from omnidl.data.stanford2d3ds import Stanford2D3DS
    out = tmp_path / "st"
    assert main(["--camera", "equirect", "--n", "2", "--out", str(out), "--width", "64", "--height", "32",
                 "--format", "stanford", "--contact-sheet", "0"]) == 0
    labels = json.loads((out / "assets" / "semantic_labels.json").read_text())
    assert labels[0].startswith("<UNK>") and len(labels) == 14
    ds = Stanford2D3DS(str(out), areas=["1"], height=32, width=64)
    assert len(ds) == 2
    got = ds[0]
    ref = render_sample(resolve_camera("equirect", 64, 32), 0, "train", 0)
    assert torch.equal(got["semantic"], ref["semantic"])
    assert (got["depth"] - ref["depth"]).abs().max() <= 1 / 512
    assert (got["image"] - ref["image"]).abs().max() <= 1 / 255


def test_horizonnet_export(tmp_path):
    out = tmp_path / "hn"
    assert main(["--camera", "equirect", "--n", "1", "--out", str(out), "--width", "64", "--height", "32",
                 "--format", "horizonnet", "--contact-sheet", "0"]) == 0
    cor = np.loadtxt(out / "label_cor" / "synth_00000.txt").reshape(-1, 2)
    sample = render_sample(resolve_camera("equirect", 64, 32), 0, "train", 0)
    n = int(sample["num_walls"])
    ok = sample["corners_valid"][:n].all(-1).numpy()
    uv = sample["corners_uv"][:n].numpy()[ok].reshape(-1, 2) - 0.5
    assert np.allclose(cor, uv, atol=0.01)
    with pytest.raises(SystemExit):
        main(["--camera", "equirect", "--n", "1", "--out", str(out), "--width", "64", "--height", "32",
              "--format", "horizonnet", "--rotation", "random"])


# -- rerunning into an existing --out (issue 14: a second run with another size/seed mixed two datasets) --
def _args(out, *extra, n=1, size=(32, 16), seed=0):
    return ["--camera", "equirect", "--n", str(n), "--out", str(out), "--width", str(size[0]), "--height",
            str(size[1]), "--seed", str(seed), "--format", "horizonnet", "--contact-sheet", "0", *extra]


def _sizes(out):
    return sorted({cv2.imread(str(p)).shape[:2] for p in (out / "img").glob("*.png")})


def test_rerun_with_other_size_or_seed_is_an_error(tmp_path):
    out = tmp_path / "hn"
    assert main(_args(out)) == 0
    manifest = json.loads((out / "synth.json").read_text())["settings"]
    assert manifest["width"] == 32 and manifest["seed"] == 0 and manifest["format"] == "horizonnet"
    with pytest.raises(SystemExit, match=r"other settings \(width: 32 there, 64 now; height: 16 there, 32 now\)"):
        main(_args(out, n=2, size=(64, 32)))
    with pytest.raises(SystemExit, match=r"seed: 0 there, 5 now.*--overwrite"):
        main(_args(out, n=2, seed=5))
    assert _sizes(out) == [(16, 32)] and len(list((out / "img").glob("*.png"))) == 1   # nothing was added


def test_same_settings_extend_and_overwrite_replaces(tmp_path):
    out = tmp_path / "hn"
    assert main(_args(out)) == 0
    assert main(_args(out, n=2)) == 0                       # same settings: resumed and extended
    assert len(list((out / "img").glob("*.png"))) == 2
    assert main(_args(out, "--overwrite", n=1, size=(64, 32), seed=5)) == 0
    assert _sizes(out) == [(32, 64)] and len(list((out / "img").glob("*.png"))) == 1
    assert json.loads((out / "synth.json").read_text())["settings"]["seed"] == 5


def test_samples_without_manifest_are_not_mixed(tmp_path):
    out = tmp_path / "hn"
    assert main(_args(out)) == 0
    (out / "synth.json").unlink()                           # e.g. a dataset written by an older omnidl
    with pytest.raises(SystemExit, match=r"already holds 2 sample files .*synth_00000.* no synth\.json"):
        main(_args(out, n=2))
    (out / "notes.txt").write_text("a folder with unrelated files is fine")
    empty = tmp_path / "other"
    empty.mkdir()
    (empty / "notes.txt").write_text("x")
    assert main(_args(empty)) == 0
