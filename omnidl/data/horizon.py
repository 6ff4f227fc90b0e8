"""Horizon-line and vertical-vanishing-point heat maps from a rotation (HoLiNet ground truth, thesis §6.2.1).

Given the orientation ``R = R_up_cam`` of a panorama (a direction ``d`` of the rotated camera is ``R @ d``
in the upright camera frame, so the rotated image is ``rotate_panorama(upright, R)``), the horizon normal
in the camera frame is ``n = R.T @ (0, -1, 0)`` and, for every pixel direction ``p`` of the output
equirectangular grid (pixel centres, exactly through :class:`~omnidl.cameras.Equirectangular`):

* horizon map ``HL(p) = exp(-asin(|n . p|)^2 / (2 s_h^2))`` (geodesic distance to the great circle);
* vanishing-point map ``VP(p) = exp(-acos(n . p)^2 / (2 s_v^2)) + w * exp(-acos(-n . p)^2 / (2 s_v^2))``:
  the zenith peak has height 1 and the nadir peak height ``w = nadir_weight`` (default 0.5), so the map
  tells zenith from nadir and the horizon hook recovers tilts beyond 90°. ``w = 1`` gives the symmetric
  maps of the reference code.

The module also holds the training data pipeline: :class:`RotatedPanoramas` wraps any dataset of
gravity-aligned panoramas and rotates them on the fly (random roll/pitch/yaw) with the augmentations of
§6.2.1 (horizontal flip, colour permutation, colour jitter, random crop), and :class:`PanoramaFolder`
reads a folder of upright panoramas.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.utils.data import Dataset

from omnidl.cameras.equirectangular import Equirectangular
from omnidl.geometry.panorama import rotate_panorama
from omnidl.geometry.rotations import random_tilt_rotation, up_from_rotation
from .readers import image_to_float
from .validate import invalid


def horizon_heatmaps(rotation: Tensor, height: int, width: int, sigma_deg: float = 3.0,
                     vp_sigma_deg: float | None = None, nadir_weight: float = 0.5) -> tuple[Tensor, Tensor]:
    """Ground-truth heat maps of orientations ``rotation`` (``(B, 3, 3)`` or ``(3, 3)``, ``R_up_cam``).

    The maps depend on the up vector ``n = R.T @ (0, -1, 0)`` only; see :func:`heatmaps_from_up`.
    """
    if rotation.shape[-2:] != (3, 3) or rotation.ndim not in (2, 3):
        raise ValueError(f"horizon_heatmaps: expected rotations (B, 3, 3) or (3, 3), got shape {tuple(rotation.shape)}")
    R = rotation if rotation.ndim == 3 else rotation[None]
    return heatmaps_from_up(up_from_rotation(R), height, width, sigma_deg, vp_sigma_deg, nadir_weight)


def heatmaps_from_up(up: Tensor, height: int, width: int, sigma_deg: float = 3.0,
                     vp_sigma_deg: float | None = None, nadir_weight: float = 0.5) -> tuple[Tensor, Tensor]:
    """Ground-truth heat maps of a batch of up vectors at any output resolution.

    Args:
        up: ``(B, 3)`` horizon normals (zenith direction) in the camera frame (normalised here).
        height, width: output grid (a full panorama, any size).
        sigma_deg: angular width (Gaussian sigma, degrees) of the horizon line.
        vp_sigma_deg: width of the vanishing-point peaks (default: ``sigma_deg``).
        nadir_weight: height of the nadir peak (zenith = 1); in ``(0, 1]``.
    Returns:
        ``horizon (B, 1, H, W)``, ``vp (B, 1, H, W)`` in ``[0, 1]``, dtype/device of ``rotation``.
    """
    if not 0 < nadir_weight <= 1:
        raise ValueError(f"nadir_weight must be in (0, 1], got {nadir_weight}")
    if sigma_deg <= 0 or (vp_sigma_deg is not None and vp_sigma_deg <= 0):
        raise ValueError("heat-map widths sigma_deg / vp_sigma_deg must be positive")
    if up.ndim != 2 or up.shape[-1] != 3:
        raise ValueError(f"heatmaps_from_up: expected up vectors (B, 3), got shape {tuple(up.shape)}")
    n = up / up.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    dtype = n.dtype if n.is_floating_point() else torch.float32
    d = Equirectangular(width=width, height=height).unproject_grid(dtype, n.device).direction  # (H, W, 3)
    dot = torch.einsum("bk,hwk->bhw", n.to(dtype), d).clamp(-1.0, 1.0)
    sh = math.radians(sigma_deg)
    sv = math.radians(vp_sigma_deg if vp_sigma_deg is not None else sigma_deg)
    hl = torch.exp(-torch.asin(dot.abs()) ** 2 / (2 * sh * sh))
    vp = torch.exp(-torch.acos(dot) ** 2 / (2 * sv * sv)) + nadir_weight * torch.exp(-torch.acos(-dot) ** 2 / (2 * sv * sv))
    return hl.unsqueeze(1), vp.clamp(max=1.0).unsqueeze(1)


# -- training data ----------------------------------------------------------------------------------
def colour_jitter(image: Tensor, strength: float, gen: torch.Generator) -> Tensor:
    """Random brightness, contrast and saturation factors in ``[1 - strength, 1 + strength]``; ``(3, H, W)``."""
    if strength <= 0:
        return image
    f = 1 + strength * (2 * torch.rand(3, generator=gen, dtype=torch.float64) - 1)
    img = image * float(f[0])
    mean = img.mean()
    img = (img - mean) * float(f[1]) + mean
    grey = (0.299 * img[0] + 0.587 * img[1] + 0.114 * img[2]).unsqueeze(0)
    img = (img - grey) * float(f[2]) + grey
    return img.clamp(0, 1)


class RotatedPanoramas(Dataset):
    """Gravity-aligned panoramas rotated on the fly, with HoLiNet targets (thesis §6.2.1).

    Args:
        base: a dataset of *upright* equirectangular panoramas (items with an ``"image"`` ``(3, H, W)``),
            e.g. :class:`omnidl.data.synthetic.SyntheticPanoramaDataset` or :class:`PanoramaFolder`.
        height, width: network input size (images are resized; ``None`` keeps the base size).
        map_height: height of the target maps (default ``height // 2``, HoLiNet's output; width 2x).
        max_tilt_deg: up vectors uniform in a cap of this angle (180 = any orientation); yaw uniform.
        sigma_deg, vp_sigma_deg, nadir_weight: target widths and nadir peak (:func:`horizon_heatmaps`).
        augment: apply flip / colour permutation / colour jitter / crop (training).
        flip_p, permute_p, jitter, crop_p, crop_min_scale: augmentation settings. Flip and colour changes
            act on the upright image (they keep it upright); a crop keeps a random window of at least
            ``crop_min_scale`` of each side of the *rotated* image and maps, resized back, so it breaks the
            panorama geometry: ``geometry_valid`` is then False and rotation metrics skip the sample.
        deterministic: the same rotation/augmentation for the same index (validation); otherwise fresh
            random draws every time (training; seeded by the engine's worker seeds).
        seed: base seed of the deterministic draws.
        length: number of samples (default ``len(base)``; indices wrap around the base).

    Items: ``{"image": (3, H, W), "horizon_map": (1, h, w), "vp_map": (1, h, w), "rotation": (3, 3)``
    ``R_up_cam``, ``"up": (3,)`` horizon normal in the camera frame, ``"geometry_valid": bool tensor,
    "meta": {...}}``.
    """

    def __init__(self, base: Dataset, height: int | None = 128, width: int | None = 256, map_height: int | None = None,
                 max_tilt_deg: float = 180.0, sigma_deg: float = 3.0, vp_sigma_deg: float | None = None,
                 nadir_weight: float = 0.5, augment: bool = True, flip_p: float = 0.5, permute_p: float = 0.5,
                 jitter: float = 0.2, crop_p: float = 0.0, crop_min_scale: float = 0.8, deterministic: bool = False,
                 seed: int = 0, length: int | None = None) -> None:
        if len(base) == 0:
            raise ValueError("RotatedPanoramas: the base dataset is empty")
        if not 0 <= max_tilt_deg <= 180:
            raise ValueError(f"RotatedPanoramas: max_tilt_deg must be in [0, 180], got {max_tilt_deg}")
        if (height is None) != (width is None) or (width is not None and width != 2 * height):
            raise ValueError(f"RotatedPanoramas: give height and width of a full panorama (width = 2 height), got "
                             f"{height} x {width}")
        if not 0 < crop_min_scale <= 1:
            raise ValueError(f"RotatedPanoramas: crop_min_scale must be in (0, 1], got {crop_min_scale}")
        self.base = base
        self.height, self.width = height, width
        self.map_height = map_height
        self.max_tilt_deg = float(max_tilt_deg)
        self.sigma_deg, self.vp_sigma_deg, self.nadir_weight = float(sigma_deg), vp_sigma_deg, float(nadir_weight)
        self.augment = bool(augment)
        self.flip_p, self.permute_p, self.jitter = float(flip_p), float(permute_p), float(jitter)
        self.crop_p, self.crop_min_scale = float(crop_p), float(crop_min_scale)
        self.deterministic = bool(deterministic)
        self.seed = int(seed)
        self.length = len(base) if length is None else int(length)

    def __len__(self) -> int:
        return self.length

    def _generator(self, index: int) -> torch.Generator:
        if self.deterministic:
            return torch.Generator().manual_seed(self.seed * 1_000_003 + index)
        return torch.Generator().manual_seed(int(torch.randint(0, 2 ** 62, (1,))))

    def __getitem__(self, index: int) -> dict[str, Any]:
        if not 0 <= index < self.length:
            raise IndexError(f"index {index} out of range for a dataset of length {self.length}")
        item = self.base[index % len(self.base)]
        if not isinstance(item, dict) or "image" not in item:
            raise KeyError(f"RotatedPanoramas: base item {index} has no 'image' (got "
                           f"{sorted(item) if isinstance(item, dict) else type(item).__name__})")
        img = image_to_float(item["image"], f"RotatedPanoramas: base item {index}").float()   # uint8: / 255 first
        if img.ndim != 3 or img.shape[0] != 3 or img.shape[2] != 2 * img.shape[1]:
            raise ValueError(f"RotatedPanoramas: base item {index}: expected an equirectangular RGB image (3, H, 2H), "
                             f"got {tuple(img.shape)}")
        if self.height is not None and tuple(img.shape[-2:]) != (self.height, self.width):
            img = F.interpolate(img[None], size=(self.height, self.width), mode="bilinear", align_corners=False,
                                antialias=True)[0]
        gen = self._generator(index)
        meta: dict[str, Any] = {"index": int(index), "flip": False, "permutation": [0, 1, 2], "crop": None}
        if self.augment:
            if float(torch.rand(1, generator=gen)) < self.flip_p:
                img = img.flip(-1)  # mirror of an upright panorama is upright
                meta["flip"] = True
            if float(torch.rand(1, generator=gen)) < self.permute_p:
                perm = torch.randperm(3, generator=gen)
                img = img[perm]
                meta["permutation"] = perm.tolist()
            img = colour_jitter(img, self.jitter, gen)
        R = random_tilt_rotation(1, math.radians(self.max_tilt_deg), generator=gen, dtype=torch.float64)[0]
        img = rotate_panorama(img, R.to(img.dtype), cache=False)[0].clamp(0, 1)
        H, W = img.shape[-2:]
        mh = self.map_height or max(1, H // 2)
        hl, vp = horizon_heatmaps(R[None].float(), mh, 2 * mh, self.sigma_deg, self.vp_sigma_deg, self.nadir_weight)
        hl, vp = hl[0], vp[0]
        geometry_valid = True
        if self.augment and self.crop_p > 0 and float(torch.rand(1, generator=gen)) < self.crop_p:
            s = self.crop_min_scale + (1 - self.crop_min_scale) * float(torch.rand(1, generator=gen))
            fy, fx = float(torch.rand(1, generator=gen)), float(torch.rand(1, generator=gen))
            img = _crop_resize(img, s, fy, fx)
            hl, vp = _crop_resize(hl, s, fy, fx), _crop_resize(vp, s, fy, fx)
            geometry_valid = False
            meta["crop"] = [s, fy, fx]
        base_meta = item.get("meta", {})
        if isinstance(base_meta, dict):
            meta["base"] = {k: v for k, v in base_meta.items() if isinstance(v, (str, int, float, bool))}
        return {"image": img, "horizon_map": hl, "vp_map": vp, "rotation": R.float(),
                "up": up_from_rotation(R).float(), "geometry_valid": torch.tensor(geometry_valid), "meta": meta}


def _crop_resize(x: Tensor, scale: float, fy: float, fx: float) -> Tensor:
    """Crop a window of ``scale`` of each side at relative offset ``(fy, fx)`` and resize it back."""
    H, W = x.shape[-2:]
    h, w = max(1, round(H * scale)), max(1, round(W * scale))
    y0, x0 = int(round(fy * (H - h))), int(round(fx * (W - w)))
    win = x[..., y0:y0 + h, x0:x0 + w]
    return F.interpolate(win[None], size=(H, W), mode="bilinear", align_corners=False)[0]


class PanoramaFolder(Dataset):
    """Upright panoramas from a folder (any sorted image files), as ``{"image": (3, H, W), "meta"}``.

    Args:
        root: folder of equirectangular images (png/jpg/...).
        height, width: resize to this size (``None`` keeps each file's size).
        aspect_tolerance: a stored image whose width is not twice its height (within this fraction) is not
            an equirectangular panorama: a :class:`~omnidl.data.validate.DataValidationError`.

    An unreadable, truncated or non-2:1 file raises a :class:`~omnidl.data.robust.CorruptSampleError` naming
    it, so training (``SkipCorrupt``) skips it with a warning.
    """

    EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")

    def __init__(self, root: str, height: int | None = 256, width: int | None = 512,
                 aspect_tolerance: float = 0.01) -> None:
        self.root = Path(root).expanduser()
        if not self.root.is_dir():
            raise FileNotFoundError(f"panorama folder {self.root} does not exist")
        self.files = sorted(p for p in self.root.iterdir() if p.suffix.lower() in self.EXTENSIONS)
        if not self.files:
            raise FileNotFoundError(f"panorama folder {self.root} holds no images ({', '.join(self.EXTENSIONS)})")
        self.height, self.width = height, width
        self.aspect_tolerance = float(aspect_tolerance)

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, index: int) -> dict[str, Any]:
        path = self.files[index]
        img = read_rgb(path)
        h, w = img.shape[-2:]
        if abs(w - 2 * h) > max(1.0, self.aspect_tolerance * w):
            raise invalid(path, "panorama size", f"{w}x{h}", "an equirectangular panorama (width = 2 x height)")
        if self.height is not None:
            img = F.interpolate(img[None], size=(self.height, self.width), mode="bilinear", align_corners=False,
                                antialias=True)[0]
        return {"image": img, "meta": {"name": path.name}}


def read_rgb(path: str | Path) -> Tensor:
    """``(3, H, W)`` float32 RGB in ``[0, 1]`` of an image file (8 or 16 bit, gray or RGB[A]), upright: the reading
    policy of :func:`omnidl.data.readers.read_rgb`.

    A missing, empty, truncated or undecodable file raises
    :class:`~omnidl.data.validate.UnreadableFileError` (an ``OSError`` and a ``CorruptSampleError``) naming it."""
    from .readers import read_rgb as _read
    return _read(path)
