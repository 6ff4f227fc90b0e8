"""rotate_panorama: R then R^T is the identity (away from interpolation blur), labels, batches;
sample_panorama: the camera's pixels, exact at pixel centres, wrapped longitude."""
import math

import pytest
import torch

from .geom_helpers import render, texture
from omnidl.cameras import Equirectangular
from omnidl.geometry import euler_to_matrix, random_rotation, rotate_panorama, rotation_y, sample_panorama, warp_grid

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


# -- masked interpolation of depth (issue 14: bilinear blended the 0 of holes into valid ranges) -----------
def _depth_with_holes(h: int = 32, w: int = 64) -> torch.Tensor:
    """``(1, 1, H, W)`` float64 ranges in [1.5, 4.5] with rectangular holes (0) and a single-pixel hole."""
    g = torch.Generator().manual_seed(3)
    i = torch.arange(h, dtype=torch.float64)[:, None]
    j = torch.arange(w, dtype=torch.float64)[None, :]
    depth = 3.0 + 1.5 * torch.sin(2 * math.pi * j / w) * torch.cos(math.pi * (i + 0.5) / h)
    depth = depth + 0.01 * torch.rand(h, w, generator=g, dtype=torch.float64)
    depth[8:14, 10:20] = 0.0
    depth[20:26, 40:47] = 0.0
    depth[16, 33] = 0.0
    return depth[None, None]


def test_rotate_depth_masked_stays_within_its_valid_taps():
    """A yaw of 0.37 column: each output samples the two row neighbours ``j0, j0+1`` (weights ``1-t``, ``t``).
    The masked output is their weighted mean over the valid ones, never below/above them, and invalid (0)
    where both are holes; plain bilinear blends the 0 in (the failure of issue 14)."""
    depth = _depth_with_holes()
    h, w = depth.shape[-2:]
    shift = 0.37                                             # columns
    R = euler_to_matrix(*(torch.tensor(a, dtype=torch.float64) for a in (0.0, 0.0, 2 * math.pi * shift / w)))
    out, valid = rotate_panorama(depth, R, mode="masked", cache=False)
    bil, _ = rotate_panorama(depth, R, mode="bilinear", cache=False)
    cam = Equirectangular(width=w, height=h)
    u = warp_grid(cam, cam, R, dtype=torch.float64, cache=False).uv[0, ..., 0]   # (H, W) sampled column
    j0 = torch.floor(u - 0.5).long()
    t = (u - 0.5) - j0
    a = depth[0, 0].gather(1, torch.remainder(j0, w))
    b = depth[0, 0].gather(1, torch.remainder(j0 + 1, w))
    wa, wb = (1 - t) * (a > 0), t * (b > 0)
    expected = torch.where(wa + wb > 0, (wa * a + wb * b) / (wa + wb).clamp_min(1e-300), torch.zeros_like(a))
    assert torch.allclose(out[0, 0], expected, atol=1e-6)
    lo = torch.where(a > 0, a, b).minimum(torch.where(b > 0, b, a))
    hi = torch.maximum(a, b)
    ok = valid[0, 0]
    assert (out[0, 0][ok] >= lo[ok] - 1e-6).all() and (out[0, 0][ok] <= hi[ok] + 1e-6).all()
    assert torch.equal(ok, (wa + wb) >= 1e-6) and (out[0, 0][~ok] == 0).all()
    # the unmasked blend: values between 0 and the valid neighbour, far below the valid range
    blend = (bil[0, 0] > 0) & (bil[0, 0] < 1.4)
    assert blend.any()


def test_rotate_depth_masked_is_exact_on_constant_regions_and_invalid_without_taps():
    depth = torch.full((1, 1, 32, 64), 2.75, dtype=torch.float32)
    depth[..., 5:12, 20:31] = 0.0
    R = euler_to_matrix(torch.tensor(0.05), torch.tensor(-0.11), torch.tensor(0.4))
    out, valid = rotate_panorama(depth, R, mode="masked", cache=False)
    assert out.dtype == torch.float32
    assert (out[valid] == 2.75).all()                        # exact: no blur of a constant
    assert (out[~valid] == 0).all() and (~valid).any()       # holes stay holes, marked invalid
    empty, v0 = rotate_panorama(torch.zeros(1, 1, 16, 32), R, mode="masked", cache=False)
    assert not v0.any() and (empty == 0).all()


def test_rotate_with_invalid_value_means_masked():
    depth = torch.full((1, 16, 32), 7.0, dtype=torch.float64)
    depth[:, 4:9, 3:11] = -1.0                               # another "no data" marker
    R = euler_to_matrix(*(torch.tensor(a, dtype=torch.float64) for a in (0.1, 0.2, 0.3)))
    out, valid = rotate_panorama(depth, R, invalid=-1.0, cache=False)
    assert (out[valid] == 7.0).all() and (out[~valid] == -1.0).all()
    nan_map = depth.clone()
    nan_map[:, 4:9, 3:11] = float("nan")                     # non-finite taps never blend either
    out, valid = rotate_panorama(nan_map, R, mode="masked", cache=False)
    assert torch.isfinite(out).all() and (out[valid] == 7.0).all()
