"""``omnidl predict`` never destroys data and keeps point clouds small when asked (issues 48 and 49).

Regression tests of the predict examples of the issues: ``a.png`` + ``a.jpg`` keep one set of outputs each;
``--out`` equal to the input folder never replaces an input named like an output (``x_depth.png``); a second
run never replaces the first's results without ``--overwrite``; a fisheye image is not stretched into a
panorama model (``--camera`` takes it there instead); ``--max-points``/``--voxel`` bound the clouds."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from omnidl.apps.cli import main as omnidl_main
from omnidl.viz import read_ply


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    """A tiny U-Net on 64x32 equirectangular panoramas (depth + semantics), saved as the engine saves it (the
    resolved config's model, data size and camera; no Hydra composition, which is slow)."""
    import torch

    from omnidl.engine.checkpoint import save_checkpoint
    from omnidl.models import create_model
    torch.manual_seed(0)
    kw = {"base_channels": 4, "levels": 1}
    path = tmp_path_factory.mktemp("ckpt") / "unet.pt"
    save_checkpoint(path, {"model": create_model("unet", **kw).state_dict(), "step": 0, "epoch": 0,
                           "config": {"model": {"name": "unet", **kw}, "data": {"height": 32, "width": 64},
                                      "camera": {"type": "equirect", "width": 64, "height": 32}}})
    return path


def _img(path: Path, w: int, h: int, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), rng.integers(0, 255, (h, w, 3), dtype=np.uint8))
    return path


def _depth(ckpt, inp, out, *extra) -> int:
    return omnidl_main(["predict", "depth", str(inp), "--checkpoint", str(ckpt), "--out", str(out),
                        "--upright", "off", *extra])


def test_same_stem_different_extensions_get_distinct_outputs(ckpt, tmp_path):
    _img(tmp_path / "in" / "a.png", 64, 32, 1)
    _img(tmp_path / "in" / "a.jpg", 64, 32, 2)
    _img(tmp_path / "in" / "b.png", 64, 32, 3)
    assert _depth(ckpt, tmp_path / "in", tmp_path / "out") == 0
    names = sorted(p.name for p in (tmp_path / "out").glob("*_depth.npy"))
    assert names == ["a_jpg_depth.npy", "a_png_depth.npy", "b_depth.npy"]
    assert not np.array_equal(np.load(tmp_path / "out" / "a_png_depth.npy"),
                              np.load(tmp_path / "out" / "a_jpg_depth.npy"))


def test_out_equal_to_the_input_folder_never_replaces_an_input(ckpt, tmp_path, capsys):
    folder = tmp_path / "scans"
    _img(folder / "x.png", 64, 32, 1)
    gt = _img(folder / "x_depth.png", 64, 32, 9)                 # e.g. a ground-truth depth named like an output
    before = gt.read_bytes()
    for extra in ((), ("--overwrite",)):
        assert _depth(ckpt, folder, folder, *extra) == 2
        err = capsys.readouterr().err
        assert "x_depth.png" in err and "never overwritten" in err, err
        assert gt.read_bytes() == before
    assert sorted(p.name for p in folder.iterdir()) == ["x.png", "x_depth.png"]   # nothing written at all


def test_previous_results_need_overwrite(ckpt, tmp_path, capsys):
    _img(tmp_path / "p.png", 64, 32)
    assert _depth(ckpt, tmp_path / "p.png", tmp_path / "out") == 0
    first = (tmp_path / "out" / "p_depth.npy").read_bytes()
    assert _depth(ckpt, tmp_path / "p.png", tmp_path / "out") == 2
    err = capsys.readouterr().err
    assert "p_depth.npy already exists" in err and "add --overwrite" in err
    assert _depth(ckpt, tmp_path / "p.png", tmp_path / "out", "--overwrite") == 0
    assert (tmp_path / "out" / "p_depth.npy").read_bytes() == first
    assert not [p for p in (tmp_path / "out").iterdir() if p.name.startswith(".")]   # no temp or lock left


def test_a_fisheye_image_is_refused_then_taken_through_its_camera(ckpt, tmp_path, capsys):
    img = _img(tmp_path / "fish.png", 108, 96)
    assert _depth(ckpt, img, tmp_path / "o1") == 1                    # refused, not stretched into 64x32
    err = capsys.readouterr().err
    assert "108x96" in err and "64x32" in err and "--camera" in err
    assert not list((tmp_path / "o1").glob("fish*"))
    assert _depth(ckpt, img, tmp_path / "o2", "--camera", "kb_f195") == 0
    out = capsys.readouterr().out
    assert "% masked" in out
    doc = json.loads((tmp_path / "o2" / "fish_predict.json").read_text())
    assert doc["camera"]["input_camera"]["type"] == "resized" and doc["camera"]["coverage"]["input_valid_pixels"] > 0
    d = np.load(tmp_path / "o2" / "fish_depth.npy")
    assert d.shape == (96, 108) and np.isfinite(d).mean() > 0.5
    assert (tmp_path / "o2" / "fish_valid.png").is_file()


def test_a_sidecar_camera_is_used(ckpt, tmp_path, capsys):
    from omnidl.cameras import resolve_camera, save
    img = _img(tmp_path / "in" / "shot.png", 108, 96)
    save(resolve_camera("kb_f195"), tmp_path / "in" / "shot.camera.yaml")
    assert _depth(ckpt, img, tmp_path / "out") == 0
    assert "sidecar camera file" in capsys.readouterr().out
    assert json.loads((tmp_path / "out" / "shot_predict.json").read_text())["camera"] is not None


def test_max_points_and_voxel_bound_the_cloud_deterministically(ckpt, tmp_path):
    img = _img(tmp_path / "r.png", 256, 128)
    assert _depth(ckpt, img, tmp_path / "all") == 0
    n_all = len(read_ply(tmp_path / "all" / "r.ply")[0])
    assert n_all > 0.9 * 256 * 128                                     # the default keeps every valid pixel
    assert _depth(ckpt, img, tmp_path / "few", "--max-points", "500") == 0
    assert _depth(ckpt, img, tmp_path / "few2", "--max-points", "500") == 0
    assert len(read_ply(tmp_path / "few" / "r.ply")[0]) == 500
    assert (tmp_path / "few" / "r.ply").read_bytes() == (tmp_path / "few2" / "r.ply").read_bytes()
    assert _depth(ckpt, img, tmp_path / "vox", "--voxel", "0.5") == 0
    n_vox = len(read_ply(tmp_path / "vox" / "r.ply")[0])
    assert 0 < n_vox < n_all
    doc = json.loads((tmp_path / "vox" / "r_predict.json").read_text())["point_cloud"]
    assert doc["points"] == n_vox and doc["voxel_m"] == 0.5 and doc["valid_pixels"] == n_all


def test_bad_cloud_options_are_refused(ckpt, tmp_path, capsys):
    img = _img(tmp_path / "r.png", 64, 32)
    assert _depth(ckpt, img, tmp_path / "o", "--max-points", "-3") == 2
    assert "--max-points must be" in capsys.readouterr().err
    assert _depth(ckpt, img, tmp_path / "o", "--voxel", "nan") == 2
    assert "--voxel must be" in capsys.readouterr().err


@pytest.mark.slow
def test_a_4096x2048_panorama_writes_a_small_cloud(ckpt, tmp_path):
    img = _img(tmp_path / "big.png", 4096, 2048)
    assert _depth(ckpt, img, tmp_path / "out", "--max-points", "20000") == 0
    ply = tmp_path / "out" / "big.ply"
    assert len(read_ply(ply)[0]) == 20000 and ply.stat().st_size < 1_000_000


# -- property: generated file names never lose a byte ----------------------------------------------------------------

from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_STEMS = st.sampled_from(["a", "A", "a_depth", "x", "x_depth", "a_png", "room 1", "é", "a.b"])
_EXTS = st.sampled_from([".png", ".jpg", ".PNG", ".jpeg", ".tif"])


@settings(max_examples=50, deadline=None, derandomize=True)
@given(files=st.lists(st.tuples(_STEMS, _EXTS), min_size=1, max_size=7, unique_by=lambda t: (t[0] + t[1]).casefold()))
def test_generated_names_give_distinct_outputs_that_never_replace_an_input(files):
    """For any folder of images (colliding stems, case variants, names like outputs): the planned outputs of
    ``predict depth`` are pairwise distinct (case-insensitively), and with ``--out`` = the input folder the run is
    refused exactly when an output would land on an existing file (with or without ``--overwrite``)."""
    import os
    import tempfile

    from omnidl.apps.predict.inputs import planned_items
    from omnidl.apps.predict.run import depth_outputs
    from omnidl.utils.outputs import OutputIsInputError, guard_outputs
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for stem, ext in files:
            (folder / f"{stem}{ext}").write_bytes(b"\x89PNG fake")
        items = planned_items(folder)
        assert len({n.casefold() for n, _ in items}) == len(items) == len(files)
        planned = [p for n, _ in items for p in depth_outputs(folder, n, True, True, False)]
        keys = [os.path.normcase(p.name).casefold() for p in planned]
        assert len(set(keys)) == len(keys)
        existing = {p.name for p in folder.iterdir()}               # this file system tells case apart
        clash = any(p.name in existing for p in planned)
        for overwrite in (False, True):
            if clash:
                with pytest.raises(OutputIsInputError):
                    guard_outputs(planned, [folder], overwrite=overwrite)
            else:
                guard_outputs(planned, [folder], overwrite=overwrite)


def test_file_names_of_any_bytes(tmp_path, ckpt):
    """An image whose name is not valid UTF-8 (as some file systems hold) is predicted like any other: OpenCV's
    binding crashed the interpreter on such a name (exit 139), so it runs in a subprocess."""
    import os
    import subprocess
    import sys
    folder = tmp_path / "in"
    folder.mkdir()
    ok, buf = cv2.imencode(".png", np.random.default_rng(0).integers(0, 255, (32, 64, 3), dtype=np.uint8))
    assert ok
    with open(os.path.join(os.fsencode(folder), b"pano_\xff\xfe.png"), "wb") as f:
        f.write(buf.tobytes())
    out = tmp_path / "out"
    res = subprocess.run([sys.executable, "-m", "omnidl.apps.cli", "predict", "depth", str(folder), "--checkpoint",
                          str(ckpt), "--out", str(out), "--no-ply"], capture_output=True, text=True, errors="replace", timeout=300,
                         env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert res.returncode == 0, res.stderr[-2000:]
    assert len(list(out.glob("*_depth.npy"))) == 1
