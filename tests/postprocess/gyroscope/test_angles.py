import math

import pytest
import torch

from omnidl.postprocess.gyroscope.angles import (axis_angle_to_matrix, euler_to_matrix, random_rotations, rot_y,
                                                  skew, tilt_from_up, tilt_rotation, up_from_rotation)
from omnidl.geometry.rotations import matrix_to_axis_angle, rotation_angle


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_tilt_rotation_maps_up_vector_to_upright(dtype):
    g = torch.Generator().manual_seed(0)
    n = torch.randn(200, 3, generator=g, dtype=dtype)
    n = n / n.norm(dim=-1, keepdim=True)
    T = tilt_rotation(n)
    up = torch.tensor([0.0, -1.0, 0.0], dtype=dtype)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    assert torch.allclose(torch.einsum("bij,bj->bi", T, n), up.expand_as(n), atol=tol)
    roll, pitch = tilt_from_up(n)
    assert torch.allclose(euler_to_matrix(roll, pitch, torch.zeros_like(roll)), T, atol=tol)
    assert (pitch.abs() <= math.pi / 2 + 1e-6).all()


def test_tilt_beyond_90_degrees_is_kept():
    # upside-down camera: up vector is +y in the camera frame -> roll 180 deg, not folded to 0
    roll, pitch = tilt_from_up(torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    assert abs(abs(float(roll)) - math.pi) < 1e-12 and abs(float(pitch)) < 1e-12


def test_axis_angle_matches_closed_form_and_kornia():
    g = torch.Generator().manual_seed(1)
    w = torch.randn(50, 3, generator=g, dtype=torch.float64)
    R = axis_angle_to_matrix(w)
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand_as(R), atol=1e-12)
    assert torch.allclose(matrix_to_axis_angle(R), w * (w.norm(dim=-1, keepdim=True) <= math.pi)
                          + torch.where(w.norm(dim=-1, keepdim=True) > math.pi,
                                        matrix_to_axis_angle(R), torch.zeros_like(w)), atol=1e-9)
    a = torch.tensor([0.3], dtype=torch.float64)
    assert torch.allclose(axis_angle_to_matrix(torch.tensor([[0.0, 0.3, 0.0]], dtype=torch.float64)), rot_y(a))
    v = torch.randn(3, dtype=torch.float64, generator=g)
    u = torch.randn(3, dtype=torch.float64, generator=g)
    assert torch.allclose(skew(v) @ u, torch.linalg.cross(v, u))
    # tiny angles use the first-order formula
    assert torch.allclose(axis_angle_to_matrix(torch.tensor([1e-10, 0, 0], dtype=torch.float64)),
                          torch.eye(3, dtype=torch.float64), atol=1e-9)


def test_random_rotations_respect_max_tilt():
    g = torch.Generator().manual_seed(2)
    R = random_rotations(500, math.radians(40), generator=g)
    up = up_from_rotation(R)
    tilt = torch.rad2deg(torch.acos((-up[:, 1]).clamp(-1, 1)))
    assert tilt.max() <= 40 + 1e-6 and tilt.max() > 30
    assert torch.allclose(torch.det(R), torch.ones(500, dtype=torch.float64))
    Rf = random_rotations(2000, math.pi, generator=g)
    # uniform over SO(3): mean of the up vector ~ 0
    assert up_from_rotation(Rf).mean(0).abs().max() < 0.06
    assert rotation_angle(R, R).abs().max() < 1e-6
