"""Rotation helpers: scipy as the reference, round trips, gradcheck (also at zero rotation)."""
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from omnidl.geometry import rotations as rot
from omnidl.geometry.rotations import (axis_angle_to_matrix, euler_to_matrix, matrix_to_axis_angle,
                                       random_tilt_rotation, rotation_angle, rotation_y, skew, tilt_from_up,
                                       tilt_rotation, up_from_rotation)

D = torch.float64


def rand_angles(n, gen):
    a = (2 * torch.rand(n, 3, generator=gen, dtype=D) - 1) * math.pi
    a[:, 1] *= 0.5  # pitch in [-pi/2, pi/2]
    return a


def test_euler_matches_scipy_and_documented_semantics(gen):
    a = rand_angles(20, gen)
    R = rot.euler_to_matrix(a[:, 0], a[:, 1], a[:, 2])
    # R_y(yaw) R_x(pitch) R_z(roll) = intrinsic Y-X-Z with angles (yaw, pitch, roll)
    ref = Rotation.from_euler("YXZ", a[:, [2, 1, 0]].numpy()).as_matrix()
    assert np.allclose(R.numpy(), ref, atol=1e-12)
    z, x = torch.tensor([0, 0, 1.0], dtype=D), torch.tensor([1.0, 0, 0], dtype=D)
    t = torch.tensor(0.3, dtype=D)
    zero = torch.zeros((), dtype=D)
    assert rot.euler_to_matrix(zero, zero, t) @ z @ x > 0  # yaw turns the optical axis right (+x)
    assert (rot.euler_to_matrix(zero, t, zero) @ z)[1] < 0  # pitch tilts it up (-y)
    assert (rot.euler_to_matrix(t, zero, zero) @ x)[1] > 0  # roll turns x towards +y
    assert rot.euler_to_matrix(0.0, 0.0, 0.0).shape == (3, 3)


def test_euler_round_trip_and_gimbal_lock(gen):
    a = rand_angles(50, gen)
    R = rot.euler_to_matrix(a[:, 0], a[:, 1], a[:, 2])
    r, p, y = rot.matrix_to_euler(R)
    assert torch.allclose(torch.stack([r, p, y], -1), a, atol=1e-10)
    yaw = torch.tensor([0.4, -2.0], dtype=D)
    for pitch in (math.pi / 2, -math.pi / 2):
        R = rot.euler_to_matrix(torch.zeros(2, dtype=D), torch.full((2,), pitch, dtype=D), yaw)
        r, p, y = rot.matrix_to_euler(R)
        assert torch.allclose(rot.euler_to_matrix(r, p, y), R, atol=1e-10)
        assert torch.isfinite(torch.stack([r, p, y])).all()


def test_kornia_conversions_round_trip(gen):
    R = rot.random_rotation(30, generator=gen, dtype=D)
    aa = rot.matrix_to_axis_angle(R)
    assert torch.allclose(rot.axis_angle_to_matrix(aa), R, atol=1e-10)
    q = rot.matrix_to_quaternion(R)
    assert (q[:, 0] >= 0).all()
    assert torch.allclose(rot.quaternion_to_matrix(q), R, atol=1e-10)
    # scipy (x, y, z, w) vs ours (w, x, y, z)
    ref = Rotation.from_matrix(R.numpy()).as_quat()
    ref = np.where(ref[:, 3:] < 0, -ref, ref)
    assert np.allclose(q[:, [1, 2, 3, 0]].numpy(), ref, atol=1e-10)
    assert np.allclose(aa.numpy(), Rotation.from_matrix(R.numpy()).as_rotvec(), atol=1e-8)
    with pytest.raises(ValueError, match="3, 3"):
        rot.matrix_to_axis_angle(torch.zeros(4, 3))


def test_gradcheck_including_zero_rotation(gen):
    for aa in (torch.zeros(2, 3, dtype=D), 0.7 * torch.randn(2, 3, generator=gen, dtype=D)):
        aa.requires_grad_()
        assert torch.autograd.gradcheck(rot.axis_angle_to_matrix, (aa,))
    ang = torch.tensor([[0.0, 0.0, 0.0], [0.2, -0.4, 1.1]], dtype=D, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a: rot.euler_to_matrix(a[:, 0], a[:, 1], a[:, 2]), (ang,))
    q = torch.tensor([[1.0, 0, 0, 0], [0.3, 0.1, -0.5, 0.2]], dtype=D, requires_grad=True)
    assert torch.autograd.gradcheck(rot.quaternion_to_matrix, (q,))
    # rotation_angle at the identity: finite gradient
    w = torch.zeros(3, dtype=D, requires_grad=True)
    rot.rotation_angle(rot.axis_angle_to_matrix(w)).backward()
    assert torch.isfinite(w.grad).all()
    w = torch.tensor([0.1, 0.2, -0.3], dtype=D, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: rot.rotation_angle(rot.axis_angle_to_matrix(v)), (w,))


def test_rotation_angle_and_tilt(gen):
    R1 = rot.random_rotation(20, generator=gen, dtype=D)
    R2 = rot.random_rotation(20, generator=gen, dtype=D)
    ang = rot.rotation_angle(R1, R2)
    ref = (Rotation.from_matrix(R1.numpy()).inv() * Rotation.from_matrix(R2.numpy())).magnitude()
    assert np.allclose(ang.numpy(), ref, atol=1e-10)
    small = rot.axis_angle_to_matrix(torch.tensor([1e-9, 0, 0], dtype=D))
    assert abs(float(rot.rotation_angle(small)) - 1e-9) < 1e-15  # acos would give 0 or noise here
    # tilt: a pure yaw has none, a pitch of 0.3 has 0.3
    z = torch.zeros((), dtype=D)
    assert rot.tilt_angle(rot.euler_to_matrix(z, z, z + 2.0)) < 1e-12
    assert abs(float(rot.tilt_angle(rot.euler_to_matrix(z, z + 0.3, z + 1.0))) - 0.3) < 1e-12


def test_random_rotations(gen):
    R = rot.random_rotation(4000, generator=gen, dtype=D)
    eye = torch.eye(3, dtype=D)
    assert torch.allclose(R @ R.transpose(-1, -2), eye.expand_as(R), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(4000, dtype=D))
    assert R.mean(0).abs().max() < 0.05  # Haar measure: E[R] = 0
    # uniform rotation angle density is (1 - cos t) / pi: mean angle pi/2 + 2/pi
    assert abs(float(rot.rotation_angle(R).mean()) - (math.pi / 2 + 2 / math.pi)) < 0.03
    T = rot.random_tilt_rotation(2000, math.radians(20), generator=gen, dtype=D)
    tilt = rot.tilt_angle(T)
    assert tilt.max() <= math.radians(20) + 1e-12 and tilt.max() > math.radians(19)
    # uniform on the cap: cos(tilt) uniform in [cos 20°, 1]
    assert abs(float(torch.cos(tilt).mean()) - (1 + math.cos(math.radians(20))) / 2) < 2e-3
    with pytest.raises(ValueError, match="max_tilt"):
        rot.random_tilt_rotation(2, -1.0)


def test_upright_to_world(gen):
    R = rot.upright_to_world(D)
    assert torch.allclose(torch.linalg.det(R), torch.tensor(1.0, dtype=D))
    assert torch.allclose(R @ torch.tensor([0, -1.0, 0], dtype=D), torch.tensor([0, 0, 1.0], dtype=D))
    assert torch.allclose(R @ torch.tensor([0, 0, 1.0], dtype=D), torch.tensor([0, 1.0, 0], dtype=D))
    assert torch.allclose(R @ torch.tensor([1.0, 0, 0], dtype=D), torch.tensor([1.0, 0, 0], dtype=D))
    # positive camera yaw turns right = clockwise seen from above (world z up)
    Rw = rot.camera_to_world_rotation(yaw=torch.tensor(0.5, dtype=D))
    fwd = Rw @ torch.tensor([0, 0, 1.0], dtype=D)
    assert fwd[2].abs() < 1e-12 and math.atan2(float(fwd[1]), float(fwd[0])) < math.pi / 2
    # a tilted camera (R_up_cam): the world up seen in its frame maps back to world +z
    R_up_cam = rot.random_tilt_rotation(5, 0.3, generator=gen, dtype=D)
    Rw = rot.camera_to_world_rotation(R_up_cam)
    up_cam = R_up_cam.transpose(-1, -2) @ torch.tensor([0, -1.0, 0], dtype=D)
    up_world = (Rw @ up_cam[..., None])[..., 0]
    assert torch.allclose(up_world, torch.tensor([0, 0, 1.0], dtype=D).expand(5, 3), atol=1e-12)
    # X_world = R X_cam + t and back
    X = torch.randn(5, 3, generator=gen, dtype=D)
    t = torch.randn(5, 3, generator=gen, dtype=D)
    assert torch.allclose(rot.world_to_camera(rot.camera_to_world(X, Rw, t), Rw, t), X, atol=1e-12)


# -- up vector, tilt, Rodrigues, skew (formerly the gyroscope's own copies) --------------------------
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
    assert torch.allclose(axis_angle_to_matrix(torch.tensor([[0.0, 0.3, 0.0]], dtype=torch.float64)), rotation_y(a))
    v = torch.randn(3, dtype=torch.float64, generator=g)
    u = torch.randn(3, dtype=torch.float64, generator=g)
    assert torch.allclose(skew(v) @ u, torch.linalg.cross(v, u))
    # tiny angles use the first-order formula
    assert torch.allclose(axis_angle_to_matrix(torch.tensor([1e-10, 0, 0], dtype=torch.float64)),
                          torch.eye(3, dtype=torch.float64), atol=1e-9)


def test_random_rotations_respect_max_tilt():
    g = torch.Generator().manual_seed(2)
    R = random_tilt_rotation(500, math.radians(40), generator=g, dtype=torch.float64)
    up = up_from_rotation(R)
    tilt = torch.rad2deg(torch.acos((-up[:, 1]).clamp(-1, 1)))
    assert tilt.max() <= 40 + 1e-6 and tilt.max() > 30
    assert torch.allclose(torch.det(R), torch.ones(500, dtype=torch.float64))
    Rf = random_tilt_rotation(2000, math.pi, generator=g, dtype=torch.float64)
    # uniform over SO(3): mean of the up vector ~ 0
    assert up_from_rotation(Rf).mean(0).abs().max() < 0.06
    assert rotation_angle(R, R).abs().max() < 1e-6


def test_upright_rotation_inverts_camera_to_world_rotation(gen):
    yaw = (2 * torch.rand(6, generator=gen, dtype=D) - 1) * math.pi
    pitch = (2 * torch.rand(6, generator=gen, dtype=D) - 1) * 1.2
    R_up_cam = rot.rotation_x(pitch)  # a pure pitch keeps the heading of the forward axis
    R_world_cam = rot.camera_to_world_rotation(R_up_cam, yaw)
    assert torch.allclose(rot.upright_rotation(R_world_cam), R_up_cam, atol=1e-12)
    # R_world_cam = R_z(h) @ UPRIGHT_TO_WORLD @ R_up_cam for any camera, also one looking straight down
    for R_w in (rot.random_rotation(5, generator=gen, dtype=D),
                rot.camera_to_world_rotation(rot.rotation_x(torch.tensor(-math.pi / 2, dtype=D)))[None]):
        R_u = rot.upright_rotation(R_w)
        assert torch.allclose(R_u @ R_u.transpose(-1, -2), torch.eye(3, dtype=D).expand_as(R_u), atol=1e-12)
        R_wu = R_w @ R_u.transpose(-1, -2)  # R_z(h) @ UPRIGHT_TO_WORLD: keeps the world up
        up, z = torch.tensor([0, -1.0, 0], dtype=D), torch.tensor([0, 0, 1.0], dtype=D)
        assert torch.allclose(R_wu @ up, z.expand(len(R_wu), 3), atol=1e-12)
