"""The 3D line through >= 4 rays (thesis §2.2.2): recovery, degeneracies, batching."""
import math

import torch

from .geom_helpers import noncentral_panorama_rays
from omnidl.cameras import Equirectangular, Rays
from omnidl.geometry import LineStatus, line_from_rays
from omnidl.geometry import plucker as P

D = torch.float64


def line_error(fit_line, points):
    """Max distance of true points on the line to the fitted line."""
    return P.point_line_distance(points, fit_line.unsqueeze(-2)).amax(-1)


def horizontal_line_points(n=4, y=1.2, z=2.5, x0=-2.0, x1=2.5):
    s = torch.linspace(x0, x1, n, dtype=D)
    return torch.stack([s, torch.full_like(s, y), torch.full_like(s, z)], -1)


def test_acceptance_horizontal_line_noncentral_panorama():
    """Four rays of a horizontal line seen by a non-central panorama (rc = 1 m): recovered to < 1e-6 m."""
    X = horizontal_line_points(4)
    fit = line_from_rays(noncentral_panorama_rays(X, rc=1.0))
    assert bool(fit.ok), fit.reason
    assert fit.reason == "ok"
    err = line_error(fit.line, X)
    assert err < 1e-6, err
    # far from the true line: a point 1 m off the line is 1 m away from the fit
    assert abs(P.point_line_distance(X[0] + torch.tensor([0, 1.0, 0], dtype=D), fit.line) - 1) < 1e-6
    assert fit.residual < 1e-9
    # the other Klein-quadric solution is the revolution axis (camera y)
    axis = torch.tensor([0, 1.0, 0, 0, 0, 0], dtype=D)
    assert P.line_distance(fit.other, axis) < 1e-9 and abs(abs(fit.other[1]) - 1) < 1e-9


def test_random_lines_batched(gen):
    """Many random lines (the RANSAC layout): each fit in a batch equals its own fit."""
    B = 16
    p = torch.randn(B, 3, generator=gen, dtype=D) * 2
    p[:, 0] += 3 * torch.sign(p[:, 0])  # keep the lines away from the camera circle
    d = torch.randn(B, 3, generator=gen, dtype=D)
    t = torch.linspace(-1.5, 1.5, 6, dtype=D)
    X = p[:, None] + t[None, :, None] * d[:, None]
    fits = line_from_rays(noncentral_panorama_rays(X, rc=1.0))
    assert fits.ok.all(), fits.reason
    assert line_error(fits.line, X).max() < 1e-6
    single = line_from_rays(noncentral_panorama_rays(X[3], rc=1.0))
    assert torch.allclose(single.line.abs(), fits.line[3].abs(), atol=1e-9)


def test_central_camera_is_degenerate():
    """Rays of a central camera (all through one point) are reported, not solved."""
    X = horizontal_line_points(6)
    cam = Equirectangular(width=64, height=32)
    uv, _ = cam.project(X)
    rays = cam.unproject(uv)
    fit = line_from_rays(rays)
    assert not bool(fit.ok)
    assert int(fit.status) == LineStatus.COMMON_POINT and "one point" in fit.reason
    assert (fit.line == 0).all()
    # a central camera somewhere else (shifted centre) too, float32 as well
    c = torch.tensor([0.3, -0.2, 0.5], dtype=D)
    shifted = P.line_from_points(c.expand_as(X), X)
    for dtype in (D, torch.float32):
        f = line_from_rays(shifted.to(dtype))
        assert int(f.status) == LineStatus.COMMON_POINT


def test_coplanar_and_too_few_rays():
    # a vertical line: all its rays leave the optical centre of one longitude
    s = torch.linspace(-1, 1.5, 5, dtype=D)
    X = torch.stack([torch.full_like(s, 1.5), s, torch.full_like(s, 2.0)], -1)
    fit = line_from_rays(noncentral_panorama_rays(X))
    assert not bool(fit.ok) and int(fit.status) == LineStatus.COMMON_POINT
    # a line crossing the revolution axis: rays from two centres, all in the plane x = 0 (holds the axis)
    s = torch.tensor([-3.0, -2.0, 2.0, 3.0], dtype=D)
    X = torch.stack([torch.zeros_like(s), torch.ones_like(s), s], -1)
    fit = line_from_rays(noncentral_panorama_rays(X))
    assert not bool(fit.ok) and int(fit.status) == LineStatus.COPLANAR and "plane" in fit.reason
    # 3 rays, or 4 with one masked out
    X = horizontal_line_points(4)
    rays = noncentral_panorama_rays(X)
    assert int(line_from_rays(rays[:3]).status) == LineStatus.TOO_FEW_RAYS
    mask = torch.tensor([True, True, False, True])
    assert int(line_from_rays(rays, valid=mask).status) == LineStatus.TOO_FEW_RAYS
    # Rays objects carry their own valid mask
    o = torch.cat([torch.zeros(4, 3, dtype=D)], 0)
    r = Rays(origin=o + 0.0, direction=rays[:, :3], valid=mask)
    assert int(line_from_rays(r).status) == LineStatus.TOO_FEW_RAYS


def test_mixed_batch_reports_per_item():
    good = noncentral_panorama_rays(horizontal_line_points(4))
    central = torch.cat([good[:, :3], torch.zeros(4, 3, dtype=D)], -1)
    fits = line_from_rays(torch.stack([good, central, good]))
    assert fits.ok.tolist() == [True, False, True]
    assert fits.reason[1].startswith("all rays pass through one point")
    assert torch.isfinite(fits.line).all() and torch.isfinite(fits.residual).all()


def test_noisy_overdetermined_and_float32(gen):
    X = horizontal_line_points(40, y=-1.0, z=-3.0, x0=-4, x1=4)  # a ceiling line behind the camera
    rays = noncentral_panorama_rays(X, rc=1.0)
    fit = line_from_rays(rays)
    assert bool(fit.ok) and line_error(fit.line, X) < 1e-6
    noisy = rays.clone()
    noisy[:, :3] += 1e-4 * torch.randn(40, 3, generator=gen, dtype=D)
    noisy[:, 3:] = torch.linalg.cross(torch.linalg.cross(rays[:, :3], rays[:, 3:], dim=-1), noisy[:, :3], dim=-1)
    f = line_from_rays(noisy)
    assert bool(f.ok) and line_error(f.line, X) < 2e-2 and f.residual < 1e-3
    f32 = line_from_rays(rays.float())
    assert bool(f32.ok) and line_error(f32.line.double(), X) < 1e-3


def test_no_axis_returns_a_solution():
    X = horizontal_line_points(4)
    fit = line_from_rays(noncentral_panorama_rays(X), axis=None)
    assert bool(fit.ok)
    sols = torch.stack([fit.line, fit.other])
    assert min(float(line_error(s, X)) for s in sols) < 1e-6
    assert math.isfinite(float(fit.residual))


def test_acceptance_with_the_registered_noncentral_panorama():
    """The same acceptance through omnidl's own camera: project the line's points, unproject the pixels."""
    from omnidl.cameras import build
    cam = build(type="noncentral_pano", width=1024, height=512, rc=1.0)
    X = horizontal_line_points(4)
    uv, valid = cam.project(X)
    assert valid.all()
    fit = line_from_rays(cam.unproject(uv))
    assert bool(fit.ok) and line_error(fit.line, X) < 1e-6


def test_axial_catadioptric_cameras_with_their_axis(gen):
    """Non-central catadioptric cameras (axis z): camera_axis finds the axis, the line is recovered."""
    import pytest

    from omnidl.cameras import get_camera_class
    from omnidl.geometry import Y_AXIS, Z_AXIS, camera_axis
    pano = get_camera_class("noncentral_pano").example()
    assert torch.allclose(camera_axis(pano), torch.tensor(Y_AXIS, dtype=D), atol=1e-9)
    for cam in get_camera_class("noncentral_catadioptric").examples():
        axis = camera_axis(cam)
        assert torch.allclose(axis, torch.tensor(Z_AXIS, dtype=D), atol=1e-9)
        r = cam.unproject(cam.sample_points(2, generator=gen))
        ends = r.at(torch.tensor([2.0, 3.0], dtype=D))
        X = ends[0] + torch.linspace(0.1, 0.9, 8, dtype=D)[:, None] * (ends[1] - ends[0])
        uv, valid = cam.project(X)
        assert valid.sum() >= 4
        fit = line_from_rays(cam.unproject(uv), valid=valid, axis=axis)
        assert bool(fit.ok) and line_error(fit.line, X[valid]) < 1e-6
    with pytest.raises(ValueError, match="central"):
        camera_axis(Equirectangular(width=16, height=8))


def test_conditioning_reports_ill_posed_samples():
    """A short, far segment is worse conditioned than a long, close one (same camera)."""
    near = line_from_rays(noncentral_panorama_rays(horizontal_line_points(4, x0=-2, x1=2.5)))
    far = line_from_rays(noncentral_panorama_rays(horizontal_line_points(4, y=3.0, z=9.0, x0=-0.3, x1=0.3)))
    assert bool(near.ok) and bool(far.ok)
    assert float(far.conditioning) < 0.1 * float(near.conditioning)
