"""The reproject CLI (``python -m omnidl.apps.reproject``): output matches the library call, clear errors for
bad inputs."""
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

from tests.geometry.geom_helpers import render
from omnidl.cameras import Equirectangular, build
from omnidl.geometry import euler_to_matrix, reproject
from omnidl.apps.reproject import main

ROOT = Path(__file__).resolve().parents[2]


def write_inputs(tmp_path):
    pano = render(Equirectangular(width=64, height=32))[0, 0].numpy()
    img = np.stack([pano, 255 - pano, 0.5 * pano], -1).round().astype(np.uint8)
    cv2.imwrite(str(tmp_path / "pano.png"), img)
    (tmp_path / "pin.yaml").write_text("_target_: omnidl.cameras.build\ntype: pinhole\nwidth: 20\nheight: 16\n"
                                       "fx: 10.0\nfy: 10.0\ncx: 10.0\ncy: 8.0\n")
    return img


def test_cli_matches_library(tmp_path, capsys):
    img = write_inputs(tmp_path)
    rc = main(["--src", str(tmp_path / "pano.png"), "--dst-camera", str(tmp_path / "pin.yaml"),
               "--out", str(tmp_path / "out.png"), "--rotation", "5,20,-30", "--mask-out", str(tmp_path / "m.png")])
    assert rc == 0 and "wrote" in capsys.readouterr().out
    out = cv2.imread(str(tmp_path / "out.png"), cv2.IMREAD_UNCHANGED)
    assert out.shape == (16, 20, 3) and out.dtype == np.uint8
    cam = build(type="pinhole", width=20, height=16, fx=10.0, fy=10.0, cx=10.0, cy=8.0)
    R = euler_to_matrix(*[torch.tensor(np.radians(v), dtype=torch.float64) for v in (5, 20, -30)])
    ref, _ = reproject(torch.from_numpy(img).permute(2, 0, 1)[None].float(), Equirectangular(width=64, height=32),
                       cam, R)
    ref = ref[0].permute(1, 2, 0).round().clamp(0, 255).numpy().astype(np.uint8)
    assert np.abs(out.astype(int) - ref.astype(int)).max() <= 1
    assert (cv2.imread(str(tmp_path / "m.png"), cv2.IMREAD_UNCHANGED) == 255).all()


def test_cli_nearest_and_module_entry_point(tmp_path):
    write_inputs(tmp_path)
    res = subprocess.run([sys.executable, "-m", "omnidl.apps.reproject", "--src", str(tmp_path / "pano.png"),
                          "--dst-camera", str(tmp_path / "pin.yaml"), "--out", str(tmp_path / "o.png"),
                          "--mode", "nearest"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert cv2.imread(str(tmp_path / "o.png")).shape == (16, 20, 3)


def test_cli_errors(tmp_path, capsys):
    write_inputs(tmp_path)
    base = ["--dst-camera", str(tmp_path / "pin.yaml"), "--out", str(tmp_path / "o.png")]
    assert main(["--src", str(tmp_path / "missing.png")] + base) == 2
    assert "missing.png" in capsys.readouterr().err
    (tmp_path / "bad.yaml").write_text("type: pinhole\nwidth: 8\nheight: 8\nfocal: 3\n")
    assert main(["--src", str(tmp_path / "pano.png"), "--dst-camera", str(tmp_path / "bad.yaml"),
                 "--out", str(tmp_path / "o.png")]) == 2
    err = capsys.readouterr().err
    assert "bad.yaml" in err and "focal" in err
    (tmp_path / "broken.yaml").write_text("type: [unclosed\n")
    assert main(["--src", str(tmp_path / "pano.png"), "--dst-camera", str(tmp_path / "broken.yaml"),
                 "--out", str(tmp_path / "o.png")]) == 2
    assert "broken.yaml" in capsys.readouterr().err
    assert main(["--src", str(tmp_path / "pano.png"), "--rotation", "1,2"] + base) == 2
    assert "roll,pitch,yaw" in capsys.readouterr().err
    assert main(["--src", str(tmp_path / "pano.png"), "--src-camera", str(tmp_path / "pin.yaml")] + base) == 2
    assert "64x32" in capsys.readouterr().err
    assert not (tmp_path / "o.png").exists()


def test_cli_cameras_from_calibration_files_and_config_names(tmp_path, capsys):
    """``--src-camera``/``--dst-camera`` take every spec resolve_camera takes: calibration files, config names."""
    from omnidl.apps.reproject import load_camera
    from omnidl.cameras import resolve_camera
    write_inputs(tmp_path)
    kb = tmp_path / "fisheye_calibration.txt"          # KB text: cx cy fx fy W H FOV k1..k4
    kb.write_text("20 16 12 12 40 32 190 0 0 0 0\n")
    assert main(["--src", str(tmp_path / "pano.png"), "--dst-camera", str(kb), "--out", str(tmp_path / "kb.png")]) == 0
    assert cv2.imread(str(tmp_path / "kb.png")).shape == (32, 40, 3)
    assert load_camera("kb_f195") == resolve_camera("kb_f195")
    # a source camera given by config name, calibrated at another size than the image: uniform resize is fine,
    # a 2:1 panorama under a 1080x960 calibration is an error naming both sizes unless a policy says otherwise
    assert load_camera("equirect", 64, 32).size == (64, 32)
    rc = main(["--src", str(tmp_path / "pano.png"), "--src-camera", "kb_f195", "--dst-camera", str(kb),
               "--out", str(tmp_path / "o.png")])
    assert rc == 2 and not (tmp_path / "o.png").exists()
    err = capsys.readouterr().err
    assert "kb_f195" in err and "64x32" in err and "1080x960" in err and "size_policy" in err
    assert load_camera("kb_f195", 64, 32, "pad").size == (64, 32)


def test_out_equal_to_src_never_replaces_the_source(tmp_path, capsys):
    """issue 48: `reproject --out` equal to `--src` replaced the source."""
    write_inputs(tmp_path)
    src = tmp_path / "pano.png"
    before = src.read_bytes()
    for extra in ([], ["--overwrite"]):
        rc = main(["--src", str(src), "--dst-camera", str(tmp_path / "pin.yaml"), "--out", str(src), *extra])
        assert rc == 2 and "is the input file" in capsys.readouterr().err
    assert src.read_bytes() == before


def test_an_existing_output_is_replaced_only_with_overwrite(tmp_path, capsys):
    write_inputs(tmp_path)
    out = tmp_path / "old.png"
    out.write_bytes(b"previous result")
    argv = ["--src", str(tmp_path / "pano.png"), "--dst-camera", str(tmp_path / "pin.yaml"), "--out", str(out)]
    assert main(argv) == 2 and "already exists" in capsys.readouterr().err and out.read_bytes() == b"previous result"
    assert main(argv + ["--overwrite"]) == 0 and cv2.imread(str(out)).shape == (16, 20, 3)
    argv = ["--src", str(tmp_path / "pano.png"), "--dst-camera", str(tmp_path / "pin.yaml"), "--out",
            str(tmp_path / "n.png"), "--mask-out", str(tmp_path / "N.png")]
    assert main(argv) == 2 and "two outputs are the same file" in capsys.readouterr().err
