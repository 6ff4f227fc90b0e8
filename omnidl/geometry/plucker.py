"""Plücker coordinates of 3D lines (thesis §2.2.1).

A line is a ``(..., 6)`` tensor ``L = (d, m)``: ``d`` the direction, ``m = p x d`` the moment
for any point ``p`` on the line (``m`` is normal to the plane through the line and the
origin, ``|m| / |d|`` is the line's distance to the origin). ``L`` and ``s * L`` (``s != 0``)
are the same line (orientation flips for ``s < 0``); :func:`normalize_line` scales ``|d|`` to 1.
Every line satisfies the Plücker identity ``d . m = 0`` (the Klein quadric).

Camera rays (:class:`omnidl.cameras.Rays`) give lines through ``Rays.plucker()``; central
cameras have ``m = 0``. All functions are batched over leading dimensions, work in
float32/float64 on any device and are differentiable (parallel/degenerate branches use
safe substitutes so gradients stay finite).
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from omnidl.cameras.base import Rays, safe_norm

_PARALLEL_EPS = 1e-12


def _cross(a: Tensor, b: Tensor) -> Tensor:
    """Cross product over the last dim with full broadcasting of the leading dims."""
    a, b = torch.broadcast_tensors(a, b)
    return torch.linalg.cross(a, b)


def _check(line: Tensor, name: str = "line") -> Tensor:
    if line.shape[-1] != 6:
        raise ValueError(f"{name} must have shape (..., 6) = (direction, moment), got {tuple(line.shape)}")
    return line


def split(line: Tensor) -> tuple[Tensor, Tensor]:
    """``(..., 6)`` -> direction ``(..., 3)``, moment ``(..., 3)``."""
    _check(line)
    return line[..., :3], line[..., 3:]


def line_from_points(p: Tensor, q: Tensor, normalize: bool = True) -> Tensor:
    """The line through ``p`` and ``q`` (``(..., 3)`` each), oriented from ``p`` to ``q``: ``(q - p, p x q)``."""
    line = torch.cat([q - p, _cross(p, q)], -1)
    return normalize_line(line) if normalize else line


def line_from_point_direction(point: Tensor, direction: Tensor, normalize: bool = True) -> Tensor:
    """The line through ``point`` along ``direction`` (``(..., 3)`` each): ``(d, p x d)``."""
    point, direction = torch.broadcast_tensors(point, direction)
    line = torch.cat([direction, _cross(point, direction)], -1)
    return normalize_line(line) if normalize else line


def lines_from_rays(rays: Rays | Tensor) -> Tensor:
    """Plücker lines ``(..., 6)`` of :class:`Rays` (a ``(..., 6)`` tensor passes through)."""
    if isinstance(rays, Rays):
        return rays.plucker()
    return _check(rays, "rays")


def normalize_line(line: Tensor) -> Tensor:
    """Scale ``line`` so that ``|d| = 1`` (a line at infinity, ``d = 0``, is scaled to ``|m| = 1``)."""
    d, m = split(line)
    nd = safe_norm(d, keepdim=True)
    nm = safe_norm(m, keepdim=True)
    scale = torch.where(nd > 0, nd, torch.where(nm > 0, nm, torch.ones_like(nm)))
    return line / scale


def plucker_identity(line: Tensor) -> Tensor:
    """``d . m`` ``(...)``: zero for every real line (the Klein quadric)."""
    d, m = split(line)
    return (d * m).sum(-1)


def side(a: Tensor, b: Tensor) -> Tensor:
    """Side operator / reciprocal product ``d_a . m_b + m_a . d_b`` ``(...)``.

    Zero iff the two lines intersect (or are parallel). For unit directions its absolute
    value is ``distance * sin(angle)`` between the lines; its sign tells on which side
    (handedness) ``b`` passes ``a``.
    """
    da, ma = split(a)
    db, mb = split(b)
    return (da * mb).sum(-1) + (ma * db).sum(-1)


def point_on_line(line: Tensor) -> Tensor:
    """The point of ``line`` closest to the origin ``(..., 3)``: ``d x m / |d|^2``."""
    d, m = split(line)
    dd = (d * d).sum(-1, keepdim=True)
    return _cross(d, m) / torch.where(dd > 0, dd, torch.ones_like(dd))


def point_line_distance(points: Tensor, line: Tensor) -> Tensor:
    """Distance ``(...)`` from ``points (..., 3)`` to ``line (..., 6)``: ``|X x d - m| / |d|``."""
    d, m = split(line)
    nd = safe_norm(d)
    return safe_norm(_cross(points, d) - m) / torch.where(nd > 0, nd, torch.ones_like(nd))


def project_point(points: Tensor, line: Tensor) -> tuple[Tensor, Tensor]:
    """Orthogonal projection of ``points`` onto ``line``: ``(foot (..., 3), t (...))`` with
    ``foot = point_on_line(line) + t * d / |d|``."""
    ln = normalize_line(line)
    d, _ = split(ln)
    p0 = point_on_line(ln)
    t = ((points - p0) * d).sum(-1)
    return p0 + t.unsqueeze(-1) * d, t


def line_distance(a: Tensor, b: Tensor) -> Tensor:
    """Shortest distance ``(...)`` between two lines (parallel lines included)."""
    a, b = normalize_line(a), normalize_line(b)
    da, ma = split(a)
    db, mb = split(b)
    cross = _cross(da, db)
    sin = safe_norm(cross)
    parallel = sin <= torch.finfo(sin.dtype).eps ** 0.5  # |side| / sin is ill-conditioned there
    skew = side(a, b).abs() / torch.where(parallel, torch.ones_like(sin), sin)
    sgn = torch.where((da * db).sum(-1, keepdim=True) < 0, -torch.ones_like(sin).unsqueeze(-1),
                      torch.ones_like(sin).unsqueeze(-1))
    par = safe_norm(_cross(da, ma - sgn * mb))
    return torch.where(parallel, par, skew)


class ClosestPoints(NamedTuple):
    """Closest points between two lines (or a line and a ray).

    Attributes:
        point_a, point_b: ``(..., 3)`` closest points on the first / second object.
        t_a, t_b: ``(...)`` their signed positions along each object's unit direction, from
            :func:`point_on_line` for lines and from the origin for rays.
        distance: ``(...)`` ``|point_a - point_b|``.
        parallel: ``(...)`` bool, the directions are parallel (the closest pair is not unique;
            ``point_a`` is then the point of ``a`` closest to the origin, or the ray's origin).
    """

    point_a: Tensor
    point_b: Tensor
    t_a: Tensor
    t_b: Tensor
    distance: Tensor
    parallel: Tensor


def _closest_params(pa: Tensor, da: Tensor, pb: Tensor, db: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Parameters ``(ta, tb)`` of the closest points of ``pa + ta da`` and ``pb + tb db`` (unit d's)."""
    n = _cross(da, db)
    nn2 = (n * n).sum(-1)
    parallel = nn2 <= _PARALLEL_EPS
    safe = torch.where(parallel, torch.ones_like(nn2), nn2)
    w = pb - pa
    ta = (_cross(w, db) * n).sum(-1) / safe
    tb = (_cross(w, da) * n).sum(-1) / safe
    # parallel: keep a's reference point, project it on b
    tb_par = ((pa - pb) * db).sum(-1)
    ta = torch.where(parallel, torch.zeros_like(ta), ta)
    tb = torch.where(parallel, tb_par, tb)
    return ta, tb, parallel


def closest_points_lines(a: Tensor, b: Tensor) -> ClosestPoints:
    """Closest points between lines ``a`` and ``b`` (``(..., 6)`` each)."""
    a, b = normalize_line(a), normalize_line(b)
    da, _ = split(a)
    db, _ = split(b)
    pa, pb = point_on_line(a), point_on_line(b)
    pa, da, pb, db = torch.broadcast_tensors(pa, da, pb, db)
    ta, tb, parallel = _closest_params(pa, da, pb, db)
    qa = pa + ta.unsqueeze(-1) * da
    qb = pb + tb.unsqueeze(-1) * db
    return ClosestPoints(qa, qb, ta, tb, safe_norm(qa - qb), parallel)


def closest_points_line_ray(line: Tensor, rays: Rays | tuple[Tensor, Tensor]) -> ClosestPoints:
    """Closest points between ``line (..., 6)`` and rays ``origin + t * direction``, ``t >= 0``.

    ``rays`` is :class:`Rays` or ``(origin, direction)``. Where the unconstrained closest
    point lies behind a ray's origin, the ray's origin is used and the line point is its
    projection. ``point_a``/``t_a`` refer to the line, ``point_b``/``t_b`` to the ray.
    """
    origin, direction = (rays.origin, rays.direction) if isinstance(rays, Rays) else rays
    ln = normalize_line(line)
    dl, _ = split(ln)
    pl = point_on_line(ln)
    nd = safe_norm(direction, keepdim=True)
    dr = direction / torch.where(nd > 0, nd, torch.ones_like(nd))
    pl, dl, origin, dr = torch.broadcast_tensors(pl, dl, origin, dr)
    ta, tb, parallel = _closest_params(pl, dl, origin, dr)
    # parallel: use the ray origin as reference instead (t_b = 0)
    ta = torch.where(parallel, ((origin - pl) * dl).sum(-1), ta)
    tb = torch.where(parallel, torch.zeros_like(tb), tb)
    behind = tb < 0
    tb = torch.where(behind, torch.zeros_like(tb), tb)
    ta = torch.where(behind, ((origin - pl) * dl).sum(-1), ta)
    qa = pl + ta.unsqueeze(-1) * dl
    qb = origin + tb.unsqueeze(-1) * dr
    return ClosestPoints(qa, qb, ta, tb, safe_norm(qa - qb), parallel)


def transform_line(line: Tensor, R: Tensor, t: Tensor | None = None) -> Tensor:
    """Apply ``X -> R X + t`` to lines: ``d' = R d``, ``m' = R m + t x (R d)``.

    Args:
        line: ``(..., 6)``; R: ``(..., 3, 3)``; t: ``(..., 3)`` or ``None``.
    """
    d, m = split(line)
    d2 = torch.einsum("...ij,...j->...i", R, d)
    m2 = torch.einsum("...ij,...j->...i", R, m)
    if t is not None:
        t, d2 = torch.broadcast_tensors(t, d2)
        m2 = m2 + _cross(t, d2)
    return torch.cat(torch.broadcast_tensors(d2, m2), -1)
