import math

import torch

from omnidl.cameras.equirectangular import Equirectangular
from omnidl.geometry.rotations import axis_angle_to_matrix, random_tilt_rotation
from omnidl.postprocess.gyroscope.pvg import pvg_refine
from omnidl.postprocess.gyroscope.scene import procedural_panorama
from omnidl.metrics.rotation import rotation_error
from tests.reference.gyroscope import spherical_gradient, tangent_basis


def test_spherical_gradient_of_a_linear_function():
    # f(d) = a . d: tangent gradient a - (a . p) p
    a = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    img = (Equirectangular(width=512, height=256).unproject_grid(torch.float64).direction @ a)[None, None]
    p = torch.nn.functional.normalize(torch.randn(1, 40, 3, dtype=torch.float64,
                                                  generator=torch.Generator().manual_seed(0)), dim=-1)
    p = p[:, (p[0, :, 1].abs() < 0.95)]  # away from the pole rows (border clamping)
    v, grad = spherical_gradient(img, p)
    expect = a - (p @ a)[..., None] * p
    assert torch.allclose(v, p @ a, atol=2e-4)
    assert torch.allclose(grad, expect, atol=5e-3)
    t1, t2 = tangent_basis(p)
    assert (t1 * p).sum(-1).abs().max() < 1e-12 and (t2 * t1).sum(-1).abs().max() < 1e-12


def test_pvg_refines_10_degree_perturbations_below_0_2_degrees():
    g = torch.Generator().manual_seed(0)
    ref = procedural_panorama(None, 64, 128, seed=2)
    R_gt = random_tilt_rotation(3, math.pi, generator=g, dtype=torch.float64)
    cur = procedural_panorama(R_gt, 64, 128, seed=2)
    w = (2 * torch.rand(3, 3, generator=g, dtype=torch.float64) - 1) * math.radians(10)
    w[:, 0] = math.radians(10) * torch.sign(w[:, 0])  # at least one axis at the full 10 degrees
    R0 = axis_angle_to_matrix(w) @ R_gt
    res = pvg_refine(cur, ref, R0.float(), level=4)
    err = rotation_error(R_gt, res.rotation.double())
    assert rotation_error(R_gt, R0).min() > 9.9
    assert err.max() < 0.2, err
    assert torch.isfinite(res.cost).all()


def test_non_finite_inputs_give_nan_not_a_plausible_answer():
    R = random_tilt_rotation(1, math.radians(30), generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    R = R.float()
    ref = procedural_panorama(None, 64, 128, seed=1).float()
    cur = procedural_panorama(R.double(), 64, 128, seed=1).float()
    bad = cur.clone()
    bad[..., 10, 20] = float("nan")
    assert torch.isnan(pvg_refine(bad, ref, R, level=3, max_iter=3).cost).all()
    Rn = R.clone()
    Rn[0, 0, 0] = float("nan")
    assert torch.isnan(pvg_refine(cur, ref, Rn, level=3, max_iter=3).rotation).all()
