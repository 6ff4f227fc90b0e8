"""A model ready for prediction from a checkpoint: the network, its input size and its camera.

Accepted files:

* checkpoints of :mod:`omnidl.engine` (``train.py``: ``best.pt``/``last.pt``): ``model`` weights and the
  resolved ``config``; the model is ``config.model``, the input size ``config.data.height/width`` and the
  camera ``config.camera``;
* FreDSNet weights converted by ``python -m omnidl.apps.convert_fredsnet`` (``model_kwargs`` +
  ``state_dict``): 512x256 equirectangular input as the official model;
* an official HorizonNet ``.pth`` (``kwargs`` + ``state_dict``, e.g. ``resnet50_rnn__st3d.pth``): 1024x512.

``compile=True`` (``omnidl predict --compile``): the eval-mode model is compiled with ``torch.compile`` and
Inductor's ``freezing`` (:func:`omnidl.engine.compile.compile_for_inference`); it runs under
``torch.no_grad()`` as always. The compilation happens at the first forward pass, at the network's input size
(the only size it is called with), which :func:`load_predictor` makes right away: ``info["compile_s"]`` is
that first pass's time minus a second pass's (``info["first_call_s"]``, ``info["call_s"]``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch


@dataclass
class Predictor:
    """Attributes: ``model`` (eval mode), ``name`` (registry name), ``height``/``width`` (network input),
    ``camera`` (camera spec for :func:`omnidl.cameras.resolve_camera`, or None = full equirect),
    ``source`` (what the checkpoint was), ``device``."""

    model: torch.nn.Module
    name: str
    height: int
    width: int
    camera: Any = None
    source: str = ""
    device: str = "cpu"
    info: dict = field(default_factory=dict)

    def camera_for(self, width: int, height: int):
        """The checkpoint's camera on a ``width x height`` image (a full equirect of the network size when none
        is configured). The image must be the calibrated one uniformly resized (or follow a ``size_policy``
        the camera config states); any other size is a ``ValueError`` naming both sizes, never a stretch."""
        from omnidl.cameras import Equirectangular, check_image_size, resolve_camera
        if self.camera is None:
            check_image_size((height, width), Equirectangular(width=self.width, height=self.height),
                             f"{self.name} input")
            return Equirectangular(width=width, height=height)
        return resolve_camera(self.camera, width, height, check_aspect=True)

    @property
    def outputs(self) -> set[str]:
        """Output names of the model: ``depth``/``semantic`` (FreDSNet, U-Net), ``boundary``/``corner``
        (HorizonNet), ``horizon``/``vp`` (HoLiNet)."""
        return set(self.info.get("outputs", ()))

    @torch.no_grad()
    def __call__(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        """``image (3, H, W)`` in [0, 1] -> the model outputs at the network size (batch of 1). ``H x W`` is the
        network's input size or that image uniformly resized (antialiased to it); any other size is a
        ``ValueError`` naming both (never stretched; ``omnidl predict --camera`` re-projects other images)."""
        import torch.nn.functional as F

        from omnidl.cameras.resolve import is_uniform_resize
        x = image[None].float()
        if x.shape[-2:] != (self.height, self.width):
            h, w = int(x.shape[-2]), int(x.shape[-1])
            if not is_uniform_resize(w, h, _Size(self.width, self.height)):
                raise ValueError(f"{self.name}: the image is {w}x{h} (W x H) but the network takes {self.width}x"
                                 f"{self.height} or that image uniformly resized; it is not stretched (give the "
                                 "image's camera with --camera to re-project it)")
            x = F.interpolate(x, size=(self.height, self.width), mode="bilinear", align_corners=False, antialias=True)
        p = next(self.model.parameters())
        out = self.model(x.to(p.device, p.dtype))
        return {k: v.detach().float().cpu() for k, v in out.items() if isinstance(v, torch.Tensor)}


@dataclass(frozen=True)
class _Size:
    width: int
    height: int


def _probe_outputs(model: torch.nn.Module, h: int, w: int) -> tuple[str, ...]:
    with torch.no_grad():
        p = next(model.parameters())
        out = model(torch.zeros(1, 3, h, w, device=p.device, dtype=p.dtype))
    return tuple(sorted(out))


def load_predictor(path: str | Path, device: str = "cpu", compile: bool = False) -> Predictor:
    """Load a checkpoint (see the module docstring) into a :class:`Predictor`; errors name the file and what
    it lacks. ``compile``: compile the model for inference (Inductor with freezing; see the module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"--checkpoint {path}: no such file (give best.pt/last.pt of a train.py run, "
                                "converted FreDSNet weights or an official HorizonNet .pth)")
    from omnidl.utils.io import safe_torch_load
    try:
        raw = safe_torch_load(path)       # weights_only=True: a checkpoint from the internet cannot run code
    except RuntimeError as e:
        raise RuntimeError(f"--checkpoint {path}: not a readable torch file ({e})") from e
    if not isinstance(raw, dict) or not ({"model_kwargs", "kwargs", "config"} & set(raw)):
        raise ValueError(f"--checkpoint {path}: no 'config' with a 'model' entry; it must be a checkpoint of "
                         "`python train.py model=...` (or converted/official weights, see `omnidl predict -h`)")
    from omnidl.models import create_model
    if "model_kwargs" in raw and "state_dict" in raw:                                     # convert_fredsnet
        model = create_model("fredsnet", **raw["model_kwargs"])
        model.load_state_dict(raw["state_dict"])
        name, h, w, cam, source = "fredsnet", 256, 512, None, "FreDSNet official weights (converted)"
    elif "kwargs" in raw and "state_dict" in raw:                                         # official HorizonNet
        sd = raw["state_dict"]
        hidden = int(sd["bi_rnn.weight_hh_l0"].shape[1]) if "bi_rnn.weight_hh_l0" in sd else 512
        model = create_model("horizonnet", backbone=raw["kwargs"].get("backbone", "resnet50"), hidden=hidden,
                             rnn=bool(raw["kwargs"].get("use_rnn", True)), official_checkpoint=str(path))
        name, h, w, cam, source = "horizonnet", 512, 1024, None, "HorizonNet official weights"
    else:
        from omegaconf import OmegaConf

        from omnidl.engine.checkpoint import load_model_weights, model_config
        ckpt = raw
        name, mcfg, conf = model_config(ckpt, f"--checkpoint {path}", "it must be a checkpoint of "
                                        "`python train.py model=...` (or converted/official weights, see "
                                        "`omnidl predict -h`)")
        model = create_model(name, **mcfg)
        load_model_weights(model, ckpt, path)
        h = OmegaConf.select(conf, "data.height", default=None) or OmegaConf.select(conf, "camera.height", default=None)
        w = OmegaConf.select(conf, "data.width", default=None) or OmegaConf.select(conf, "camera.width", default=None)
        if h is None or w is None:
            raise ValueError(f"--checkpoint {path}: config has neither data.height/width nor camera.height/width; "
                             "cannot tell the network's input size")
        h, w = int(h), int(w)
        cam = OmegaConf.to_container(conf.camera, resolve=True) if OmegaConf.select(conf, "camera") else None
        source = f"train.py checkpoint (step {ckpt.get('step', '?')})"
    model = model.to(device).eval()
    if not compile:
        return Predictor(model, name, h, w, cam, source, device, {"outputs": _probe_outputs(model, h, w)})
    from omnidl.engine.compile import compile_for_inference
    compiled = compile_for_inference(model, device, "--compile")
    try:
        t0 = _synced_clock(device)
        outputs = _probe_outputs(compiled, h, w)                    # traces and compiles (the lazy part)
        t1 = _synced_clock(device)
        _probe_outputs(compiled, h, w)                              # a compiled call, for comparison
        t2 = _synced_clock(device)
    except Exception as e:
        raise RuntimeError(f"--compile: torch.compile of {name} failed ({type(e).__name__}: {e}); run without "
                           "--compile") from e
    info = {"outputs": outputs, "compiled": True, "compile_s": max(0.0, (t1 - t0) - (t2 - t1)),
            "first_call_s": t1 - t0, "call_s": t2 - t1}
    return Predictor(compiled, name, h, w, cam, source, device, info)


def _synced_clock(device: str | torch.device) -> float:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter()
