"""omnidl.cameras.resolve_camera: every spec kind, resizing, the aspect check, errors, and the old names."""
import subprocess
import sys

import pytest
import torch
from omegaconf import OmegaConf

from omnidl.cameras import (CAMERA_CONFIG_DIR, Equirectangular, NonCentralPanorama, ResizedCamera, build,
                            check_image_size, list_cameras, resolve_camera)

F195_VALUES = [540, 480, 287, 287, 1080, 960, 195, 3.37012024344156e-19, -3.543830680552053e-05,
               9.999999999924497e-08, -6.883696004705416e-11]


@pytest.fixture(scope="module")
def f195():
    return build(OmegaConf.load(CAMERA_CONFIG_DIR / "kb_f195.yaml"))


@pytest.fixture
def calib_file(tmp_path):
    path = tmp_path / "fisheye_calibration_FOV195.txt"
    path.write_text("\n".join(repr(float(v)) for v in F195_VALUES) + "\n")
    return path


def test_camera_object_is_returned_as_is(f195):
    assert resolve_camera(f195) is f195


def test_mapping_and_dictconfig(f195):
    cfg = OmegaConf.to_container(OmegaConf.load(CAMERA_CONFIG_DIR / "kb_f195.yaml"))
    assert "_target_" in cfg
    assert resolve_camera(cfg) == f195
    assert resolve_camera(OmegaConf.create(cfg)) == f195
    node = OmegaConf.create({"w": 64, "camera": {"type": "equirect", "width": "${w}", "height": 32}}).camera
    assert resolve_camera(node) == Equirectangular(width=64, height=32)
    assert resolve_camera({"type": "equirect", "width": 64, "height": 32}, height=16, width=32) == \
        Equirectangular(width=64, height=32).resized(32, 16)


def test_fields_override_a_config():
    cam = resolve_camera({"type": "noncentral_pano", "width": 64, "height": 32, "rc": 1.0}, rc=0.25)
    assert isinstance(cam, NonCentralPanorama) and cam.rc == 0.25
    cam = resolve_camera("noncentral_pano", 64, 32, rc=0.5)
    assert (cam.width, cam.height) == (64, 32)
    with pytest.raises(ValueError, match=r"\['rc'\].*Equirectangular object"):
        resolve_camera(Equirectangular(width=64, height=32), rc=0.5)


def test_calibration_file_and_calib_file_mapping(calib_file, f195):
    assert resolve_camera(calib_file) == f195
    assert resolve_camera(str(calib_file)) == f195
    assert resolve_camera({"calib_file": str(calib_file)}) == f195          # type defaults to kannala_brandt
    assert resolve_camera({"calib_file": str(calib_file), "_target_": "omnidl.cameras.build"}) == f195
    assert resolve_camera(calib_file, fx=290.0).fx == 290.0                  # fields override the file


def test_yaml_file(tmp_path, f195):
    assert resolve_camera(CAMERA_CONFIG_DIR / "kb_f195.yaml") == f195
    assert resolve_camera(str(CAMERA_CONFIG_DIR / "kb_f195.yaml")) == f195
    bad = tmp_path / "bad.yaml"
    bad.write_text("width: 10\n")
    with pytest.raises(ValueError, match=r"bad\.yaml.*'type'"):
        resolve_camera(bad)


def test_config_name(f195):
    assert resolve_camera("kb_f195") == f195
    # a config name wins over the registered type of the same name
    assert resolve_camera("equirect") == build(OmegaConf.load(CAMERA_CONFIG_DIR / "equirect.yaml"))


def test_registered_type_is_built_at_the_size():
    assert "pinhole" in list_cameras()
    cam = resolve_camera("fisheye", 48, 40, f=10.0, cx=24.0, cy=20.0)
    assert not isinstance(cam, ResizedCamera) and (cam.width, cam.height) == (48, 40)
    with pytest.raises(ValueError, match="'fisheye' needs width and height"):
        resolve_camera("fisheye")


def test_resize_and_aspect_check(f195):
    small = resolve_camera("kb_f195", 72, 64)
    assert isinstance(small, ResizedCamera) and small.base == f195 and (small.width, small.height) == (72, 64)
    assert resolve_camera(f195, 1080, 960) is f195                         # same size: unchanged
    assert resolve_camera(f195, 64, 64).width == 64                         # no check by default
    assert resolve_camera(f195, 72, 64, check_aspect=True) == small
    with pytest.raises(ValueError, match=r"64x64.*disagrees with the calibration.*1080x960"):
        resolve_camera(f195, 64, 64, check_aspect=True)
    with pytest.raises(ValueError, match="both width and height"):
        resolve_camera(f195, width=72)
    with pytest.raises(ValueError, match="1080x960"):
        check_image_size((64, 64), f195)
    check_image_size((64, 72), f195)


def test_none_with_and_without_default():
    with pytest.raises(TypeError, match=r"no camera given \(None\); expected a Camera"):
        resolve_camera(None)
    assert resolve_camera(None, default=None) is None
    pano = Equirectangular(width=64, height=32)
    assert resolve_camera(None, default=pano) is pano
    assert resolve_camera(None, 32, 16, default=pano) == pano.resized(32, 16)
    assert resolve_camera({"type": "equirect", "width": 8, "height": 4}, default=pano).width == 8


def test_errors_name_what_was_given_and_what_is_accepted(tmp_path):
    with pytest.raises(ValueError, match=r"unknown camera 'no_such_camera'.*kb_f195.*kannala_brandt") as info:
        resolve_camera("no_such_camera")
    assert str(CAMERA_CONFIG_DIR) in str(info.value)
    with pytest.raises(TypeError, match=r"camera spec of type int \(3\); expected a Camera, a config mapping"):
        resolve_camera(3)
    for name in ("missing.txt", "missing.yaml"):
        with pytest.raises(FileNotFoundError, match=name):
            resolve_camera(tmp_path / name)
    short = tmp_path / "short.txt"
    short.write_text("1 2 3\n")
    with pytest.raises(ValueError, match=r"short\.txt.*expected 11 values"):
        resolve_camera(short)
    with pytest.raises(ValueError, match="needs a 'type'"):
        resolve_camera({"width": 8, "height": 4})


def test_every_consumer_uses_the_one_resolver(calib_file, f195):
    """The consumers' former adapters (``data.fisheye.load_camera``, ``models.unet.resolve_camera``,
    ``nn.projected_conv.as_camera``, ``synth.cameras``) are options of :func:`resolve_camera`."""
    from omnidl.data import synthetic
    from omnidl.models import unet
    from omnidl.nn import ProjectedConv2d
    assert synthetic.resolve_camera is resolve_camera
    assert unet.check_image_size is check_image_size and unet.resolve_camera is resolve_camera
    assert resolve_camera(None, default=None) is None and resolve_camera(str(calib_file), default=None) == f195
    assert resolve_camera(calib_file, check_aspect=True) == f195
    with pytest.raises(ValueError, match="disagrees"):                  # datasets check the aspect
        resolve_camera(calib_file, 64, 64, check_aspect=True)
    assert resolve_camera(calib_file, 64, 64, check_aspect=False).width == 64
    pano = Equirectangular(width=64, height=32)
    in_memory = dict(allow_files=False)
    assert resolve_camera(None, default=None, **in_memory) is None
    assert resolve_camera(None, default=pano, **in_memory) is pano
    assert resolve_camera(OmegaConf.create({"type": "equirect", "width": 64, "height": 32}), **in_memory) == pano
    with pytest.raises(TypeError, match="resolve_camera"):                 # layers take in-memory specs only
        resolve_camera("equirect", **in_memory)
    with pytest.raises(TypeError, match="resolve_camera"):
        ProjectedConv2d(2, 2, 3, camera="equirect")


@pytest.mark.slow
def test_import_pulls_in_no_higher_package():
    code = ("import sys, omnidl.cameras; bad = [m for m in sys.modules if m.split('.')[:2] in "
            "[['omnidl', p] for p in ('nn', 'models', 'synth', 'data')] or m == 'omegaconf']; print(bad)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"



# -- image size vs calibration: size policies ---------------------------------------------------------------

def test_size_mismatch_is_an_error_naming_the_file_and_both_sizes(calib_file, f195):
    from omnidl.cameras.resolve import is_uniform_resize
    assert is_uniform_resize(72, 64, f195) and is_uniform_resize(34, 30, f195) and is_uniform_resize(33, 30, f195)
    assert is_uniform_resize(2160, 1920, f195)
    assert not is_uniform_resize(1088, 960, f195) and not is_uniform_resize(1081, 960, f195)
    assert not is_uniform_resize(2161, 1920, f195) and not is_uniform_resize(64, 64, f195)
    for spec in (calib_file, {"calib_file": str(calib_file)}):
        with pytest.raises(ValueError, match=r"1088x960.*disagrees with the calibration of '.*fisheye_calibration_"
                                             r"FOV195\.txt' \(1080x960\).*size_policy") as info:
            resolve_camera(spec, 1088, 960, check_aspect=True)
        assert all(p in str(info.value) for p in ("'pad'", "'crop'", "'scale'"))
        with pytest.raises(ValueError, match="1088x960.*fisheye_calibration_FOV195"):
            resolve_camera(spec, 1088, 960, size_policy="error")
    with pytest.raises(ValueError, match=r"1088x960.*kb_f195\.yaml.*1080x960"):
        resolve_camera("kb_f195", 1088, 960, check_aspect=True)
    with pytest.raises(ValueError, match="size_policy must be one of"):
        resolve_camera(f195, 1088, 960, size_policy="stretch")
    assert resolve_camera(calib_file, 540, 480, check_aspect=True) == f195.resized(540, 480)   # uniform: fine


def test_pad_policy_keeps_the_calibration(calib_file, f195):
    cam = resolve_camera(calib_file, 1088, 960, size_policy="pad")
    assert (cam.width, cam.height) == (1088, 960) and (cam.scale_x, cam.scale_y) == (1.0, 1.0)
    pts = torch.tensor([[0.3, -0.2, 1.0], [-1.0, 0.5, 0.2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    assert torch.equal(cam.project(pts)[0], f195.project(pts)[0])            # every pixel stays where it was
    assert cam.project(pts[2:])[0].tolist() == [[540.0, 480.0]]
    rays = cam.unproject(torch.tensor([[1084.0, 480.0], [1000.0, 480.0]], dtype=torch.float64))
    assert rays.valid.tolist() == [False, True]                               # the 8 extra columns are outside
    # padded and downscaled by 4 (a 272x240 network input of the 1088x960 padded image)
    small = resolve_camera(f195, 272, 240, size_policy="pad")
    assert small.scale_x == small.scale_y == 0.25
    # the config key states the policy (mapping or camera YAML)
    assert resolve_camera({"calib_file": str(calib_file), "size_policy": "pad"}, 1088, 960) == cam
    assert resolve_camera(OmegaConf.create({"calib_file": str(calib_file), "size_policy": "pad"}), 1088, 960) == cam


def test_crop_policy(calib_file, f195):
    cam = resolve_camera(calib_file, 1072, 960, size_policy="crop")
    assert (cam.width, cam.height) == (1072, 960) and (cam.scale_x, cam.scale_y) == (1.0, 1.0)
    pts = torch.tensor([[0.3, -0.2, 1.0]], dtype=torch.float64)
    assert torch.equal(cam.project(pts)[0], f195.project(pts)[0])
    assert not cam.unproject(torch.tensor([1075.0, 480.0], dtype=torch.float64)).valid   # cut off
    half = resolve_camera(f195, 536, 480, size_policy="crop")                 # cropped 1072x960, halved
    assert half.scale_x == half.scale_y == 0.5


def test_scale_policy_is_the_old_two_percent_stretch(calib_file, f195, tmp_path):
    cam = resolve_camera(calib_file, 1088, 960, size_policy="scale")
    assert (cam.scale_x, cam.scale_y) == (1088 / 1080, 1.0)
    with pytest.raises(ValueError, match=r"64x64.*disagrees with the calibration.*1080x960.*aspect"):
        resolve_camera(calib_file, 64, 64, size_policy="scale")
    check_image_size((960, 1088), f195, size_policy="scale")
    check_image_size((960, 1088), f195, size_policy="pad")
    with pytest.raises(ValueError, match="1088x960"):
        check_image_size((960, 1088), f195)
    yaml = tmp_path / "cam.yaml"
    yaml.write_text(f"type: kannala_brandt\ncalib_file: {calib_file}\nsize_policy: scale\n")
    assert resolve_camera(yaml, 1088, 960) == cam
    assert resolve_camera(yaml) == f195
    # an explicit argument wins over the config key
    assert resolve_camera(yaml, 1088, 960, size_policy="pad").scale_x == 1.0


def test_presets_come_from_the_package_wherever_the_command_runs(tmp_path, monkeypatch):
    """Camera presets (``configs/camera/<name>.yaml``) ship inside the package (importlib.resources), so a name
    such as ``kb_f195`` resolves from any working directory and in a wheel install (tests/test_wheel.py)."""
    from importlib import resources
    from pathlib import Path

    import omnidl
    from omnidl.cameras.resolve import config_names
    assert CAMERA_CONFIG_DIR == Path(str(resources.files("omnidl").joinpath("configs", "camera")))
    assert CAMERA_CONFIG_DIR.parent.parent == Path(omnidl.__file__).parent
    assert {"kb_f195", "kb_f165", "equirect", "pinhole"} <= set(config_names())
    monkeypatch.chdir(tmp_path)
    cam = resolve_camera("kb_f195")
    assert (cam.width, cam.height) == (1080, 960) and type(cam).__name__ == "KannalaBrandt"
