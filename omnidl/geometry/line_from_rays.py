"""The 3D line through four or more projecting rays (thesis §2.2.2).

A line ``L = (l, l_bar)`` meets a ray ``Xi = (xi, xi_bar)`` iff ``side(L, Xi) = l . xi_bar +
l_bar . xi = 0``. Stacking one row ``A_i = (xi_bar_i, xi_i)`` per ray gives ``A L = 0``. With
four independent rays the null space of ``A`` (the last two right singular vectors ``L0``,
``L1``) is a pencil of 6-vectors; intersecting the pencil ``alpha L0 + beta L1`` with the Klein
quadric ``l . l_bar = 0`` is the quadratic

    a alpha^2 + b alpha beta + c beta^2 = 0,   a = l0.lb0,  b = l0.lb1 + l1.lb0,  c = l1.lb1,

whose two roots are two real lines meeting every ray. For an axial camera (non-central
panorama, non-central catadioptric) one of them is the revolution axis, which every ray
meets; the other is the sought line. We solve it in homogeneous form, so no root is ever
at infinity: ``q = -(b + sign(b) sqrt(b^2 - 4ac)) / 2``, solutions ``q L0 + a L1`` and
``c L0 + q L1``.

Degenerate configurations are detected and *reported* (never raised) in :class:`LineFit`:
fewer than four rays; all rays through one point (a central camera: its rays give at most
three independent constraints); all rays in one plane (e.g. a plane through the revolution
axis, or the plane of the circle of optical centres); other rank deficiencies; a pencil that
misses the Klein quadric (noise); both solutions equal to the axis; a line at infinity.

Everything is batched: rays ``(..., N, 6)`` give one fit per leading index (RANSAC evaluates
many candidate 4-ray samples at once).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import torch
from torch import Tensor

from omnidl.cameras.base import Rays, safe_norm

from .plucker import line_distance, normalize_line, point_line_distance, side

#: revolution axis of the non-central panorama (camera ``y``, through the origin)
Y_AXIS = (0.0, 1.0, 0.0, 0.0, 0.0, 0.0)
#: revolution axis of the non-central catadioptric cameras (camera ``z``, through the origin)
Z_AXIS = (0.0, 0.0, 1.0, 0.0, 0.0, 0.0)


class LineStatus(IntEnum):
    """Outcome codes of :func:`line_from_rays`."""

    OK = 0
    TOO_FEW_RAYS = 1
    COMMON_POINT = 2
    COPLANAR = 3
    RANK_DEFICIENT = 4
    NO_REAL_SOLUTION = 5
    AXIS_ONLY = 6
    AT_INFINITY = 7


REASONS = {
    LineStatus.OK: "ok",
    LineStatus.TOO_FEW_RAYS: "fewer than 4 valid rays",
    LineStatus.COMMON_POINT: "all rays pass through one point (central camera): the 4 constraints are dependent",
    LineStatus.COPLANAR: "all rays lie in one plane (e.g. a plane through the revolution axis or the plane of "
                         "the optical centres): the line is not determined",
    LineStatus.RANK_DEFICIENT: "the ray constraints have rank < 4",
    LineStatus.NO_REAL_SOLUTION: "the null-space pencil does not meet the Klein quadric (inconsistent rays)",
    LineStatus.AXIS_ONLY: "the only solution is the revolution axis",
    LineStatus.AT_INFINITY: "the solution is a line at infinity",
}


@dataclass
class LineFit:
    """Result of :func:`line_from_rays` (all tensors share the batch shape ``(...)``).

    Attributes:
        line: ``(..., 6)`` the line, ``|d| = 1``; zeros where ``ok`` is False.
        ok: ``(...)`` bool.
        status: ``(...)`` int64 :class:`LineStatus` codes.
        residual: ``(...)`` RMS over the valid rays of ``side(line, ray)`` with unit directions,
            i.e. ``distance * sin(angle)`` between line and ray, in metres.
        other: ``(..., 6)`` the second Klein-quadric solution (normally the revolution axis).
        singular_values: ``(..., 6)`` singular values of the (unit-ray) constraint matrix.
    """

    line: Tensor
    ok: Tensor
    status: Tensor
    residual: Tensor
    other: Tensor
    singular_values: Tensor

    @property
    def conditioning(self) -> Tensor:
        """``(...)`` ``sigma_4 / sigma_1``: how far the four strongest constraints are from dependent.

        The line's error grows roughly like (ray noise) / conditioning; short segments seen
        from far away with a small ``rc`` are ill-conditioned. Use float64 rays when it is small
        (float32 rays alone carry ~1e-7 relative rounding).
        """
        return self.singular_values[..., 3] / self.singular_values[..., 0].clamp_min(torch.finfo(
            self.singular_values.dtype).tiny)

    @property
    def reason(self) -> str | list:
        """Human-readable reason(s): a string for an unbatched fit, else nested lists."""
        codes = self.status.tolist()

        def text(c):
            return [text(x) for x in c] if isinstance(c, list) else REASONS[LineStatus(c)]
        return text(codes)


def _fit_plane_spread(points: Tensor, w: Tensor) -> Tensor:
    """Smallest RMS distance of weighted ``points (..., P, 3)`` to a plane ``(...)``."""
    n = w.sum(-1, keepdim=True).clamp_min(1)
    c = (points * w.unsqueeze(-1)).sum(-2) / n
    x = (points - c.unsqueeze(-2)) * w.unsqueeze(-1)
    s = torch.linalg.svdvals(x)
    return s[..., -1] / n.squeeze(-1).sqrt()


def _common_point(d: Tensor, o: Tensor, w: Tensor) -> Tensor:
    """Least-squares point closest to all weighted lines ``(o, d)`` ``(..., N, 3)`` -> ``(..., 3)``."""
    eye = torch.eye(3, dtype=d.dtype, device=d.device)
    P = eye - d.unsqueeze(-1) * d.unsqueeze(-2)  # (..., N, 3, 3)
    P = P * w[..., None, None]
    M = P.sum(-3)
    r = (P @ o.unsqueeze(-1)).sum(-3)
    return (torch.linalg.pinv(M) @ r).squeeze(-1)


def line_from_rays(rays: Rays | Tensor, valid: Tensor | None = None, axis: Tensor | tuple | None = Y_AXIS,
                   rank_tol: float | None = None, dist_tol: float | None = None) -> LineFit:
    """The 3D line meeting every ray (§2.2.2): SVD null space + Klein quadric, degeneracies reported.

    Args:
        rays: :class:`Rays` of shape ``(..., N)`` or Plücker rays ``(..., N, 6)`` (any direction
            length), ``N >= 4``.
        valid: ``(..., N)`` bool mask of rays to use (default: ``rays.valid`` or all).
        axis: ``(6,)`` Plücker line that every ray of the camera meets (the revolution axis);
            of the two Klein-quadric solutions the one farther from it is returned. Default:
            the camera ``y`` axis (non-central panorama). ``None``: return the first solution.
        rank_tol: relative singular-value threshold below which the constraints count as
            dependent (default ``1e-9`` in float64, ``1e-5`` in float32).
        dist_tol: relative distance threshold for "one point"/"one plane"/"is the axis"
            (default ``1e-7`` in float64, ``1e-4`` in float32), times the scene scale.

    Returns:
        :class:`LineFit`.
    """
    if isinstance(rays, Rays):
        if valid is None:
            valid = rays.valid
        rays = rays.plucker()
    if rays.dim() < 2 or rays.shape[-1] != 6:
        raise ValueError(f"rays must be Rays or a (..., N, 6) Plücker tensor, got shape {tuple(rays.shape)}")
    if not rays.is_floating_point():
        raise TypeError(f"rays must be floating point, got {rays.dtype}")
    dtype, device = rays.dtype, rays.device
    f64 = dtype == torch.float64
    rank_tol = rank_tol if rank_tol is not None else (1e-9 if f64 else 1e-5)
    dist_tol = dist_tol if dist_tol is not None else (1e-7 if f64 else 1e-4)
    batch = rays.shape[:-2]
    if valid is None:
        valid = torch.ones(rays.shape[:-1], dtype=torch.bool, device=device)
    valid = valid.expand(rays.shape[:-1])

    # unit directions; invalid or zero rays get weight 0
    rays = normalize_line(rays)
    d, m = rays[..., :3], rays[..., 3:]
    valid = valid & (safe_norm(d) > 0) & torch.isfinite(rays).all(-1)
    w = valid.to(dtype)
    A = torch.cat([m, d], -1) * w.unsqueeze(-1)  # rows (xi_bar, xi)
    n_rays = valid.sum(-1)

    _, S, Vh = torch.linalg.svd(A, full_matrices=True)
    if S.shape[-1] < 6:
        S = torch.cat([S, S.new_zeros(*S.shape[:-1], 6 - S.shape[-1])], -1)
    smax = S[..., 0].clamp_min(torch.finfo(dtype).tiny)
    dependent = S[..., 3] <= rank_tol * smax

    # scene scale: points of the rays closest to the origin
    o = torch.linalg.cross(d, m, dim=-1)  # foot points (|d| = 1)
    scale = 1.0 + ((safe_norm(o) * w).sum(-1) / w.sum(-1).clamp_min(1))
    p = _common_point(d, o, w)
    dist = (point_line_distance(p.unsqueeze(-2), rays) * w).amax(-1)
    common = dist <= dist_tol * scale
    plane_spread = _fit_plane_spread(torch.cat([o, o + d], -2), torch.cat([w, w], -1))
    coplanar = plane_spread <= dist_tol * scale

    # Klein quadric on the pencil alpha L0 + beta L1
    L0, L1 = Vh[..., 4, :], Vh[..., 5, :]
    l0, lb0, l1, lb1 = L0[..., :3], L0[..., 3:], L1[..., :3], L1[..., 3:]
    a = (l0 * lb0).sum(-1)
    b = (l0 * lb1).sum(-1) + (l1 * lb0).sum(-1)
    c = (l1 * lb1).sum(-1)
    disc = b * b - 4 * a * c
    no_real = disc < -(1e-6 if not f64 else 1e-10) * (b * b + 4 * (a * c).abs()).clamp_min(torch.finfo(dtype).tiny)
    sq = torch.sqrt(disc.clamp_min(0))
    sgn = torch.where(b < 0, -torch.ones_like(b), torch.ones_like(b))
    q = -0.5 * (b + sgn * sq)
    s1 = q.unsqueeze(-1) * L0 + a.unsqueeze(-1) * L1
    s2 = c.unsqueeze(-1) * L0 + q.unsqueeze(-1) * L1
    fallback = torch.where((a.abs() <= c.abs()).unsqueeze(-1), L0, L1)
    tiny = 1e-12 if f64 else 1e-6
    s1 = torch.where((safe_norm(s1) <= tiny).unsqueeze(-1), fallback, s1)
    s2 = torch.where((safe_norm(s2) <= tiny).unsqueeze(-1), fallback, s2)

    def finite_line(s: Tensor) -> tuple[Tensor, Tensor]:
        nd = safe_norm(s[..., :3])
        inf = nd <= tiny * safe_norm(s[..., 3:]).clamp_min(1)
        return normalize_line(s), inf

    s1, inf1 = finite_line(s1)
    s2, inf2 = finite_line(s2)

    if axis is not None:
        ax = normalize_line(torch.as_tensor(axis, dtype=dtype, device=device))
        ax = ax.expand(*batch, 6)

        def axis_likeness(s: Tensor) -> Tensor:
            cos = (s[..., :3] * ax[..., :3]).sum(-1).abs().clamp(max=1)
            return line_distance(s, ax) / scale + (1 - cos)

        k1, k2 = axis_likeness(s1), axis_likeness(s2)
        swap = k2 > k1
        line = torch.where(swap.unsqueeze(-1), s2, s1)
        other = torch.where(swap.unsqueeze(-1), s1, s2)
        inf_line = torch.where(swap, inf2, inf1)
        axis_only = torch.maximum(k1, k2) <= dist_tol
    else:
        line, other, inf_line = s1, s2, inf1
        axis_only = torch.zeros_like(inf1)

    status = torch.full(batch, int(LineStatus.OK), dtype=torch.int64, device=device)

    def mark(cond: Tensor, code: LineStatus) -> None:
        nonlocal status
        status = torch.where((status == LineStatus.OK) & cond, torch.full_like(status, int(code)), status)

    mark(n_rays < 4, LineStatus.TOO_FEW_RAYS)
    mark(dependent & common, LineStatus.COMMON_POINT)
    mark(dependent & coplanar, LineStatus.COPLANAR)
    mark(dependent, LineStatus.RANK_DEFICIENT)
    mark(no_real, LineStatus.NO_REAL_SOLUTION)
    mark(axis_only, LineStatus.AXIS_ONLY)
    mark(inf_line, LineStatus.AT_INFINITY)
    ok = status == LineStatus.OK

    res = side(line.unsqueeze(-2), rays)
    residual = torch.sqrt(((res * res) * w).sum(-1) / w.sum(-1).clamp_min(1))
    line = torch.where(ok.unsqueeze(-1), line, torch.zeros_like(line))
    return LineFit(line=line, ok=ok, status=status, residual=residual, other=other, singular_values=S)


def camera_axis(camera, max_rays: int = 400, tol: float = 1e-8) -> Tensor:
    """The line ``(6,)`` float64 that every ray of an axial (non-central) camera meets.

    Found as the null vector of the side-operator constraints of the valid rays of about
    ``max_rays`` pixels on a regular grid over the image. Raises ``ValueError`` for a central camera (its
    rays meet in a point, every line through it qualifies) or when no common line exists.
    """
    n = max(3, int(math.ceil(math.sqrt(max_rays))))
    u = (torch.arange(n, dtype=torch.float64) + 0.5) * (camera.width / n)
    v = (torch.arange(n, dtype=torch.float64) + 0.5) * (camera.height / n)
    uv = torch.stack(torch.meshgrid(u, v, indexing="xy"), -1).reshape(-1, 2)  # an n x n grid over the image
    rays = camera.unproject(uv)
    lines = normalize_line(rays.plucker()[rays.valid])
    if len(lines) < 5:
        raise ValueError(f"{type(camera).__name__}: fewer than 5 valid sample pixels, cannot find its axis")
    if bool((safe_norm(lines[:, 3:]) < 1e-12).all()):
        raise ValueError(f"{type(camera).__name__} is central: all rays meet in one point, there is no unique axis")
    A = torch.cat([lines[:, 3:], lines[:, :3]], -1)
    _, S, Vh = torch.linalg.svd(A, full_matrices=True)
    S = torch.cat([S, S.new_zeros(6 - len(S))]) if len(S) < 6 else S
    if S[5] > tol * S[0] or S[4] <= tol * S[0]:
        raise ValueError(f"{type(camera).__name__}: its rays do not meet exactly one common line "
                         f"(singular values {S.tolist()})")
    axis = normalize_line(Vh[5])
    return axis * torch.where(axis[:3].sum() < 0, -1.0, 1.0)
