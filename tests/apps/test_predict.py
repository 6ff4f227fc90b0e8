"""Fast checks of ``omnidl predict``'s parts: argument errors, the loader, the y-up OBJ, the H.264 writer."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from omnidl.apps.cli import main as omnidl_main
from omnidl.apps.predict.inputs import kind_of
from omnidl.apps.predict.loader import load_predictor
from omnidl.apps.predict.run import layout_in_input_frame, layout_obj_y_up
from omnidl.apps.predict.video import H264Writer, backend


def test_cli_errors_name_the_problem(tmp_path, capsys):
    assert omnidl_main([]) == 2
    assert omnidl_main(["frobnicate"]) == 2
    assert "unknown command 'frobnicate'" in capsys.readouterr().err
    img = tmp_path / "a.png"
    import cv2
    cv2.imwrite(str(img), np.zeros((8, 16, 3), np.uint8))
    assert omnidl_main(["predict", "depth", str(img), "--out", str(tmp_path / "o")]) == 2
    assert "needs --checkpoint" in capsys.readouterr().err
    assert omnidl_main(["predict", "depth", str(tmp_path / "nope.png"), "--checkpoint", "x", "--out", "o"]) == 2
    assert "nope.png: no such file" in capsys.readouterr().err
    (tmp_path / "a.txt").write_text("x")
    with pytest.raises(ValueError, match="unknown extension '.txt'"):
        kind_of(tmp_path / "a.txt")


def test_loader_rejects_files_without_a_config(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such file"):
        load_predictor(tmp_path / "missing.pt")
    torch.save({"model": {"w": torch.zeros(1)}}, tmp_path / "bare.pt")
    with pytest.raises(ValueError, match="no 'config' with a 'model' entry"):
        load_predictor(tmp_path / "bare.pt")
    (tmp_path / "junk.pt").write_bytes(b"not torch")
    with pytest.raises(RuntimeError, match="not a readable torch file"):
        load_predictor(tmp_path / "junk.pt")


def test_layout_frames():
    corners = [[2.0, 1.0], [-2.0, 1.0], [-2.0, -1.0], [2.0, -1.0]]
    lay = {"ok": True, "corners_2d": corners,
           "ceiling_corners": [[x, y, 1.2] for x, y in corners], "floor_corners": [[x, y, -1.5] for x, y in corners]}
    fl, ce = layout_in_input_frame(lay, None)
    # layout frame (x_w, y_w, z_w) = (x_c, z_c, -y_c): the floor is below (camera +y)
    assert np.allclose(fl[0], [2.0, 1.5, 1.0]) and np.allclose(ce[0], [2.0, -1.2, 1.0])
    R = torch.tensor([[1.0, 0, 0], [0, 0.8, -0.6], [0, 0.6, 0.8]], dtype=torch.float64)  # camera -> upright
    fl_t, _ = layout_in_input_frame(lay, R)
    assert np.allclose(fl_t @ R.numpy().T, fl)
    obj = layout_obj_y_up(lay).splitlines()
    v = np.array([[float(t) for t in line.split()[1:]] for line in obj if line.startswith("v ")])
    assert v.shape == (8, 3) and np.allclose(v[:4, 1], 1.2) and np.allclose(v[4:, 1], -1.5)   # y up
    assert np.allclose(v[0], [2.0, 1.2, -1.0])                                                 # forward = -z
    assert layout_obj_y_up({"ok": False, "reason": "no corners"}).startswith("# no layout: no corners")


@pytest.mark.skipif(backend() is None, reason="needs imageio-ffmpeg or PyAV (the video extra)")
def test_h264_writer(tmp_path):
    with H264Writer(tmp_path / "v.mp4", fps=4) as w:
        for k in range(3):
            w.write(np.full((33, 65, 3), 40 * k, np.uint8))        # odd sizes are cropped to even
    assert (tmp_path / "v.mp4").stat().st_size > 0 and not list(tmp_path.glob(".*"))
    with pytest.raises(ValueError, match="video frame is"):
        with H264Writer(tmp_path / "w.mp4") as w:
            w.write(np.zeros((8, 8, 3), np.uint8))
            w.write(np.zeros((16, 8, 3), np.uint8))


@pytest.mark.slow
def test_loader_takes_official_horizonnet_and_converted_fredsnet_files(tmp_path):
    """The two official-weight formats of docs/model_zoo.md load without a config (tiny stand-ins here)."""
    from omnidl.models import create_model
    from omnidl.models.horizonnet import HorizonNet
    from tests.models.test_horizonnet import _official_from
    torch.manual_seed(0)
    hn = HorizonNet(backbone="resnet18", hidden=16, rnn=True)
    torch.save({"args": {}, "kwargs": {"backbone": "resnet18", "use_rnn": True}, "state_dict": _official_from(hn)},
               tmp_path / "resnet18_rnn__st3d.pth")
    pred = load_predictor(tmp_path / "resnet18_rnn__st3d.pth")
    assert pred.name == "horizonnet" and (pred.width, pred.height) == (1024, 512)
    assert {"boundary", "corner"} <= pred.outputs and "official" in pred.source
    kwargs = dict(backbone="resnet18", width=0.0625, head_width=64, semantic_bn_relu=True)
    fd = create_model("fredsnet", **kwargs)
    torch.save({"model_kwargs": kwargs, "state_dict": fd.state_dict(), "official_args": {}}, tmp_path / "fd.pth")
    pred = load_predictor(tmp_path / "fd.pth")
    assert pred.name == "fredsnet" and (pred.width, pred.height) == (512, 256) and "depth" in pred.outputs
    out = pred(torch.rand(3, 100, 200))                 # any input size: resized to the network's
    assert out["depth"].shape == (1, 1, 256, 512)
