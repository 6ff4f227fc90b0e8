import math

import torch

from omnidl.geometry.panorama import sample_panorama
from omnidl.geometry.rotations import axis_angle_to_matrix, rotation_y
from omnidl.postprocess.gyroscope.icosahedron import icosahedron_vertices
from omnidl.geometry.rotations import random_tilt_rotation
from omnidl.postprocess.gyroscope.mpp import abs_zn, mpp_field, mpp_table, mpp_yaw
from omnidl.postprocess.gyroscope.scene import procedural_panorama
from omnidl.metrics.rotation import rotation_error
from tests.reference.gyroscope import rotation_jacobian


def test_abs_zn_normalisation():
    I = torch.tensor([[1.0, 2.0, 3.0, 6.0]], dtype=torch.float64)
    out = abs_zn(I)
    raw = (I - 3).abs()
    assert torch.allclose(out, raw / raw.sum())
    assert torch.allclose(out.sum(-1), torch.ones(1, dtype=torch.float64))


def test_field_gradient_and_rotation_jacobian_match_finite_differences():
    g = torch.Generator().manual_seed(0)
    X = icosahedron_vertices(2, torch.float64)
    I = abs_zn(torch.rand(1, len(X), generator=g, dtype=torch.float64))
    lam = 0.325
    p = torch.nn.functional.normalize(torch.randn(1, 7, 3, generator=g, dtype=torch.float64), dim=-1)
    G, grad = mpp_field(X, I, p, lam, with_grad=True)
    # ambient gradient, tangential part, vs central differences along tangent directions
    t = torch.nn.functional.normalize(torch.linalg.cross(p, torch.randn_like(p)), dim=-1)
    h = 1e-6
    Gp, _ = mpp_field(X, I, torch.nn.functional.normalize(p + h * t, dim=-1), lam)
    Gm, _ = mpp_field(X, I, torch.nn.functional.normalize(p - h * t, dim=-1), lam)
    assert torch.allclose((Gp - Gm) / (2 * h), (grad * t).sum(-1), rtol=1e-5, atol=1e-8)
    # Jacobian of G(R(w).T s) w.r.t. w at R0, with R(w) = exp([w]x) R0
    R0 = axis_angle_to_matrix(torch.tensor([0.2, -0.5, 0.3], dtype=torch.float64))
    s = X[:5]
    q = (R0.T @ s.T).T[None]
    _, gq = mpp_field(X, I, q, lam, with_grad=True)
    J = rotation_jacobian(gq, R0[None], s)[0]  # (5, 3)
    for k in range(3):
        w = torch.zeros(3, dtype=torch.float64)
        w[k] = h
        fp, _ = mpp_field(X, I, ((axis_angle_to_matrix(w) @ R0).T @ s.T).T[None], lam)
        fm, _ = mpp_field(X, I, ((axis_angle_to_matrix(-w) @ R0).T @ s.T).T[None], lam)
        assert torch.allclose((fp - fm)[0] / (2 * h), J[:, k], rtol=1e-5, atol=1e-8)


def test_table_matches_exact_field():
    X = icosahedron_vertices(3, torch.float64)
    I = abs_zn(torch.rand(1, len(X), generator=torch.Generator().manual_seed(1), dtype=torch.float64))
    table = mpp_table(X, I, 0.325, 64)
    p = torch.nn.functional.normalize(torch.randn(1, 50, 3, dtype=torch.float64), dim=-1)
    G, _ = mpp_field(X, I, p, 0.325)
    Gt = sample_panorama(table, p)[:, 0]
    assert ((Gt - G).abs() / G.abs().max()).max() < 2e-3


def test_mpp_recovers_any_pure_yaw_below_3_degrees():
    # a yaw of a gravity-aligned panorama is a roll of its columns: exact renders, any angle
    ref = procedural_panorama(None, 64, 128, seed=1)
    shifts = torch.tensor([-63, -32, 21, 64])  # columns: -177.2, -90, 59.1, 180 degrees
    cur = torch.stack([torch.roll(ref[0], int(k), dims=-1) for k in shifts])
    yaw_true = -2 * math.pi * shifts.double() / 128  # rolling columns right = turning the camera left
    res = mpp_yaw(cur, ref, level=3, lambda_g=0.325)
    err = rotation_error(rotation_y(yaw_true), res.rotation.double())
    assert err.max() < 3.0, err


def test_mpp_without_iterations_keeps_the_starts():
    R = random_tilt_rotation(1, math.radians(30), generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    ref = procedural_panorama(None, 64, 128, seed=1).float()
    cur = procedural_panorama(R, 64, 128, seed=1).float()
    r = mpp_yaw(cur, ref, R.float(), level=2, tries=4, max_iter=0)
    assert r.iterations == 0 and torch.isinf(r.cost).all()
