"""Single-wall, Manhattan and Atlanta solvers against exact rays of known rooms (independent ray caster)."""
import math

import numpy as np
import pytest

from omnidl.apps.layout.simulate import (Room, random_manhattan_room, render_boundaries, ring_camera,
                                                simulate_columns)
from omnidl.postprocess.layout.solvers import (_quadratic_roots, atlanta_rows, manhattan_rows, ransac_iterations,
                                               solve_atlanta, solve_manhattan, solve_walls, solve_walls_central)


def _wall_truth(room, k):
    p0, p1 = room.polygon[k], room.polygon[(k + 1) % len(room.polygon)]
    e = (p1 - p0) / np.linalg.norm(p1 - p0)
    n = np.array([-e[1], e[0]])
    return e, abs(float(n @ p0))


def _columns(room, rc, width=1024):
    rays, _ = simulate_columns(room, ring_camera(rc, width))
    _, wall = render_boundaries(room, ring_camera(rc, width))
    return rays, wall


def test_ransac_iterations_matches_thesis_numbers():
    # thesis §5.4.4: P = 99.99 %, eps = 20 %, k = 3 -> 12.84 hypotheses; eps = 60 %, k = 6 -> 2244
    assert ransac_iterations(0.9999, 0.2, 3) == 13
    assert ransac_iterations(0.9999, 0.6, 6) == 2245          # 2244.6 rounded up (thesis truncates)
    with pytest.raises(ValueError):
        ransac_iterations(1.0, 0.2, 3)


def test_quadratic_roots_closed_form():
    r = _quadratic_roots(np.array([1.0, 0.0, 1.0]), np.array([-3.0, 2.0, 0.0]), np.array([2.0, -4.0, 1.0]))
    assert sorted(r[0]) == pytest.approx([1.0, 2.0])
    assert r[1][0] == pytest.approx(2.0) and np.isnan(r[1][1])      # linear case
    assert np.isnan(r[2]).all()                                       # no real root


@pytest.mark.parametrize("rc", [1.0, 0.65, 0.2])
def test_single_wall_solver_exact(rc):
    rng = np.random.default_rng(1)
    room = random_manhattan_room(rng, n_notches=1, rc=max(rc, 0.5))
    rays, wall = _columns(room, rc)
    mc, mf = rays.moments("ceiling"), rays.moments("floor")
    for k in range(len(room.polygon)):
        idx = np.flatnonzero(wall == k)[2:-2]
        if len(idx) < 8:
            continue
        fit = solve_walls(rays.ceiling[idx][None], mc[idx][None], rays.floor[idx][None], mf[idx][None])
        e, d = _wall_truth(room, k)
        assert fit.ok[0]
        assert fit.h_c[0] == pytest.approx(room.h_ceiling, abs=1e-7)
        assert fit.h_f[0] == pytest.approx(room.h_floor, abs=1e-7)
        assert fit.d[0] == pytest.approx(d, abs=1e-7)
        assert abs(math.sin(fit.theta[0] - math.atan2(e[1], e[0]))) < 1e-8      # parallel
        # canonical: e2 points from the camera to the wall
        assert fit.normal[0] @ room.polygon[k] == pytest.approx(d, abs=1e-7)


def test_single_wall_solver_batched_matches_single_and_ignores_zero_rows():
    rng = np.random.default_rng(2)
    room = random_manhattan_room(rng, n_notches=0)
    rays, wall = _columns(room, 1.0)
    mc, mf = rays.moments("ceiling"), rays.moments("floor")
    groups = [np.flatnonzero(wall == k)[3:-3] for k in range(4)]
    L = max(len(g) for g in groups)
    pad = np.zeros((4, L), int)
    w = np.zeros((4, L))
    for i, g in enumerate(groups):
        pad[i, :len(g)] = g
        w[i, :len(g)] = 1
    fit = solve_walls(rays.ceiling[pad], mc[pad], rays.floor[pad], mf[pad], w, w)
    for i, g in enumerate(groups):
        one = solve_walls(rays.ceiling[g][None], mc[g][None], rays.floor[g][None], mf[g][None])
        assert fit.d[i] == pytest.approx(one.d[0], abs=1e-8)
        assert fit.h_c[i] == pytest.approx(room.h_ceiling, abs=1e-7)


def test_central_wall_solver_uses_camera_height():
    rng = np.random.default_rng(3)
    room = random_manhattan_room(rng, n_notches=0, rc=0.5)
    rays, wall = _columns(room, 0.0)
    idx = np.flatnonzero(wall == 0)[3:-3]
    fit = solve_walls_central(rays.ceiling[idx][None], rays.floor[idx][None], camera_height=-room.h_floor)
    _, d = _wall_truth(room, 0)
    assert fit.ok[0]
    assert fit.h_c[0] == pytest.approx(room.h_ceiling, abs=1e-8)
    assert fit.d[0] == pytest.approx(d, abs=1e-8)


def _manhattan_setup(room, rc):
    rays, wall = _columns(room, rc)
    keep = np.zeros_like(wall, bool)
    for k in range(len(room.polygon)):
        idx = np.flatnonzero(wall == k)
        keep[idx[2:-2]] = True
    idx = np.flatnonzero(keep)
    return rays, idx, wall[idx]


def test_manhattan_solver_exact_rotated_room():
    rng = np.random.default_rng(4)
    room = random_manhattan_room(rng, n_notches=2, rotation=0.4)
    rays, idx, wall = _manhattan_setup(room, 1.0)
    n = len(room.polygon)
    e = np.stack([_wall_truth(room, k)[0] for k in range(n)])
    ang = np.arctan2(e[:, 1], e[:, 0])
    label = (np.abs(np.sin(ang - 0.4)) > 0.5).astype(int)
    A = manhattan_rows(rays.ceiling[idx], rays.moments("ceiling")[idx], rays.floor[idx], rays.moments("floor")[idx],
                       label, wall, n)
    th0, d, h_c, h_f, ok = solve_manhattan(A, label)
    assert ok
    assert h_c == pytest.approx(room.h_ceiling, abs=1e-7) and h_f == pytest.approx(room.h_floor, abs=1e-7)
    assert abs(math.sin(2 * (th0 - 0.4))) < 1e-7                   # the room orientation is recovered
    for k in range(n):
        assert abs(d[k]) == pytest.approx(_wall_truth(room, k)[1], abs=1e-6)


def test_atlanta_solver_exact_with_known_directions():
    poly = np.array([[3.0, -2.0], [3.5, 1.0], [1.0, 3.2], [-2.5, 2.5], [-3.0, -1.5], [0.0, -3.0]])
    room = Room(poly, 1.1, -1.5)
    rays, idx, wall = _manhattan_setup(room, 1.0)
    n = len(poly)
    theta = np.empty(n)
    for k in range(n):
        e, _ = _wall_truth(room, k)
        # canonical direction: e2 = (-uy, ux) points to the wall (d > 0)
        th = math.atan2(e[1], e[0])
        if np.array([-math.sin(th), math.cos(th)]) @ poly[k] < 0:
            th += math.pi
        theta[k] = th
    A = atlanta_rows(rays.ceiling[idx], rays.moments("ceiling")[idx], rays.floor[idx], rays.moments("floor")[idx],
                     theta, wall, n)
    h_c, h_f, d, ok = solve_atlanta(A)
    assert ok
    assert h_c == pytest.approx(1.1, abs=1e-8) and h_f == pytest.approx(-1.5, abs=1e-8)
    assert d == pytest.approx([_wall_truth(room, k)[1] for k in range(n)], abs=1e-7)
    # central rays: no scale from the moments, but fixing the floor gives it back
    rays0, idx0, wall0 = _manhattan_setup(room, 0.0)
    A0 = atlanta_rows(rays0.ceiling[idx0], rays0.moments("ceiling")[idx0], rays0.floor[idx0],
                      rays0.moments("floor")[idx0], theta, wall0, n)
    h_c0, h_f0, d0, ok0 = solve_atlanta(A0, fix_h_f=-1.5)
    assert ok0 and h_c0 == pytest.approx(1.1, abs=1e-8)
    assert d0 == pytest.approx(d, abs=1e-7)
