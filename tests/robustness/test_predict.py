"""Bad inputs of ``omnidl predict`` and its parts (inputs, checkpoints, upright, viz writers): each row's verdict."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from omnidl.apps.predict.inputs import iter_inputs
from omnidl.apps.predict.loader import load_predictor
from omnidl.apps.predict.run import predict_upright
from omnidl.geometry.upright import estimate_upright
from omnidl.viz import depth_to_points, read_depth_png16, write_depth_png16, write_semantic_png

from .verdicts import ERROR, OK, SKIP, expect, row


def _png(path, arr):
    import cv2
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), arr)
    return path


def _input_case(kind, tmp):
    if kind == "missing":
        return tmp / "nope.png"
    if kind == "bad_extension":
        (tmp / "notes.txt").write_text("x")
        return tmp / "notes.txt"
    if kind == "empty_folder":
        (tmp / "empty").mkdir()
        return tmp / "empty"
    if kind == "corrupt_single":
        (tmp / "broken.png").write_bytes(b"\x89PNG not really")
        return tmp / "broken.png"
    if kind == "corrupt_in_folder":
        _png(tmp / "f" / "a.png", np.zeros((8, 16, 3), np.uint8))
        (tmp / "f" / "b.png").write_bytes(b"junk")
        return tmp / "f"
    if kind == "garbage_video":
        (tmp / "clip.mp4").write_bytes(b"not a video")
        return tmp / "clip.mp4"
    if kind == "gray16":
        return _png(tmp / "g.png", np.full((8, 16), 65535, np.uint16))
    if kind == "rgba":
        return _png(tmp / "rgba.png", np.full((8, 16, 4), 255, np.uint8))
    raise AssertionError(kind)


INPUTS = [
    row("missing input", "missing", verdict=ERROR, match=r"nope\.png: no such file"),
    row("unknown extension", "bad_extension", verdict=ERROR, match=r"notes\.txt: unknown extension '\.txt'"),
    row("empty folder", "empty_folder", verdict=ERROR, match=r"empty holds no images"),
    row("corrupt single image", "corrupt_single", verdict=ERROR, match=r"cannot decode image .*broken\.png \(INPUT: truncated or not an image"),
    row("corrupt image in a folder", "corrupt_in_folder", verdict=SKIP, match=r"cannot decode image .*b\.png \(INPUT: truncated or not an image\?\); skipped"),
    row("video OpenCV cannot read", "garbage_video", verdict=ERROR, match=r"clip\.mp4: (cannot open video .*clip\.mp4 \(OpenCV cannot decode it\)|the video has no)"),
    row("16-bit grey image", "gray16", verdict=OK),
    row("RGBA image", "rgba", verdict=OK),
]


@pytest.mark.parametrize("kind,verdict,match", INPUTS)
def test_inputs(kind, verdict, match, tmp_path):
    path = _input_case(kind, tmp_path)
    out = expect(lambda: list(iter_inputs(path)), verdict, match)
    if kind == "corrupt_in_folder":
        assert [n for n, im in out] == ["a", "b"] and out[1][1] is None
    elif verdict == OK:
        (name, img), = out
        assert img.shape == (3, 8, 16) and torch.allclose(img, torch.ones_like(img))


def _ckpt_case(kind, tmp):
    p = tmp / "ck.pt"
    if kind == "missing":
        return tmp / "missing.pt"
    if kind == "not_torch":
        p.write_bytes(b"hello")
    elif kind == "bare_state_dict":
        torch.save({"model": {"w": torch.zeros(1)}}, p)
    elif kind == "no_model_name":
        torch.save({"model": {}, "config": {"model": {"backbone": "resnet18"}}}, p)
    elif kind == "no_size":
        from omnidl.models import create_model
        m = create_model("unet", base_channels=4, levels=2)
        torch.save({"model": m.state_dict(), "config": {"model": {"name": "unet", "base_channels": 4, "levels": 2}}}, p)
    return p


CHECKPOINTS = [
    row("checkpoint missing", "missing", verdict=ERROR, match=r"missing\.pt: no such file"),
    row("not a torch file", "not_torch", verdict=ERROR, match=r"ck\.pt: not a readable torch file"),
    row("bare state dict", "bare_state_dict", verdict=ERROR, match=r"ck\.pt: no 'config' with a 'model' entry"),
    row("config.model without name", "no_model_name", verdict=ERROR, match=r"ck\.pt: config\.model has no 'name'"),
    row("config without input size", "no_size", verdict=ERROR, match=r"ck\.pt: config has neither data\.height/width"),
]


@pytest.mark.parametrize("kind,verdict,match", CHECKPOINTS)
def test_checkpoints(kind, verdict, match, tmp_path):
    expect(lambda: load_predictor(_ckpt_case(kind, tmp_path)), verdict, match)


def _nan_pano():
    x = torch.zeros(3, 64, 128)
    x[1, 3, 4] = float("nan")
    return x


UPRIGHT = [
    row("not 2:1", lambda: estimate_upright(torch.zeros(3, 64, 100)), verdict=ERROR, match=r"W = 2H.*100x64"),
    row("four channels", lambda: estimate_upright(torch.zeros(4, 64, 128)), verdict=ERROR, match=r"\(3, H, W\).*\(4, 64, 128\)"),
    row("NaN pixel", lambda: estimate_upright(_nan_pano()), verdict=ERROR, match="non-finite"),
    row("featureless panorama", lambda: estimate_upright(torch.full((3, 128, 256), 0.3)), verdict=OK),
]


@pytest.mark.parametrize("fn,verdict,match", UPRIGHT)
def test_upright(fn, verdict, match):
    est = expect(fn, verdict, match)
    if verdict == OK:
        assert not est.ok and "line segments" in est.reason


def test_predict_upright_rows(tmp_path):
    expect(lambda: predict_upright("x", torch.zeros(3, 64, 100), tmp_path), ERROR, r"predict upright x: .*100x64")
    files = expect(lambda: predict_upright("flat", torch.full((3, 64, 128), 0.5), tmp_path), OK, None)
    assert all(f.exists() for f in files)                      # written, with the reason in the JSON
    assert "line segments" in (tmp_path / "flat_upright.json").read_text()


VIZ = [
    row("semantic id 300", lambda p: write_semantic_png(p / "s.png", torch.full((2, 2), 300)), verdict=ERROR,
        match=r"class ids must be in \[0, 255\], got \[300, 300\]"),
    row("depth PNG without its scale", lambda p: read_depth_png16(
        (write_depth_png16(p / "d.png", torch.ones(2, 2))[0].with_suffix(".json").unlink(), p / "d.png")[1]),
        verdict=ERROR, match=r"d\.png: its scale file d\.json is missing"),
    row("non-positive scale", lambda p: write_depth_png16(p / "d.png", torch.ones(2, 2), scale=0.0), verdict=ERROR,
        match=r"scale must be > 0 metres per unit, got 0\.0"),
    row("unknown PLY frame", lambda p: depth_to_points(torch.ones(1, 4, 8), None, frame="z_up"), verdict=ERROR,
        match=r"frame must be one of \['camera', 'gravity_y_up'\], got 'z_up'"),
    row("all-invalid depth", lambda p: write_depth_png16(p / "z.png", torch.full((2, 2), float("nan"))), verdict=OK),
]


@pytest.mark.parametrize("fn,verdict,match", VIZ)
def test_viz_writers(fn, verdict, match, tmp_path):
    out = expect(lambda: fn(tmp_path), verdict, match)
    if verdict == OK:
        assert read_depth_png16(out[0]).max() == 0


# -- `omnidl predict --camera`, the no-stretch rule and the cloud options (issue 49) ------------------------------

def _oracle(h=32, w=64, camera=None):
    from omnidl.apps.predict.loader import Predictor

    class Net(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.zeros(1))

        def forward(self, x):
            return {"depth": torch.full((1, 1, h, w), 2.0) + 0 * self.w}
    return Predictor(Net(), "oracle", h, w, camera, "test", info={"outputs": ("depth",)})


def _camera_case(kind, tmp):
    from omnidl.apps.predict.camera import CameraBridge, input_camera
    from omnidl.apps.predict.points import CloudOptions
    from omnidl.apps.predict.run import UprightPolicy, check_input_size, predict_depth
    from omnidl.cameras import Equirectangular, NonCentralPanorama
    if kind == "preset_other_aspect":
        return input_camera("kb_f195", 512, 256)
    if kind == "unknown_preset":
        return input_camera("kb_f999", 64, 32)
    if kind == "missing_file":
        return input_camera(str(tmp / "calib.yaml"), 64, 32)
    if kind == "yaml_without_type":
        (tmp / "cam.yaml").write_text("fx: 100\nfy: 100\n")
        return input_camera(str(tmp / "cam.yaml"), 64, 32)
    if kind == "noncentral_model":
        return CameraBridge(Equirectangular(width=64, height=32), NonCentralPanorama(width=64, height=32, rc=0.2))
    if kind == "negative_max_points":
        return CloudOptions(max_points=-1)
    if kind == "inf_voxel":
        return CloudOptions(voxel=float("inf"))
    if kind == "fisheye_into_panorama_model":
        return check_input_size(_oracle(), 1280, 960)
    if kind == "predictor_squeeze":
        return _oracle()(torch.rand(3, 64, 72))
    if kind == "own_camera_through_camera":          # --camera equirect on a panorama: nothing masked
        files = predict_depth(_oracle(), "p", torch.rand(3, 32, 64), tmp, UprightPolicy(mode="off"),
                              camera=input_camera("equirect", 64, 32))
        import json
        cov = json.loads((tmp / "p_predict.json").read_text())["camera"]["coverage"]
        assert cov["input_covered_fraction"] == 1.0 and np.allclose(np.load(tmp / "p_depth.npy"), 2.0, atol=1e-5)
        return files
    raise AssertionError(kind)


CAMERA_ROWS = [
    row("--camera preset of another aspect", "preset_other_aspect", verdict=ERROR,
        match=r"--camera 'kb_f195'.*512x256.*1080x960"),
    row("--camera unknown preset", "unknown_preset", verdict=ERROR, match=r"--camera 'kb_f999': unknown camera"),
    row("--camera file missing", "missing_file", verdict=ERROR, match=r"calib\.yaml.*does not exist"),
    row("--camera YAML without a model", "yaml_without_type", verdict=ERROR, match=r"--camera '.*cam\.yaml'"),
    row("checkpoint of a non-central camera with --camera", "noncentral_model", verdict=ERROR,
        match=r"non-central.*without the scene's depth"),
    row("--max-points -1", "negative_max_points", verdict=ERROR, match=r"--max-points must be a whole number >= 0"),
    row("--voxel inf", "inf_voxel", verdict=ERROR, match=r"--voxel must be a finite size"),
    row("1280x960 fisheye into a 64x32 panorama model", "fisheye_into_panorama_model", verdict=ERROR,
        match=r"1280x960.*64x32.*--camera"),
    row("72x64 image into a 64x32 network", "predictor_squeeze", verdict=ERROR, match=r"72x64.*64x32.*not stretched"),
    row("panorama with --camera equirect", "own_camera_through_camera", verdict=OK),
]


@pytest.mark.parametrize("kind,verdict,match", CAMERA_ROWS)
def test_camera_rows(kind, verdict, match, tmp_path):
    expect(lambda: _camera_case(kind, tmp_path), verdict, match)
