"""The ``omnidl`` console script (omnidl/apps/cli.py): every subcommand is listed and dispatched; ``omnidl calib
convert|show`` (omnidl/apps/calib.py) and ``omnidl export`` (omnidl/apps/export.py) end to end."""
from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from omnidl.apps import calib
from omnidl.apps.cli import COMMANDS, main
from omnidl.cameras import build, io, resolve_camera

sys.path.insert(0, str(Path(__file__).resolve().parent))

ALL = ("train", "evaluate", "predict", "export", "synth", "reproject", "calib", "report")


def test_help_lists_every_subcommand(capsys):
    assert main(["-h"]) == 0
    out = capsys.readouterr().out
    assert tuple(COMMANDS) == ALL
    for cmd in ALL:
        assert f"\n  {cmd} " in out, cmd
    assert main([]) == 2


def test_unknown_command_names_it(capsys):
    assert main(["trian"]) == 2
    err = capsys.readouterr().err
    assert "unknown command 'trian'" in err and "calib" in err


@pytest.mark.parametrize("cmd", [c for c in ALL if c not in ("train", "evaluate")])
def test_every_argparse_subcommand_has_help(cmd, capsys):
    with pytest.raises(SystemExit) as e:
        main([cmd, "-h"])
    assert e.value.code == 0
    assert "usage:" in capsys.readouterr().out


def test_hydra_subcommands_dispatch_to_the_apps(monkeypatch):
    """``omnidl train|evaluate ARGS`` run the Hydra apps with ``sys.argv = ['omnidl <cmd>', *ARGS]``."""
    from omnidl.apps import evaluate, train
    seen = {}
    for mod in (train, evaluate):
        monkeypatch.setattr(mod, "_run", lambda mod=mod: seen.setdefault(mod.__name__, list(sys.argv)))
    monkeypatch.setattr(sys, "argv", ["omnidl"])
    assert main(["train", "model=fredsnet", "trainer=debug"]) == 0
    assert main(["evaluate", "model=fredsnet", "checkpoint=x.pt"]) == 0
    assert seen["omnidl.apps.train"] == ["omnidl train", "model=fredsnet", "trainer=debug"]
    assert seen["omnidl.apps.evaluate"] == ["omnidl evaluate", "model=fredsnet", "checkpoint=x.pt"]


# ----------------------------------------------------------------------------------------------- calib

#: a radial-tangential lens every format with an OpenCV model holds (COLMAP OPENCV, Kalibr pinhole-radtan)
RADTAN = {"type": "opencv", "width": 64, "height": 48, "fx": 40.0, "fy": 40.5, "cx": 32.3, "cy": 23.8,
          "k1": -0.2, "k2": 0.05, "p1": 0.0015, "p2": -0.002}


def test_calib_convert_round_trips_and_never_overwrites(tmp_path, capsys):
    src = tmp_path / "kb.yaml"
    cam = build(RADTAN)
    io.save(cam, src, format="omnidl")
    out = tmp_path / "cameras.txt"
    assert main(["calib", "convert", str(src), str(out), "--to", "colmap"]) == 0
    assert "validity identical" in capsys.readouterr().out
    assert io.detect_format(out) == "colmap"
    diff, changed = calib.round_trip_px(cam, io.load(out))
    assert diff < 1e-9 and changed == 0
    before = out.read_bytes()
    assert main(["calib", "convert", str(src), str(out), "--to", "colmap"]) == 2
    assert "exists: pass --overwrite" in capsys.readouterr().err and out.read_bytes() == before
    assert main(["calib", "convert", str(src), str(src), "--to", "omnidl", "--overwrite"]) == 2
    assert "is the input" in capsys.readouterr().err
    assert main(["calib", "convert", str(src), str(out), "--to", "kalibr", "--overwrite"]) == 0
    assert io.detect_format(out) == "kalibr"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cameras.txt", "kb.yaml"]  # no temp file left


def test_calib_convert_refuses_a_format_that_narrows_the_lens(tmp_path, capsys):
    """A 195 degree Kannala-Brandt lens into COLMAP (whose reader caps the field of view at 180 degrees) is
    refused, by the writer or by convert's read-back check, and nothing is written (issue 48: lossless or
    refused)."""
    src = tmp_path / "f195.yaml"
    io.save(resolve_camera("kb_f195"), src, format="omnidl")
    out = tmp_path / "cameras.txt"
    assert main(["calib", "convert", str(src), str(out), "--to", "colmap"]) == 2
    err = capsys.readouterr().err
    assert "colmap" in err and ("does not reproduce" in err or "cannot" in err), err
    assert not out.exists() and not list(tmp_path.glob(".*part*"))


def test_calib_convert_refuses_a_model_the_format_cannot_hold(tmp_path, capsys):
    src = tmp_path / "pano.yaml"
    io.save(build({"type": "noncentral_pano", "width": 64, "height": 32}), src, format="omnidl")
    assert main(["calib", "convert", str(src), str(tmp_path / "c.txt"), "--to", "colmap"]) == 2
    assert "colmap" in capsys.readouterr().err and not (tmp_path / "c.txt").exists()


def test_calib_show_a_preset_with_its_picture(tmp_path, capsys):
    png = tmp_path / "f195.png"
    assert main(["calib", "show", "kb_f195", "--out", str(png)]) == 0
    out = capsys.readouterr().out
    assert "kannala_brandt" in out and "1080 x 960" in out and "195.00 deg" in out
    img = cv2.imread(str(png))
    assert img.shape == (480, 540, 3)  # analysed on every 2nd pixel (at most 1024 on the long side)
    red = (img[..., 2] > 200) & (img[..., 1] < 50) & (img[..., 0] < 50)
    assert red.any() and not red[0, 230:310].any()  # the image circle is drawn; where it is cut by the
    assert (img[0, 270] == 150).all()                   # frame (top centre), the frame is no boundary
    assert (img.reshape(-1, 3) == 0).all(-1).any()  # invalid corners are black
    assert main(["calib", "show", "kb_f195", "--out", str(png)]) == 2
    assert "exists" in capsys.readouterr().err


def test_describe_numbers():
    eq = calib.describe(build({"type": "equirect", "width": 64, "height": 32}))
    assert eq["valid_fraction"] == 1.0 and eq["fov_h_deg"] == pytest.approx(360 * 63 / 64)
    assert eq["fov_v_deg"] == pytest.approx(180 * 31 / 32) and eq["reprojection_px"] < 1e-9
    pin = calib.describe(build({"type": "pinhole", "width": 64, "height": 64, "fx": 32.0, "fy": 32.0,
                                "cx": 32.0, "cy": 32.0}))
    half = np.degrees(np.arctan(31.5 / 32))  # the outermost pixel centres of a 90 degree pinhole
    assert pin["fov_h_deg"] == pytest.approx(2 * half) and pin["valid_fraction"] == 1.0


def test_calib_show_reports_a_missing_file(tmp_path, capsys):
    assert main(["calib", "show", str(tmp_path / "none.yaml")]) == 2
    assert "none.yaml" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------- export

@pytest.fixture(scope="module")
def unet_ckpt(tmp_path_factory):
    from test_predict_helpers import tiny_checkpoint
    return tiny_checkpoint(tmp_path_factory.mktemp("export") / "unet.pt", "unet")


@pytest.mark.slow
def test_export_pt2_matches_eager_and_never_overwrites(unet_ckpt, tmp_path, capsys):
    out = tmp_path / "unet.pt2"
    assert main(["export", str(unet_ckpt), str(out)]) == 0
    printed = capsys.readouterr().out
    assert "(1, 3, 32, 64)" in printed and "max |exported - eager|" in printed
    prog = torch.export.load(str(out)).module()
    x = torch.rand(1, 3, 32, 64)
    from omnidl.apps.predict.loader import load_predictor
    ref = load_predictor(unet_ckpt).model(x)
    got = prog(x)
    for k in ref:
        torch.testing.assert_close(got[k], ref[k], atol=1e-5, rtol=1e-5)
    before = out.stat().st_mtime_ns
    assert main(["export", str(unet_ckpt), str(out)]) == 2
    assert "--overwrite" in capsys.readouterr().err and out.stat().st_mtime_ns == before
    assert main(["export", str(unet_ckpt), str(unet_ckpt), "--format", "pt2", "--overwrite"]) == 2
    assert "checkpoint itself" in capsys.readouterr().err
    assert main(["export", str(unet_ckpt), str(tmp_path / "x.bin")]) == 2
    assert "--format" in capsys.readouterr().err


@pytest.mark.slow
def test_export_onnx_matches_eager(unet_ckpt, tmp_path, capsys):
    pytest.importorskip("onnxscript")
    pytest.importorskip("onnxruntime")
    out = tmp_path / "unet.onnx"
    assert main(["export", str(unet_ckpt), str(out)]) == 0
    assert "max |exported - eager|" in capsys.readouterr().out and out.stat().st_size > 0
