"""rotate_panorama: R then R^T is the identity (away from interpolation blur), labels, batches;
sample_panorama: the camera's pixels, exact at pixel centres, wrapped longitude."""
import math

import pytest
import torch

from .geom_helpers import render, texture
from omnidl.cameras import Equirectangular
from omnidl.geometry import euler_to_matrix, random_rotation, rotate_panorama, rotation_y, sample_panorama

D = torch.float64


def test_rotate_then_inverse(gen):
    cam = Equirectangular(width=128, height=64)
    img = render(cam)
    R = random_rotation(3, generator=gen, dtype=D)
    once, valid = rotate_panorama(img, R)
    assert once.shape == (3, 1, 64, 128) and valid.all()
    back, _ = rotate_panorama(once, R.transpose(-1, -2))
    # two bilinear resamplings blur a little: compare away from the poles (rows 8..56)
    err = (back - img).abs()[..., 8:-8, :]
    assert err.mean() < 0.5 and err.max() < 6, (float(err.mean()), float(err.max()))
    # the rotated panorama shows the texture at R d
    d = cam.unproject_grid(dtype=D).direction
    true = texture(torch.einsum("bij,hwj->bhwi", R, d))
    assert (once[:, 0] - true)[:, 8:-8].abs().mean() < 0.3


def test_yaw_is_a_column_shift():
    img = torch.rand(1, 3, 32, 64, dtype=D)
    z = torch.zeros((), dtype=D)
    R = euler_to_matrix(z, z, torch.tensor(2 * math.pi * 5 / 64, dtype=D))  # 5 columns
    out, _ = rotate_panorama(img, R)
    assert torch.allclose(out, torch.roll(img, -5, dims=-1), atol=1e-9)
    lab = torch.randint(0, 13, (32, 64))
    out, _ = rotate_panorama(lab, R, mode="nearest")
    assert out.dtype == torch.int64 and torch.equal(out, torch.roll(lab, -5, dims=-1))


def test_labels_keep_their_values(gen):
    lab = torch.randint(1, 13, (1, 1, 32, 64), generator=gen)
    R = random_rotation(1, generator=gen, dtype=D)[0]
    out, valid = rotate_panorama(lab, R, mode="nearest")
    assert valid.all() and set(out.unique().tolist()) <= set(lab.unique().tolist())
    back, _ = rotate_panorama(out, R.T, mode="nearest")
    assert (back == lab).double().mean() > 0.6  # nearest twice: most pixels come home exactly


def test_pyequilib_rotation_oracle():
    """pyequilib's ``equi2equi(z_down=True, roll, pitch, yaw)`` rotates by our
    ``euler_to_matrix(roll, pitch, yaw)``. Its pixel grid differs from ours: the output pixel
    ``(j, i)`` takes the direction of our coordinate ``(j, i)`` (a pixel corner, not ``+0.5``),
    and the source is read at our coordinate ``(u + 1, v + 1)``; we adapt those offsets here."""
    import warnings

    from equilib import equi2equi

    from omnidl.geometry import WarpGrid, sample_grid

    cam = Equirectangular(width=128, height=64)
    img = render(cam).float()
    for r, p, y in [(0.3, -0.2, 0.7), (-0.5, 0.4, -2.0), (0.1, 0.6, 2.5)]:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ref = equi2equi(img.clone(), rots=[{"roll": r, "pitch": p, "yaw": y}], z_down=True, mode="bilinear")
        R = euler_to_matrix(*(torch.tensor(a, dtype=D) for a in (r, p, y)))
        d = cam.unproject(cam.pixel_grid(D) - 0.5).direction
        uv, valid = cam.project(torch.einsum("ij,hwj->hwi", R, d))
        ours, _ = sample_grid(img, WarpGrid((uv + 1.0)[None].float(), valid[None], 128, 64, True))
        assert (ours - ref).abs()[..., 2:-2, :].mean() < 0.05


def _directions(height, width, dtype):
    return Equirectangular(width=width, height=height).unproject_grid(dtype).direction


def test_sample_panorama_reads_where_the_camera_projects():
    """Sampling asks the camera (the gyroscope's former copy of the projection formula is gone):
    a ramp image whose values are the pixel coordinates reads back ``camera.project``'s ``(u, v)``."""
    cam = Equirectangular(width=64, height=32)
    g = torch.Generator().manual_seed(0)
    d = torch.randn(500, 3, generator=g, dtype=torch.float64)
    uv, _ = cam.project(d)
    u = (torch.arange(64, dtype=torch.float64) + 0.5).expand(32, 64)
    v = (torch.arange(32, dtype=torch.float64) + 0.5)[:, None].expand(32, 64)
    out = sample_panorama(torch.stack([u, v])[None], d)[0].T  # (500, 2)
    inner = (uv[:, 0] > 0.5) & (uv[:, 0] < 63.5) & (uv[:, 1] > 0.5) & (uv[:, 1] < 31.5)
    assert inner.sum() > 400 and torch.allclose(out[inner], uv[inner], atol=1e-9)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_sampling_pixel_centres_is_exact(dtype):
    img = torch.rand(2, 3, 16, 32, dtype=dtype)
    d = _directions(16, 32, dtype).reshape(-1, 3)
    out = sample_panorama(img, d)
    assert torch.allclose(out, img.reshape(2, 3, -1), atol=1e-5)


def test_longitude_wraps():
    img = torch.zeros(1, 1, 8, 16, dtype=torch.float64)
    img[..., 0] = 1.0  # first column
    # exactly at longitude -pi (the seam between last and first column): half of each
    d = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
    assert abs(float(sample_panorama(img, d)) - 0.5) < 1e-9


def test_yaw_by_whole_columns_is_a_roll_and_sampling_matches_rotate_panorama():
    img = render(Equirectangular(width=64, height=32)).repeat(1, 3, 1, 1)  # a smooth texture
    k = 5
    R = rotation_y(torch.tensor(2 * math.pi * k / 64, dtype=torch.float64))
    out, _ = rotate_panorama(img, R)
    assert torch.allclose(out, torch.roll(img, shifts=-k, dims=-1), atol=1e-9)
    R2 = euler_to_matrix(torch.tensor(0.2, dtype=torch.float64), torch.tensor(-0.3, dtype=torch.float64),
                         torch.tensor(1.0, dtype=torch.float64))
    ours = sample_panorama(img, torch.einsum("ij,hwj->hwi", R2, _directions(32, 64, torch.float64))
                           .reshape(-1, 3)).reshape(1, 3, 32, 64)
    theirs, _ = rotate_panorama(img, R2)
    # identical away from the two pole rows (border handling may differ there)
    assert torch.allclose(ours[..., 2:-2, :], theirs[..., 2:-2, :], atol=1e-6)
