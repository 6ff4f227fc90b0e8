"""Model conversion: fit a camera family to another camera's rays (non-linear least squares).

Given a central ``source`` camera, :func:`fit` samples a grid of pixels over the source's valid image,
unprojects them with the source (rays ``d_i`` for pixels ``p_i``) and finds the target family's
parameters ``theta`` minimising the reprojection error in pixels::

    min_theta  sum_i | project_theta(d_i) - p_i |^2          (scipy.optimize.least_squares, TRF)

The target keeps the source's ``width``/``height``. Every float field of the target is fitted except
``width``, ``height``, ``max_fov`` (set to cover the sampled rays), the fields in ``fixed`` and fields
that only rescale another one (Kannala–Brandt's ``k0`` next to ``fx, fy``: cv2.fisheye's ``k0 = 1``).
Non-float fields (a lens name, a polynomial tuple) keep their given/default value. Starting values:
``**init``, else the principal point and the focal length measured on the source for fields named
``cx, cy`` and ``fx, fy, f``, else the dataclass defaults (or the family's ``example()``); the fit is
repeated from the shape parameters of each ``examples()`` instance and the best one kept.

Uses: a tool that only speaks Double Sphere given a Kannala–Brandt calibration, unified -> KB, etc.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from .base import Camera
from .registry import construct, get_camera_class

#: fields that only rescale others (fitting both would leave the problem rank deficient)
REDUNDANT_FIELDS: dict[str, tuple[str, ...]] = {"kannala_brandt": ("k0",)}
#: fields whose start is measured on the source (principal point, focal length), never taken from examples
_SCALE_FIELDS = ("cx", "cy", "fx", "fy", "f")
#: per-component residual of a parameter vector the family rejects (its ``__post_init__`` raises)
_REJECTED = 1e4


@dataclass(frozen=True)
class FitReport:
    """How well the fitted camera reproduces the source's rays.

    Attributes:
        family: the target family's registry name.
        rms_px, max_px: RMS / max reprojection error in pixels over all samples.
        num_samples: number of sampled source pixels (valid rays of the source).
        num_invalid: samples the fitted camera does not project as valid (outside its field of view or
            its image; a border sample may land just outside the image by its error).
        fitted: names of the fitted fields.
        success, message: scipy's convergence flag and message.
    """

    family: str
    rms_px: float
    max_px: float
    num_samples: int
    num_invalid: int
    fitted: tuple[str, ...]
    success: bool
    message: str


def _sample_rays(source: Camera, grid: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(uv (N, 2), directions (N, 3))`` on a ``grid``-wide lattice of pixel centres, valid rays only."""
    nu = max(2, int(grid))
    nv = max(2, round(grid * source.height / source.width))
    u = torch.linspace(0.5, source.width - 0.5, nu, dtype=torch.float64)
    v = torch.linspace(0.5, source.height - 0.5, nv, dtype=torch.float64)
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    uv = torch.stack([uu, vv], -1).reshape(-1, 2)
    rays = source.unproject(uv)
    return uv[rays.valid], rays.direction[rays.valid]


def _examples(cls: type) -> list[Camera]:
    try:
        return list(cls.examples())
    except NotImplementedError:
        return []


def _start_values(cls: type, source: Camera, dirs: torch.Tensor, init: dict[str, Any]) -> dict[str, Any]:
    fields = [f for f in dataclasses.fields(cls)]
    example = None
    start: dict[str, Any] = {"width": source.width, "height": source.height}
    for f in fields:
        if f.name in start:
            continue
        if f.default is not dataclasses.MISSING:
            start[f.name] = f.default
        elif f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
            start[f.name] = f.default_factory()  # type: ignore[misc]
        else:
            example = example or cls.example()
            start[f.name] = getattr(example, f.name)
    # principal point and focal length measured on the source (pixels per radian near the axis)
    axis = torch.tensor([[0.0, 0.0, 1.0], [1e-4, 0.0, 1.0], [0.0, 1e-4, 1.0]], dtype=torch.float64)
    uv, ok = source.project(axis)
    if bool(ok.all()):
        c = uv[0]
        fx, fy = float(uv[1, 0] - c[0]) / 1e-4, float(uv[2, 1] - c[1]) / 1e-4
        guess = dict(zip(_SCALE_FIELDS, (float(c[0]), float(c[1]), fx, fy, 0.5 * (fx + fy))))
    else:
        guess = {"cx": source.width / 2, "cy": source.height / 2}
    for name, val in guess.items():
        if name in start and isinstance(start[name], float) and math.isfinite(val):
            start[name] = val
    if "max_fov" in start:
        theta = torch.atan2(torch.linalg.norm(dirs[:, :2], dim=-1), dirs[:, 2])
        start["max_fov"] = min(2 * math.pi, 2 * float(theta.max()) * 1.01)
    start.update(init)
    return start


def fit(family: str | type, source: Camera, *, grid: int = 48, fixed: tuple[str, ...] = (),
        restarts: bool = True, max_nfev: int | None = None, **init: Any) -> tuple[Camera, FitReport]:
    """Fit camera ``family`` to the rays of the central ``source`` camera.

    Args:
        family: a registered camera name (:func:`omnidl.cameras.list_cameras`) or a camera class.
        source: the camera to imitate (central; any registered model, resized or not).
        grid: samples per image row (a ``grid x grid * H / W`` lattice of pixel centres, borders included;
            only pixels the source sees are used).
        fixed: more field names to keep at their starting value.
        restarts: also start from the shape parameters of each of the family's ``examples()`` and keep
            the best fit (local minima exist, e.g. Double Sphere's ``xi < 0`` branch).
        max_nfev: limit on residual evaluations (scipy's default when None).
        **init: starting (or, with ``fixed``, fixed) values of the target's fields.

    Returns:
        ``(camera, report)``: the fitted camera (``width x height`` of the source) and a :class:`FitReport`.

    Raises:
        ValueError: a non-central source, a source with fewer valid samples than parameters, a family
            with no float field to fit, or unknown field names in ``init``/``fixed``.
    """
    from scipy.optimize import least_squares

    cls = get_camera_class(family) if isinstance(family, str) else family
    name = getattr(cls, "name", "") or cls.__name__
    if not source.central:
        raise ValueError(f"fit: the source camera {type(source).__name__} is not central; only central cameras' "
                         "rays can be fitted")
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted((set(init) | set(fixed)) - names)
    if unknown:
        raise ValueError(f"fit {name!r}: unknown field(s) {unknown}; expected some of {sorted(names)}")
    uv_src, dirs = _sample_rays(source, grid)
    start = _start_values(cls, source, dirs, dict(init))
    keep = {"width", "height", "max_fov", *fixed, *REDUNDANT_FIELDS.get(name, ())}
    free = [f.name for f in dataclasses.fields(cls)
            if f.name not in keep and isinstance(start[f.name], float) and f.type in ("float", float)]
    if not free:
        raise ValueError(f"fit {name!r}: no float field to fit (fields {sorted(names)}, fixed {sorted(keep)})")
    if len(uv_src) < len(free):
        raise ValueError(f"fit {name!r}: the source has {len(uv_src)} valid samples for {len(free)} parameters; "
                         "raise grid")
    target = uv_src.numpy().reshape(-1)

    def camera(x: np.ndarray) -> Camera:
        return construct(cls, {**start, **{k: float(v) for k, v in zip(free, x)}})

    def residual(x: np.ndarray) -> np.ndarray:
        try:
            cam = camera(x)
        except ValueError:
            return np.full_like(target, _REJECTED)
        uv, _ = cam.project(dirs)
        r = uv.detach().numpy().reshape(-1) - target
        return np.nan_to_num(r, nan=_REJECTED, posinf=_REJECTED, neginf=-_REJECTED)

    # starts: the defaults, then the shape parameters of each of the family's examples (their scale
    # fields cx, cy, fx, fy, f stay the source's): the fits can have local minima (Double Sphere's xi < 0)
    starts = [np.array([start[k] for k in free], dtype=np.float64)]
    if restarts:
        for ex in _examples(cls):
            x = np.array([start[k] if k in _SCALE_FIELDS or k in init else float(getattr(ex, k)) for k in free])
            if not any(np.array_equal(x, y) for y in starts):
                starts.append(x)
    sol = None
    for x0 in starts:
        if not np.all(np.abs(residual(x0)) < _REJECTED):
            continue
        s = least_squares(residual, x0, x_scale="jac", method="trf", ftol=1e-12, xtol=1e-12, gtol=1e-12,
                          max_nfev=max_nfev)
        if sol is None or s.cost < sol.cost:
            sol = s
    if sol is None:
        raise ValueError(f"fit {name!r}: the family rejects every starting value ({dict(zip(free, starts[0]))}); "
                         "give valid starting values as keyword arguments")
    cam = camera(sol.x)
    uv, valid = cam.project(dirs)
    err = torch.linalg.norm(uv - uv_src, dim=-1)
    report = FitReport(family=name, rms_px=float(err.square().mean().sqrt()), max_px=float(err.max()),
                       num_samples=len(uv_src),
                       num_invalid=int((~valid).sum()), fitted=tuple(free), success=bool(sol.success),
                       message=str(sol.message))
    return cam, report
