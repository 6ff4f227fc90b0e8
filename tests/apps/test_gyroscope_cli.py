import json
import math

import cv2
import numpy as np
import torch

from omnidl.apps.gyroscope import list_frames, main
from omnidl.geometry.rotations import euler_to_matrix
from omnidl.postprocess.gyroscope.scene import procedural_panorama


def _write(path, img):
    arr = (img.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)[..., ::-1]
    cv2.imwrite(str(path), arr)


def test_cli_over_a_folder_with_bad_frames(tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    yaws = [0.0, 40.0, -120.0]
    for k, y in enumerate(yaws):
        R = euler_to_matrix(torch.tensor(0.0), torch.tensor(0.0), torch.tensor(math.radians(y))).double()
        _write(frames / f"e_{10 * k + 2:06d}.png", procedural_panorama(R[None], 32, 64, seed=7)[0])
    _write(frames / "e_000005.png", torch.zeros(3, 32, 64))          # black
    _write(frames / "e_000007.png", torch.rand(3, 16, 32))           # wrong size
    (frames / "e_000009.png").write_bytes(b"not an image")            # unreadable
    assert [p.name for p in list_frames(frames)][:3] == ["e_000002.png", "e_000005.png", "e_000007.png"]
    out = tmp_path / "out"
    rc = main([str(frames), "--out", str(out), "--assume-upright", "--height", "32", "--pvg-level", "3",
               "--video"])
    assert rc == 0
    res = json.loads((out / "rotations.json").read_text())["frames"]
    status = {r["name"]: r["status"] for r in res}
    assert status == {"e_000002.png": "ok", "e_000005.png": "no_estimate", "e_000007.png": "no_estimate",
                      "e_000009.png": "no_estimate", "e_000012.png": "ok", "e_000022.png": "ok"}
    yaw = {r["name"]: r["yaw"] for r in res if r["status"] == "ok"}
    assert abs(yaw["e_000012.png"] - 40) < 2 and abs(yaw["e_000022.png"] + 120) < 2
    assert (out / "angles.png").stat().st_size > 0 and (out / "rotations.csv").read_text().count("\n") == 7
    assert len(list((out / "stabilised").glob("*.png"))) == 3
    assert len(list((out / "before_after").glob("*.png"))) == 5 + 1  # the unreadable one as an empty panel
    # missing reference: clear error, exit code 2
    assert main([str(frames), "--out", str(out), "--assume-upright", "--reference", "nope.png"]) == 2
    assert main([str(tmp_path / "none"), "--out", str(out), "--assume-upright"]) == 2
    assert main([str(frames), "--out", str(out)]) == 2  # neither checkpoint nor --assume-upright


def test_load_holinet_from_an_engine_checkpoint(tmp_path):
    from omnidl.engine.checkpoint import save_checkpoint
    from omnidl.models import create_model
    from omnidl.apps.gyroscope import load_holinet
    from omnidl.postprocess.gyroscope.pipeline import model_horizon_fn
    kw = dict(backbone="resnet18", width=0.125, conv="standard")
    m = create_model("holinet", **kw)
    cfg = {"camera": {"type": "equirect", "width": 64, "height": 32},
           "model": {"_target_": "omnidl.models.create_model", "name": "holinet", **kw},
           "data": {"height": 32}}
    save_checkpoint(tmp_path / "best.pt", {"model": m.state_dict(), "config": cfg})
    m2, h = load_holinet(tmp_path / "best.pt")
    assert h == 32
    hl, vp = model_horizon_fn(m2, h)(torch.rand(2, 3, 64, 128))
    assert hl.shape == vp.shape == (2, 1, 16, 32) and (hl >= 0).all() and (hl <= 1).all()


def test_checkpoint_of_another_model_is_a_clear_error(tmp_path, capsys):
    """Issue 14: a FreDSNet checkpoint gave KeyError: 'horizon' after the frames were read."""
    import pytest
    from omnidl.apps.gyroscope import load_holinet
    from omnidl.engine.checkpoint import save_checkpoint
    save_checkpoint(tmp_path / "fredsnet.pt", {"model": {"w": torch.zeros(1)},
                                               "config": {"model": {"name": "fredsnet", "width": 0.0625}}})
    with pytest.raises(ValueError, match=r"fredsnet\.pt holds a 'fredsnet' model.*HoLiNet.*--assume-upright"):
        load_holinet(tmp_path / "fredsnet.pt")
    frames = tmp_path / "frames"
    frames.mkdir()
    _write(frames / "e_000000.png", torch.rand(3, 16, 32))
    assert main([str(frames), "--out", str(tmp_path / "out"), "--checkpoint", str(tmp_path / "fredsnet.pt")]) == 2
    assert "holds a 'fredsnet' model" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
