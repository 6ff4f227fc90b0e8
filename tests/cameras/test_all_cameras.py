"""Contract tests run automatically on every registered camera model."""
import pytest
import torch

from omnidl.cameras import list_cameras, get_camera_class

# every registered model, every variant it declares (Camera.examples), e.g. "fisheye-1" = 2nd lens
EXAMPLES = {f"{name}-{i}": cam for name in list_cameras()
            for i, cam in enumerate(get_camera_class(name).examples())}


def _cam(name):
    return EXAMPLES[name]


@pytest.mark.parametrize("name", sorted(EXAMPLES))
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-9), (torch.float32, 1e-4)])
def test_project_unproject_roundtrip(name, dtype, tol):
    cam = _cam(name)
    g = torch.Generator().manual_seed(0)
    uv = cam.sample_points(500, dtype=torch.float64, generator=g).to(dtype)
    rays = cam.unproject(uv)
    assert rays.valid.all()
    assert torch.allclose(rays.direction.norm(dim=-1), torch.ones((), dtype=dtype), atol=10 * tol)
    pts = rays.at(torch.full(uv.shape[:-1], 3.0, dtype=dtype))
    uv2, valid = cam.project(pts)
    assert valid.all()
    assert (uv2 - uv).abs().max() < tol


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_ray_passes_through_point(name):
    cam = _cam(name)
    g = torch.Generator().manual_seed(1)
    uv = cam.sample_points(200, generator=g)
    rays = cam.unproject(uv)
    depth = 0.5 + 4 * torch.rand(len(uv), dtype=torch.float64, generator=g)
    pts = rays.at(depth)
    uv2, valid = cam.project(pts)
    rays2 = cam.unproject(uv2)
    # X lies on the re-unprojected ray: |(X - o) x d| == 0
    off = torch.linalg.cross(pts - rays2.origin, rays2.direction, dim=-1).norm(dim=-1)
    assert valid.all() and off.max() < 1e-9


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_outside_fov_is_invalid_and_finite(name):
    cam = _cam(name)
    uv = torch.tensor([[-5.0, -5.0], [cam.width + 3.0, 1.0], [1.0, cam.height + 7.0]], dtype=torch.float64)
    rays = cam.unproject(uv)
    assert not rays.valid.any()
    assert torch.isfinite(rays.direction).all() and torch.isfinite(rays.origin).all()
    pts = torch.tensor([[0.0, 0.0, 0.0], [1e-3, -2.0, -50.0], [0.0, 0.0, -1.0], [1.0, 1.0, 1.0]], dtype=torch.float64)
    uv, valid = cam.project(pts)
    assert torch.isfinite(uv).all()
    assert not valid[0]


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_gradcheck(name):
    cam = _cam(name)
    g = torch.Generator().manual_seed(2)
    uv = cam.sample_points(6, generator=g).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: cam.unproject(x).direction, (uv,))
    pts = cam.unproject(uv.detach()).at(torch.full((6,), 2.0, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: cam.project(p)[0], (pts,))


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_resized_halves_pixels(name):
    cam = _cam(name)
    small = cam.resized(cam.width // 2, cam.height // 2)
    g = torch.Generator().manual_seed(3)
    uv = cam.sample_points(50, generator=g)
    pts = cam.unproject(uv).at(torch.full((50,), 2.0, dtype=torch.float64))
    uv_small, valid = small.project(pts)
    assert valid.all()
    assert torch.allclose(uv_small, uv / 2, atol=1e-9)


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_config_roundtrip(name):
    from omnidl.cameras import build
    cam = _cam(name)
    assert build(cam.to_config()) == cam


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_special_points_have_finite_gradients(name):
    """The optical axis, the principal point, the origin, points behind and pixels outside: finite values/grads."""
    cam = _cam(name)
    pts = torch.tensor([[0, 0, 2.0], [0, 0, -2.0], [0, 0, 0.0], [1e-3, -2, -50], [0, 2.0, 0], [3, 0, 0.0]],
                       dtype=torch.float64, requires_grad=True)
    uv, _ = cam.project(pts)
    (g,) = torch.autograd.grad(uv.sum(), pts)
    centre = [getattr(cam, "cx", cam.width / 2), getattr(cam, "cy", cam.height / 2)]
    pix = torch.tensor([centre, [-5.0, -5.0], [cam.width / 2, cam.height / 2]], dtype=torch.float64,
                       requires_grad=True)
    rays = cam.unproject(pix)
    (g2,) = torch.autograd.grad(rays.direction.sum() + rays.origin.sum(), pix)
    for t in (uv, g, rays.direction, rays.origin, g2):
        assert torch.isfinite(t).all()
