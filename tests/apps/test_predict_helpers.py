"""Fixtures of the ``omnidl predict`` tests: tiny randomly initialised checkpoints saved as ``omnidl.engine``
saves them (``model`` state + the unresolved ``config``), and synthetic panoramas of mixed sizes made with
the synth CLI plus a tilted copy of each."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[2]

#: per model config: overrides that make a CPU-tiny network at a small input size
TINY = {
    "fredsnet": ["model=fredsnet", "model.width=0.0625", "model.head_width=64", "data.width=128", "data.height=64"],
    "horizonnet": ["model=horizonnet", "model.hidden=16", "data.width=128", "data.height=64"],
    # the smallest registered depth model (fast to torch.compile): a one-level U-Net on equirect panoramas
    "unet": ["model=unet", "model.base_channels=4", "model.levels=1", "data=synthetic_pano", "camera=equirect",
             "data.width=64", "data.height=32"],
}


def tiny_checkpoint(path: Path, model: str, seed: int = 0) -> Path:
    """``path``: a checkpoint of a randomly initialised tiny ``model`` in the engine's format."""
    from omnidl.engine.build import build_model
    from omnidl.engine.checkpoint import save_checkpoint
    from omnidl.engine.config import register_configs
    register_configs()
    from omnidl.engine.config import config_root
    with initialize_config_dir(version_base="1.3", config_dir=str(config_root()), job_name="predict_test"):
        cfg = compose(config_name="train", overrides=[f"paths.output_dir={path.parent}", *TINY[model]])
    torch.manual_seed(seed)
    net = build_model(cfg)
    save_checkpoint(path, {"model": net.state_dict(), "config": OmegaConf.to_container(cfg, resolve=False),
                           "step": 0, "epoch": 0})
    return path


def tilt(image: torch.Tensor, roll_deg: float, pitch_deg: float) -> tuple[torch.Tensor, torch.Tensor]:
    """A tilted copy of an upright panorama ``(3, H, W)``: ``(image, R_up_cam)`` with the tilt's true up."""
    import math

    from omnidl.geometry.rotations import euler_to_matrix
    from omnidl.geometry.upright import to_input_frame
    R = euler_to_matrix(math.radians(roll_deg), math.radians(pitch_deg), 0.0).double()
    return to_input_frame(image, R).clamp(0, 1), R


def synth_folder(out: Path, sizes=((256, 128), (192, 96)), n: int = 1, tilted: bool = True) -> Path:
    """``out/images``: ``n`` rooms per size rendered by the synth CLI, plus ``<name>_tilted.png`` copies."""
    import cv2

    from omnidl.apps.synth import main as synth_main
    from omnidl.apps.predict.inputs import read_image
    img_dir = out / "images"
    img_dir.mkdir(parents=True, exist_ok=True)
    for w, h in sizes:
        raw = out / f"synth_{w}x{h}"
        assert synth_main(["--camera", "equirect", "--width", str(w), "--height", str(h), "--n", str(n),
                           "--out", str(raw), "--contact-sheet", "0", "--seed", str(w)]) == 0
        for k, f in enumerate(sorted((raw / "area_1" / "pano" / "rgb").glob("*.png"))):
            name = f"room_{w}x{h}_{k}"
            shutil.copy(f, img_dir / f"{name}.png")
            if tilted:
                t, _ = tilt(read_image(f), 12.0, -7.0)
                bgr = (t.permute(1, 2, 0).numpy()[..., ::-1] * 255).round().astype(np.uint8)
                cv2.imwrite(str(img_dir / f"{name}_tilted.png"), bgr)
    return img_dir


def readme_fisheye_fixture(folder: Path) -> dict[str, Path]:
    """The files of the README's ``omnidl predict depth my_fisheye.jpg --camera calib.yaml`` example in
    ``folder``: ``my_fisheye.jpg`` (a synthetic room through the F195 fisheye at 270x240, a quarter of its
    1080x960 calibration), ``calib.yaml`` (that calibration, omnidl's camera YAML; any format
    :func:`omnidl.cameras.load` reads works) and ``ckpt.pt`` (a tiny randomly initialised U-Net of 64x32
    equirectangular panoramas, saved as ``train.py`` saves checkpoints)."""
    import cv2

    from omnidl.cameras import resolve_camera, save
    from omnidl.engine.checkpoint import save_checkpoint
    from omnidl.models import create_model
    from omnidl.synth import render_sample
    folder.mkdir(parents=True, exist_ok=True)
    s = render_sample(resolve_camera("kb_f195", 270, 240), 0, "test", 0, furniture=False)
    bgr = (s["image"].permute(1, 2, 0).numpy()[..., ::-1] * 255).round().astype(np.uint8)
    assert cv2.imwrite(str(folder / "my_fisheye.jpg"), bgr)
    save(resolve_camera("kb_f195"), folder / "calib.yaml")
    torch.manual_seed(0)
    kw = {"base_channels": 4, "levels": 1}
    save_checkpoint(folder / "ckpt.pt", {"model": create_model("unet", **kw).state_dict(), "step": 0, "epoch": 0,
                                         "config": {"model": {"name": "unet", **kw}, "data": {"height": 32, "width": 64},
                                                    "camera": {"type": "equirect", "width": 64, "height": 32}}})
    return {"image": folder / "my_fisheye.jpg", "camera": folder / "calib.yaml", "checkpoint": folder / "ckpt.pt"}
