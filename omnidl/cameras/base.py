"""The one camera interface every part of omnidl asks for geometry.

Conventions (fixed project-wide, see README "Conventions"):

* Camera frame: OpenCV — x right, y down, z forward. Metres and radians.
* Pixels: continuous coordinates ``(u, v)``, ``u`` to the right, ``v`` down. The
  centre of pixel (row ``i``, column ``j``) is ``(j + 0.5, i + 0.5)``; the image
  covers ``[0, W) x [0, H)``.
* ``project`` maps ``(..., 3)`` camera-frame points to ``(..., 2)`` pixels and a
  ``(...)`` bool mask. Points outside the field of view, or whose pixel falls
  outside the image, are ``valid=False`` with finite (never NaN) pixel values.
* ``unproject`` maps ``(..., 2)`` pixels to :class:`Rays` — origin ``(..., 3)``,
  unit direction ``(..., 3)``, valid ``(...)``. Central cameras return origin 0.
* Everything is batched torch, works in float32/float64 on any device, and is
  differentiable w.r.t. the points/pixels where the maths is (invalid entries
  are computed on safe substitute values so their gradients are finite).

Camera objects are immutable, hashable and compared by value (frozen
dataclasses), so layers can cache per-camera sampling plans keyed by camera.
Parameters are plain Python floats; computations use the dtype/device of the
input tensor.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple

import torch
from torch import Tensor

from .validate import Domain, check_domains, check_size, check_types, family_name


class Rays(NamedTuple):
    """A bundle of rays (lines with an orientation and a start point).

    Attributes:
        origin: ``(..., 3)`` start points in metres (zeros for central cameras).
        direction: ``(..., 3)`` unit directions.
        valid: ``(...)`` bool, False where the pixel does not see the scene.
    """

    origin: Tensor
    direction: Tensor
    valid: Tensor

    def plucker(self) -> Tensor:
        """Plücker coordinates ``(..., 6)`` = ``(d, m)`` with ``m = o x d``."""
        return torch.cat([self.direction, torch.linalg.cross(self.origin, self.direction, dim=-1)], dim=-1)

    def at(self, t: Tensor) -> Tensor:
        """Points ``origin + t * direction``; ``t``: ``(...)`` range along the ray."""
        return self.origin + t.unsqueeze(-1) * self.direction

    def reshape(self, *shape: int) -> "Rays":
        return Rays(self.origin.reshape(*shape, 3), self.direction.reshape(*shape, 3), self.valid.reshape(*shape))


def pixel_grid(width: int, height: int, dtype: torch.dtype = torch.float32,
               device: torch.device | str | None = None) -> Tensor:
    """Pixel centres of a ``width x height`` image: ``(H, W, 2)`` with ``(u, v) = (j + .5, i + .5)``."""
    u = torch.arange(width, dtype=dtype, device=device) + 0.5
    v = torch.arange(height, dtype=dtype, device=device) + 0.5
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack([uu, vv], dim=-1)


def in_image(uv: Tensor, width: float, height: float) -> Tensor:
    """``(...)`` bool: pixel ``uv (..., 2)`` lies inside ``[0, W) x [0, H)``."""
    u, v = uv[..., 0], uv[..., 1]
    return (u >= 0) & (u < width) & (v >= 0) & (v < height) & torch.isfinite(u) & torch.isfinite(v)


def safe_norm(x: Tensor, dim: int = -1, keepdim: bool = False, eps: float = 1e-30) -> Tensor:
    """Euclidean norm whose gradient is finite at 0 (returns ``sqrt(|x|^2 + eps)``-like values only at 0)."""
    sq = (x * x).sum(dim=dim, keepdim=keepdim)
    zero = sq <= eps
    return torch.where(zero, torch.zeros_like(sq), torch.sqrt(torch.where(zero, torch.ones_like(sq), sq)))


def normalize(x: Tensor, dim: int = -1) -> Tensor:
    """Unit vectors along ``dim``; zero vectors map to zero (finite gradient)."""
    n = safe_norm(x, dim=dim, keepdim=True)
    return x / torch.where(n > 0, n, torch.ones_like(n))


def _finite_where_invalid(x: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
    """``valid & all(isfinite(x), -1)`` and ``x`` with its non-finite entries set to 0 (``x (..., k)``)."""
    fin = torch.isfinite(x)
    return torch.where(fin, x, torch.zeros((), dtype=x.dtype, device=x.device)), valid & fin.all(-1)


def _finite_project(fn):
    @functools.wraps(fn)
    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        uv, valid = fn(self, points)
        return _finite_where_invalid(uv, valid)
    project._finite = True  # type: ignore[attr-defined]
    return project


def _finite_unproject(fn):
    @functools.wraps(fn)
    def unproject(self, uv: Tensor) -> Rays:
        rays = fn(self, uv)
        origin, valid = _finite_where_invalid(rays.origin, rays.valid)
        direction, valid = _finite_where_invalid(rays.direction, valid)
        return Rays(origin, direction, valid)
    unproject._finite = True  # type: ignore[attr-defined]
    return unproject


@dataclass(frozen=True)
class Camera:
    """Base class of every projection model.

    Subclasses are frozen dataclasses holding the calibration (``width`` and
    ``height`` are the image size in pixels) and implement :meth:`project` and
    :meth:`unproject`. Registered subclasses (see :func:`omnidl.cameras.register_camera`)
    also implement :meth:`example`, a typical instance used by the registry-wide tests.
    """

    #: every ray passes through the origin
    central: ClassVar[bool] = True
    #: registry name, set by ``register_camera``
    name: ClassVar[str] = ""
    #: parameter domains (field -> :class:`~omnidl.cameras.validate.Domain`) beyond "finite"; see
    #: :mod:`omnidl.cameras.validate`
    domains: ClassVar[Mapping[str, Domain]] = {}

    width: int
    height: int

    def __post_init__(self) -> None:
        check_types(self)
        check_domains(self)

    def __init_subclass__(cls, **kwargs: Any) -> None:
        # a family's own __post_init__ runs between the shared type/finiteness check and the domain check,
        # so every subclass is validated by the one layer in omnidl.cameras.validate; its project/unproject
        # are wrapped so that non-finite results are invalid and invalid results finite (the contract above)
        super().__init_subclass__(**kwargs)
        for attr, wrap in (("project", _finite_project), ("unproject", _finite_unproject)):
            fn = cls.__dict__.get(attr)
            if fn is not None and not getattr(fn, "_finite", False):
                setattr(cls, attr, wrap(fn))
        own = cls.__dict__.get("__post_init__")
        if own is not None and not getattr(own, "_validated", False):
            @functools.wraps(own)
            def __post_init__(self, _own=own) -> None:
                check_types(self)
                _own(self)
                check_domains(self)
            __post_init__._validated = True  # type: ignore[attr-defined]
            cls.__post_init__ = __post_init__  # type: ignore[method-assign]

    # -- the interface -----------------------------------------------------------------
    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """``points (..., 3)`` camera frame -> ``uv (..., 2)`` pixels, ``valid (...)`` bool."""
        raise NotImplementedError

    def unproject(self, uv: Tensor) -> Rays:
        """``uv (..., 2)`` pixels -> :class:`Rays` of shape ``(...)``."""
        raise NotImplementedError

    @property
    def wraps_horizontally(self) -> bool:
        """True when column ``W`` is column ``0`` again (full 360° longitude range)."""
        return False

    @property
    def panoramic(self) -> bool:
        """True for panoramas (columns are longitudes, rows latitudes about a vertical axis): kernels of
        projected convolutions stay upright there instead of turning about the optical axis. Default:
        :attr:`wraps_horizontally`; longitude–latitude models say ``True`` even for a partial range."""
        return self.wraps_horizontally

    # -- derived helpers ------------------------------------------------------------------
    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)``."""
        return self.width, self.height

    def pixel_grid(self, dtype: torch.dtype = torch.float32, device=None) -> Tensor:
        """``(H, W, 2)`` pixel centres."""
        return pixel_grid(self.width, self.height, dtype, device)

    def unproject_grid(self, dtype: torch.dtype = torch.float32, device=None) -> Rays:
        """Rays of every pixel centre, shape ``(H, W)``."""
        return self.unproject(self.pixel_grid(dtype, device))

    def resized(self, width: int, height: int, pad_right: int = 0, pad_bottom: int = 0) -> "Camera":
        """The same optics seen on a ``width x height`` feature map.

        The calibrated image (``self.width x self.height``) is assumed padded on the
        right/bottom by ``pad_right``/``pad_bottom`` pixels before the network, and the
        feature map spans the padded image. With ``s = (W + p_w) / W_FM`` every pixel
        coordinate is divided by ``s`` (thesis Eq. 7.3: ``f_k = f (W_FM - p_w/s) / W_c
        = f / s``, the same for the principal point). Padded areas are invalid.
        """
        width, height, pad_right, pad_bottom = _resize_args(self, width, height, pad_right, pad_bottom)
        return ResizedCamera(base=self, width=width, height=height,
                             scale_x=width / (self.width + pad_right),
                             scale_y=height / (self.height + pad_bottom))

    def replace(self, **changes: Any) -> "Camera":
        """A copy with some fields changed (dataclasses.replace)."""
        return dataclasses.replace(self, **changes)

    def to_config(self) -> dict:
        """A plain dict that :func:`omnidl.cameras.build` turns back into this camera."""
        cfg = {"type": self.name}
        for f in dataclasses.fields(self):
            val = getattr(self, f.name)
            if isinstance(val, Camera):
                val = val.to_config()
            elif isinstance(val, tuple):
                val = list(val)
            cfg[f.name] = val
        return cfg

    @classmethod
    def example(cls) -> "Camera":
        """A typical instance for tests and docs."""
        raise NotImplementedError

    @classmethod
    def examples(cls) -> list["Camera"]:
        """Every variant the registry-wide tests should exercise (default: ``[example()]``).

        Models with discrete variants (fisheye lenses, mirror shapes) return one instance per variant.
        """
        return [cls.example()]

    def sample_points(self, n: int, dtype: torch.dtype = torch.float64, generator: torch.Generator | None = None,
                      margin: float = 0.02) -> Tensor:
        """``(n, 2)`` random pixels inside the valid image area (for tests and sampling).

        Pixels are drawn uniformly in the image shrunk by ``margin`` of its size and
        kept where ``unproject`` says they are valid.
        """
        out = []
        total = 0
        while total < n:
            r = torch.rand(4 * n + 16, 2, dtype=dtype, generator=generator)
            uv = torch.stack([(margin + (1 - 2 * margin) * r[:, 0]) * self.width,
                              (margin + (1 - 2 * margin) * r[:, 1]) * self.height], -1)
            uv = uv[self.unproject(uv).valid]
            out.append(uv)
            total += len(uv)
        return torch.cat(out)[:n]


def _resize_args(camera: Camera, width: Any, height: Any, pad_right: Any, pad_bottom: Any) -> tuple[Any, ...]:
    """Checked ``resized()`` arguments: sizes positive integers; pads finite (negative crops) leaving >= 1 pixel."""
    who = f"{family_name(camera)}: resized({width!r}, {height!r})"
    w, h = check_size(who, width, height)
    for key, pad, side in (("pad_right", pad_right, camera.width), ("pad_bottom", pad_bottom, camera.height)):
        if isinstance(pad, bool) or not isinstance(pad, numbers.Real) or not math.isfinite(pad) or side + pad < 1:
            raise ValueError(f"{who}: {key} must be a finite number of pixels leaving at least 1 pixel of the "
                             f"{side}-pixel side, got {pad!r}")
    return w, h, pad_right, pad_bottom


@dataclass(frozen=True)
class ResizedCamera(Camera):
    """``base`` seen on a resized (and possibly padded) image: pixel coordinates scale by ``(scale_x, scale_y)``."""

    name: ClassVar[str] = "resized"
    domains: ClassVar[Mapping[str, Domain]] = {"scale_x": Domain(0.0), "scale_y": Domain(0.0)}
    base: Camera = None  # type: ignore[assignment]
    scale_x: float = 1.0
    scale_y: float = 1.0

    @property
    def central(self) -> bool:  # type: ignore[override]
        return self.base.central

    @property
    def wraps_horizontally(self) -> bool:
        return self.base.wraps_horizontally and abs(self.scale_x * self.base.width - self.width) < 1e-9

    @property
    def panoramic(self) -> bool:  # type: ignore[override]
        return self.wraps_horizontally or self.base.panoramic

    def __post_init__(self) -> None:
        if not isinstance(self.base, Camera):
            raise ValueError(f"resized camera: base must be a Camera, got {self.base!r}")

    def _scale(self, like: Tensor) -> Tensor:
        return torch.tensor([self.scale_x, self.scale_y], dtype=like.dtype, device=like.device)

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        uv, valid = self.base.project(points)
        uv = uv * self._scale(uv)
        return uv, valid & in_image(uv, self.width, self.height)

    def unproject(self, uv: Tensor) -> Rays:
        rays = self.base.unproject(uv / self._scale(uv))
        return rays._replace(valid=rays.valid & in_image(uv, self.width, self.height))

    def resized(self, width: int, height: int, pad_right: int = 0, pad_bottom: int = 0) -> Camera:
        width, height, pad_right, pad_bottom = _resize_args(self, width, height, pad_right, pad_bottom)
        sx = width / (self.width + pad_right)
        sy = height / (self.height + pad_bottom)
        return ResizedCamera(base=self.base, width=width, height=height,
                             scale_x=self.scale_x * sx, scale_y=self.scale_y * sy)

    @classmethod
    def example(cls) -> Camera:
        from .equirectangular import Equirectangular
        return Equirectangular(width=64, height=32).resized(32, 16)
