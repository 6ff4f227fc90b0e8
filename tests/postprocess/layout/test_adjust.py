"""Final adjustment: analytic Jacobian vs finite differences; refinement recovers a perturbed room."""
import numpy as np
import pytest

from omnidl.postprocess.layout.adjust import AdjustProblem, adjust_layout, residuals_and_jacobian
from omnidl.apps.layout.simulate import Room, render_boundaries, ring_camera, simulate_columns


def _problem(room, rc=1.0, side=0.5, manh=10.0, W=256):
    rays, _ = simulate_columns(room, ring_camera(rc, W))
    _, wall = render_boundaries(room, ring_camera(rc, W))
    # vertices in column order: wall k sees polygon edge k, corner order along increasing column
    idx = np.flatnonzero(rays.valid)
    lat_c, lat_f = rays.elevations()
    az = np.arctan2(room.polygon[:, 0], room.polygon[:, 1])
    return rays, AdjustProblem(seg=wall[idx], origin2=rays.origin[idx, :2], b=rays.horizontal[idx], lat_c=lat_c[idx],
                               lat_f=lat_f[idx], dir_c=rays.ceiling[idx], mom_c=rays.moments("ceiling")[idx],
                               dir_f=rays.floor[idx], mom_f=rays.moments("floor")[idx], corner_az=az,
                               corner_w=np.full(len(az), 0.3), n_corners=len(az), pix_lat=np.pi / (W // 2),
                               pix_az=2 * np.pi / W, side_weight=side, manhattan_weight=manh,
                               s0=np.full(len(idx), 3.0))


ROOM = Room(np.array([[3.0, -2.5], [3.0, 3.5], [-2.0, 3.5], [-2.0, -2.5]]), 1.25, -1.45)


def test_jacobian_matches_finite_differences():
    _, P = _problem(ROOM)
    rng = np.random.default_rng(0)
    x = np.concatenate([[1.2, -1.5], (ROOM.polygon + rng.normal(0, 0.1, ROOM.polygon.shape)).reshape(-1)])
    r, J = residuals_and_jacobian(x, P)
    eps = 1e-6
    Jn = np.stack([(residuals_and_jacobian(x + eps * e, P, False)[0] - residuals_and_jacobian(x - eps * e, P, False)[0])
                   / (2 * eps) for e in np.eye(len(x))], 1)
    assert np.allclose(J, Jn, rtol=1e-5, atol=1e-4 * np.abs(Jn).max())


def test_residuals_vanish_at_truth_and_adjustment_recovers_it():
    _, P = _problem(ROOM, side=0.0)
    x = np.concatenate([[1.25, -1.45], ROOM.polygon.reshape(-1)])
    r, _ = residuals_and_jacobian(x, P, False)
    assert np.abs(r).max() < 1e-6
    rng = np.random.default_rng(1)
    h_c, h_f, C, cost = adjust_layout(1.15, -1.35, ROOM.polygon + rng.normal(0, 0.08, (4, 2)), P, max_nfev=100)
    assert h_c == pytest.approx(1.25, abs=1e-4) and h_f == pytest.approx(-1.45, abs=1e-4)
    assert np.abs(C - ROOM.polygon).max() < 1e-3
