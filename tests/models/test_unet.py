"""U-Net (thesis ch. 7): shapes, tasks, calibrated convolutions with identical state dicts, pretrained
weights, size checks, and the Hydra configs."""
import math

import pytest
import torch

from omnidl.cameras.kannala_brandt import KannalaBrandt
from omnidl.models import create_model
from omnidl.models.unet import UNet, check_image_size
from omnidl.nn.projected_conv import ProjectedConv2d


@pytest.fixture(autouse=True)
def _one_thread(single_thread):
    yield


def small_fisheye(w=24, h=16):
    return KannalaBrandt(width=w, height=h, fx=5.5, fy=5.5, cx=w / 2, cy=h / 2, max_fov=math.radians(195))


@pytest.mark.parametrize("tasks", [["depth"], ["semantic"], ["depth", "semantic"]])
@pytest.mark.parametrize("hw", [(16, 24), (15, 21)])
def test_shapes_and_tasks(tasks, hw):
    torch.manual_seed(0)
    m = UNet(tasks=tasks, base_channels=4, levels=3).eval()
    out = m(torch.rand(2, 3, *hw))
    assert sorted(out) == sorted(tasks)
    if "depth" in out:
        assert out["depth"].shape == (2, 1, *hw) and bool((out["depth"] >= 0).all())
    if "semantic" in out:
        assert out["semantic"].shape == (2, 14, *hw)


def test_calibrated_same_state_dict_and_switch_back():
    torch.manual_seed(0)
    std = UNet(base_channels=4, levels=2).eval()
    cam = small_fisheye()
    cal = UNet(base_channels=4, levels=2, conv="projected", camera=cam).eval()
    assert list(std.state_dict()) == list(cal.state_dict())
    cal.load_state_dict(std.state_dict())
    n_proj = sum(isinstance(m, ProjectedConv2d) for m in cal.modules())
    n_conv3 = sum(isinstance(m, torch.nn.Conv2d) and m.kernel_size == (3, 3) for m in std.modules())
    assert n_proj == n_conv3 > 0
    x = torch.rand(1, 3, 16, 24)
    a, b = std(x), cal(x)
    assert not torch.allclose(a["depth"], b["depth"])      # the kernels are deformed
    # weights are shared Parameters: calibrate() in place keeps them; standardize() gives nn.Conv2d back
    std2 = UNet(base_channels=4, levels=2).eval()
    std2.load_state_dict(std.state_dict())
    w_before = std2.inc[0].weight
    std2.calibrate(cam)
    assert std2.inc[0].weight is w_before
    torch.testing.assert_close(std2(x)["depth"], b["depth"])
    std2.standardize()
    torch.testing.assert_close(std2(x)["depth"], a["depth"])


def test_calibrated_with_a_pinhole_camera_at_its_centre_is_nearly_standard():
    """A pinhole camera barely deforms a 3x3 kernel near the image centre: both outputs agree there."""
    from omnidl.cameras.pinhole import Pinhole
    torch.manual_seed(0)
    std = UNet(tasks=["depth"], base_channels=4, levels=1).eval()
    cal = UNet(tasks=["depth"], base_channels=4, levels=1, conv="projected",
               camera=Pinhole(width=16, height=16, fx=200.0, fy=200.0, cx=8.0, cy=8.0)).eval()
    cal.load_state_dict(std.state_dict())
    x = torch.rand(1, 3, 16, 16)
    torch.testing.assert_close(cal(x)["depth"][..., 4:12, 4:12], std(x)["depth"][..., 4:12, 4:12],
                               atol=2e-3, rtol=1e-2)


def test_image_size_must_match_calibration_aspect():
    cal = UNet(base_channels=2, levels=1, conv="projected", camera=small_fisheye(48, 32))
    cal(torch.rand(1, 3, 16, 24))   # uniformly resized: fine
    with pytest.raises(ValueError, match="disagrees with the calibration"):
        cal(torch.rand(1, 3, 16, 16))
    with pytest.raises(ValueError, match="1080x960"):
        check_image_size((64, 64), KannalaBrandt(width=1080, height=960, fx=287, fy=287, cx=540, cy=480,
                                                max_fov=math.radians(195)))


def test_bad_arguments():
    with pytest.raises(ValueError, match="needs the camera"):
        UNet(conv="projected")
    with pytest.raises(ValueError, match="conv must be"):
        UNet(conv="equi")
    with pytest.raises(ValueError, match="tasks"):
        UNet(tasks=["normals"])
    with pytest.raises(ValueError, match=r"expects RGB images of shape \(B, 3, H, W\)"):
        UNet(base_channels=2, levels=1)(torch.rand(3, 8, 8))


def test_pretrained_weights_from_local_path(tmp_path):
    from omnidl.engine.checkpoint import save_checkpoint
    torch.manual_seed(1)
    src = UNet(base_channels=4, levels=2)
    save_checkpoint(tmp_path / "bl.pt", {"model": src.state_dict()})
    m = create_model("unet", base_channels=4, levels=2, pretrained=str(tmp_path / "bl.pt"), conv="projected",
                     camera=small_fisheye())
    for k, v in src.state_dict().items():
        torch.testing.assert_close(m.state_dict()[k], v)
    with pytest.raises(FileNotFoundError, match="do not exist"):
        UNet(pretrained=str(tmp_path / "missing.pt"))
    with pytest.raises(RuntimeError, match="does not fit|size mismatch"):
        UNet(base_channels=8, levels=2, pretrained=str(tmp_path / "bl.pt"))


def test_hydra_configs_compose_and_build(tmp_path):
    from pathlib import Path

    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from omnidl.engine.config import register_configs
    register_configs()
    root = Path(__file__).resolve().parents[2] / "configs"
    with initialize_config_dir(config_dir=str(root), version_base="1.3"):
        cfg = compose("train", overrides=["model=unet_small", "experiment=fisheye_f195_calib",
                                          f"paths.output_dir={tmp_path}"])
        model = instantiate(cfg.model, _convert_="all")
        assert model.conv == "projected" and model.camera.width == 1080
        ds = instantiate(cfg.data.test, _convert_="all")
        assert (ds.camera.width, ds.camera.height) == (72, 64)
        loss = instantiate(cfg.loss, _convert_="all")
        assert loss.wrap is False
        cfg = compose("train", overrides=["model=unet", "experiment=fisheye_pers", f"paths.output_dir={tmp_path}"])
        assert cfg.model.conv == "standard" and "Perspective" in cfg.data.train._target_
