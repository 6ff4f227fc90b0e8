"""Plücker lines against point-based closed forms and brute-force searches."""
import math

import pytest
import torch

from omnidl.cameras import Equirectangular
from omnidl.geometry import plucker as P

D = torch.float64


def rand_points(n, gen, scale=3.0):
    return scale * (2 * torch.rand(n, 3, generator=gen, dtype=D) - 1)


def brute_distance(pa, da, pb, db, ts):
    """min over a dense (t, s) grid of |pa + t da - pb - s db|."""
    A = pa[None] + ts[:, None] * da[None]  # (T, 3)
    B = pb[None] + ts[:, None] * db[None]
    return torch.cdist(A, B).min()


def test_construction_and_identity(gen):
    p, q = rand_points(20, gen), rand_points(20, gen)
    L = P.line_from_points(p, q)
    assert torch.allclose(L[:, :3].norm(dim=-1), torch.ones(20, dtype=D))
    assert P.plucker_identity(L).abs().max() < 1e-13
    assert P.point_line_distance(p, L).max() < 1e-12 and P.point_line_distance(q, L).max() < 1e-12
    assert P.point_line_distance((p + q) / 2, L).max() < 1e-12
    L2 = P.line_from_point_direction(p, 2.5 * (q - p))
    assert torch.allclose(L, L2, atol=1e-12)
    # the point closest to the origin is on the line and orthogonal to d
    c = P.point_on_line(L)
    assert P.point_line_distance(c, L).max() < 1e-12
    assert (c * L[:, :3]).sum(-1).abs().max() < 1e-12
    # |m| / |d| = distance to the origin
    assert torch.allclose(L[:, 3:].norm(dim=-1), c.norm(dim=-1))
    # scale invariance of normalisation (and sign flips orientation only)
    assert torch.allclose(P.normalize_line(-3.0 * L), -L)


def test_point_line_distance_closed_form(gen):
    p, q, x = rand_points(50, gen), rand_points(50, gen), rand_points(50, gen)
    L = P.line_from_points(p, q, normalize=False)
    d = q - p
    t = ((x - p) * d).sum(-1, keepdim=True) / (d * d).sum(-1, keepdim=True)
    ref = (x - (p + t * d)).norm(dim=-1)
    assert torch.allclose(P.point_line_distance(x, L), ref, atol=1e-12)
    foot, _ = P.project_point(x, L)
    assert torch.allclose(foot, p + t * d, atol=1e-12)


def test_side_operator(gen):
    p, q, r = rand_points(30, gen), rand_points(30, gen), rand_points(30, gen)
    # lines through a common point intersect: side = 0
    assert P.side(P.line_from_points(p, q), P.line_from_points(p, r)).abs().max() < 1e-12
    # skew lines: |side| = distance * sin(angle) for unit directions, sign flips with orientation
    a, b = P.line_from_points(p, q), P.line_from_points(r, rand_points(30, gen))
    cp = P.closest_points_lines(a, b)
    sin = torch.linalg.cross(a[:, :3], b[:, :3], dim=-1).norm(dim=-1)
    assert torch.allclose(P.side(a, b).abs(), cp.distance * sin, atol=1e-10)
    assert torch.allclose(P.side(a, -b), -P.side(a, b))
    assert torch.allclose(P.side(a, b), P.side(b, a))


def test_line_distance_and_closest_points(gen):
    p, q, r, s = (rand_points(8, gen) for _ in range(4))
    a, b = P.line_from_points(p, q), P.line_from_points(r, s)
    cp = P.closest_points_lines(a, b)
    dist = P.line_distance(a, b)
    assert torch.allclose(cp.distance, dist, atol=1e-10)
    # the connecting segment is orthogonal to both lines, its ends lie on the lines
    seg = cp.point_b - cp.point_a
    assert (seg * a[:, :3]).sum(-1).abs().max() < 1e-10 and (seg * b[:, :3]).sum(-1).abs().max() < 1e-10
    assert P.point_line_distance(cp.point_a, a).max() < 1e-10 and P.point_line_distance(cp.point_b, b).max() < 1e-10
    # brute force over a dense parameter grid
    ts = torch.linspace(-30, 30, 1201, dtype=D)
    for i in range(3):
        ref = brute_distance(P.point_on_line(a[i]), a[i, :3], P.point_on_line(b[i]), b[i, :3], ts)
        assert dist[i] <= ref + 1e-12 and ref - dist[i] < 5e-2


def test_parallel_lines(gen):
    p, off = rand_points(10, gen), rand_points(10, gen)
    d = rand_points(10, gen)
    a = P.line_from_point_direction(p, d)
    b = P.line_from_point_direction(p + off, -2 * d)  # parallel, opposite orientation
    perp = off - (off * d).sum(-1, keepdim=True) * d / (d * d).sum(-1, keepdim=True)
    assert torch.allclose(P.line_distance(a, b), perp.norm(dim=-1), atol=1e-10)
    cp = P.closest_points_lines(a, b)
    assert cp.parallel.all()
    assert torch.allclose(cp.distance, perp.norm(dim=-1), atol=1e-10)


def test_closest_points_line_ray(gen):
    p, q = rand_points(6, gen), rand_points(6, gen)
    line = P.line_from_points(p, q)
    origin = rand_points(6, gen)
    direction = rand_points(6, gen)
    cp = P.closest_points_line_ray(line, (origin, direction))
    assert (cp.t_b >= 0).all()
    ts = torch.linspace(0, 20, 1001, dtype=D)
    tl = torch.linspace(-25, 25, 2501, dtype=D)
    dn = direction / direction.norm(dim=-1, keepdim=True)
    for i in range(6):
        R = origin[i] + ts[:, None] * dn[i]
        Lp = P.point_on_line(line[i]) + tl[:, None] * line[i, :3]
        ref = torch.cdist(R, Lp).min()
        assert cp.distance[i] <= ref + 1e-12 and ref - cp.distance[i] < 2e-2
    # a ray pointing away from the line: the closest point is its origin
    o = torch.tensor([0.0, 0.0, 2.0], dtype=D)
    L = P.line_from_point_direction(torch.zeros(3, dtype=D), torch.tensor([1.0, 0, 0], dtype=D))
    cp = P.closest_points_line_ray(L, (o, torch.tensor([0.0, 0.3, 1.0], dtype=D)))
    assert cp.t_b == 0 and torch.allclose(cp.point_b, o) and torch.allclose(cp.distance, torch.tensor(2.0, dtype=D))
    # camera Rays are accepted
    cam = Equirectangular(width=8, height=4)
    rays = cam.unproject_grid(dtype=D)
    cp = P.closest_points_line_ray(L, rays)
    assert cp.distance.shape == (4, 8) and torch.isfinite(cp.distance).all()


def test_transform_line(gen):
    from omnidl.geometry.rotations import random_rotation
    p, q = rand_points(10, gen), rand_points(10, gen)
    R = random_rotation(10, generator=gen, dtype=D)
    t = rand_points(10, gen)
    moved = P.transform_line(P.line_from_points(p, q), R, t)
    ref = P.line_from_points((R @ p[..., None])[..., 0] + t, (R @ q[..., None])[..., 0] + t)
    assert torch.allclose(moved, ref, atol=1e-12)


def test_lines_from_rays_and_float32(gen):
    cam = Equirectangular(width=8, height=4)
    rays = cam.unproject_grid(dtype=torch.float32)
    L = P.lines_from_rays(rays)
    assert L.shape == (4, 8, 6) and L.dtype == torch.float32 and (L[..., 3:] == 0).all()
    with pytest.raises(ValueError, match="6"):
        P.side(torch.zeros(3, 5), torch.zeros(3, 6))
    p, q = rand_points(5, gen).float(), rand_points(5, gen).float()
    assert P.point_line_distance(p, P.line_from_points(p, q)).max() < 1e-5


def test_gradcheck(gen):
    p, q, r, s = (rand_points(3, gen).requires_grad_() for _ in range(4))
    x = rand_points(3, gen).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b, c, d: P.line_distance(P.line_from_points(a, b),
                                                                       P.line_from_points(c, d)), (p, q, r, s))
    assert torch.autograd.gradcheck(lambda a, b, c: P.point_line_distance(c, P.line_from_points(a, b)), (p, q, x))
    assert torch.autograd.gradcheck(lambda a, b, c, d: P.closest_points_lines(P.line_from_points(a, b),
                                                                              P.line_from_points(c, d)).point_a,
                                    (p, q, r, s))
    # finite gradients where a point lies on the line (distance 0)
    a = torch.zeros(3, dtype=D, requires_grad=True)
    L = P.line_from_points(torch.tensor([-1.0, 0, 0], dtype=D), torch.tensor([1.0, 0, 0], dtype=D))
    P.point_line_distance(a, L).backward()
    assert torch.isfinite(a.grad).all()
    assert not math.isnan(float(P.line_distance(L, L)))


def test_broadcasting(gen):
    """One line against many points / lines (leading dims broadcast)."""
    p, q = rand_points(1, gen)[0], rand_points(1, gen)[0]
    line = P.line_from_points(p, q)  # (6,)
    t = torch.linspace(-2, 3, 7, dtype=D)[:, None]
    X = p + t * (q - p)  # (7, 3) on the line
    assert P.point_line_distance(X, line).shape == (7,) and P.point_line_distance(X, line).max() < 1e-12
    others = P.line_from_points(rand_points(5, gen), rand_points(5, gen))
    assert P.line_distance(line, others).shape == (5,)
    assert P.closest_points_lines(line, others).point_a.shape == (5, 3)
    assert P.line_from_point_direction(X, q - p).shape == (7, 6)
