"""Calibrated convolution offsets (thesis §7.3.2) on the 195° camera: the public recipe (ported as coded,
checked against its reference values) against omnidl.nn.compute_sampling."""
import math

import numpy as np
import pytest

from omnidl.cameras.kannala_brandt import KannalaBrandt
from omnidl.cameras import resolve_camera
from omnidl.nn.offsets import compute_sampling

from .recipe_reference import F195, kb_inv, recipe_offsets, scaled_calibration


@pytest.fixture(autouse=True)
def _one_thread(single_thread):
    """Small tensors: one intra-op thread (see tests/conftest.py)."""
    yield


@pytest.mark.parametrize("u, v, w, h, off_x0, off_y0", [
    (540, 480, 1082, 960, [0.09725, 0.0, -0.09725], [0.09725] * 3),
    (800, 480, 1082, 960, [0.0964, -0.00096, -0.09832], [-0.03811, -0.03915, -0.0402]),
    (540, 100, 1082, 960, [-0.23452, 0.0, 0.23452], [0.09939, 0.09774, 0.09939]),
    (400, 240, 541, 480, [0.09543, -0.00193, -0.09929], None),
])
def test_recipe_port_matches_reference_values(u, v, w, h, off_x0, off_y0):
    oy, ox = recipe_offsets(F195, w, h, u, v)
    np.testing.assert_allclose(ox[0], off_x0, atol=1e-5)
    if off_y0 is not None:
        np.testing.assert_allclose(oy[0], off_y0, atol=1e-5)


def test_recipe_scaling_reference_values():
    assert scaled_calibration(F195, 541, 480) == pytest.approx((270.0, 240.0, 143.5, 143.5))


def omnidl_camera_for_recipe(calib, img_w, img_h, fx_full=None):
    """Explicit adapter: the recipe's feature-map calibration (Eq. 7.3 as coded, integer-centred pixels)
    as an omnidl camera of the map size (pixel centres at +0.5)."""
    calib = list(calib)
    if fx_full is not None:
        calib[2] = calib[3] = fx_full
    cx, cy, fx, fy = scaled_calibration(calib, img_w, img_h)
    return KannalaBrandt(width=img_w, height=img_h, fx=fx, fy=fy, cx=cx + 0.5, cy=cy + 0.5, k0=1.0,
                         k1=calib[7], k2=calib[8], k3=calib[9], k4=calib[10], max_fov=math.radians(calib[6]))


def _compare(cam, calib, w, h, pitch=None, stride=16):
    """Worst |omnidl - recipe| offset (px) over the anchors (multiples of ``stride``) whose taps are all seen.

    The kernel at an anchor does not depend on the stride (omnidl computes strided layers at output
    positions, anchor = output index * stride), so a stride samples the map cheaply."""
    off, mask = compute_sampling(cam, (h, w), 3, stride=stride, padding=1, kernel="tangent")
    ho, wo = off.shape[-2:]
    off = off[0].reshape(9, 2, ho, wo)
    full = mask[0].all(0)
    worst, n = 0.0, 0
    for oy in range(ho):
        for ox in range(wo):
            if not bool(full[oy, ox]):
                continue
            oy_ref, ox_ref = recipe_offsets(calib, w, h, ox * stride, oy * stride, pitch=pitch)
            got_y = off[:, 0, oy, ox].numpy().reshape(3, 3)
            got_x = off[:, 1, oy, ox].numpy().reshape(3, 3)
            worst = max(worst, np.abs(got_y - oy_ref).max(), np.abs(got_x - ox_ref).max())
            n += 1
    return worst, n


# The recipe's Eq. 7.3 scaling is isotropic (fx' = fy') on the full 1082 x 960 map and on its half,
# 541 x 480 (the next sizes, 270 x 240 etc., scale x and y differently); the comparison uses 541 x 480.
W_MAP, H_MAP = 541, 480


def test_omnidl_equals_recipe_with_the_recipe_pitch_on_f195_distortion():
    """F195 distortion with the focal length whose pixel pitch equals the recipe's kernel pitch
    (fx' = map width / FOV): omnidl's tangent kernel reproduces the recipe as coded."""
    fx_full = 2 * W_MAP / math.radians(195)   # fx' = fx / 2 = W_map / FOV: one pixel at the principal point
    calib = list(F195)
    calib[2] = calib[3] = fx_full
    cam = omnidl_camera_for_recipe(F195, W_MAP, H_MAP, fx_full)
    worst, n = _compare(cam, calib, W_MAP, H_MAP)
    assert n > 300
    assert worst < 1e-4   # pitch 2tan(3d/2)/3 vs tan(d): ~0.4 d^3 rad, a few 1e-5 px where the lens stretches


def test_omnidl_equals_recipe_geometry_on_the_real_f195_with_omnidl_pitch():
    """The real F195 (fx = 287): ProjectedConv2d has no kernel-pitch parameter (its pitch is one pixel at
    the principal point); with the recipe's tap spacing set to that pitch the two agree everywhere."""
    cam = omnidl_camera_for_recipe(F195, W_MAP, H_MAP)
    fx = scaled_calibration(F195, W_MAP, H_MAP)[2]
    pitch = math.tan(kb_inv(1.0 / fx, tuple(F195[7:11])))   # angle of one pixel at the principal point
    worst, n = _compare(cam, F195, W_MAP, H_MAP, pitch=pitch)
    assert n > 300
    assert worst < 1e-6


def test_recipe_pitch_differs_from_omnidl_on_real_f195():
    """Documented difference: the recipe's centre kernel on F195 spans fx/d = 0.903 px, not 1 px."""
    oy, ox = recipe_offsets(F195, 1082, 960, 540, 480)
    d = 3 / (2 * math.tan(3 / 1082 * math.radians(195) / 2))
    assert ox[1, 0] == pytest.approx(1 - 287 * math.atan(1 / d), abs=1e-6)   # fx * theta of the tap
    assert 287 * math.atan(1 / d) == pytest.approx(0.9028, abs=1e-4)
    cam = omnidl_camera_for_recipe(F195, W_MAP, H_MAP)
    off, _ = compute_sampling(cam, (H_MAP, W_MAP), 3, stride=10, padding=1)
    assert float(off[0, :, 24, 27].abs().max()) < 1e-6        # principal point: integer pixel (270, 240)


def test_equidistant_principal_point_kernel_is_the_regular_grid():
    """Equidistant fisheye (r = f theta) with the principal point on a pixel centre: the default kernel
    there is the regular grid (< 1e-6 px), for 3x3 and 5x5 dilation 2."""
    f = 20.0
    cam = KannalaBrandt(width=64, height=64, fx=f, fy=f, cx=32.5, cy=32.5, max_fov=math.radians(195))
    for k, dil in ((3, 1), (5, 2)):
        off, mask = compute_sampling(cam, (64, 64), k, 32, (k // 2) * dil, dil)  # anchors 0 and 32
        assert bool(mask[0, :, 1, 1].all())
        assert float(off[0, :, 1, 1].abs().max()) < 1e-6
        assert float(off[0, :, 0, 1].abs().max()) > 1e-3   # off-centre anchors do deform


def test_equidistant_principal_point_tangent_kernel_closed_form():
    """``kernel="tangent"`` (the thesis' square lattice on the tangent plane, pitch tan(1/f)): the middle
    row/column taps land exactly one pixel apart; a diagonal tap at f*atan(sqrt2*tan(1/f))/sqrt2 per axis."""
    f = 20.0
    cam = KannalaBrandt(width=64, height=64, fx=f, fy=f, cx=32.5, cy=32.5, max_fov=math.radians(195))
    off, _ = compute_sampling(cam, (64, 64), 3, 32, 1, kernel="tangent")
    o = off[0, :, 1, 1].reshape(3, 3, 2)
    for i, j in ((0, 1), (1, 0), (1, 2), (2, 1), (1, 1)):
        assert float(o[i, j].abs().max()) < 1e-9
    diag = 1 - f * math.atan(math.sqrt(2) * math.tan(1 / f)) / math.sqrt(2)
    assert float(o[0, 0, 0]) == pytest.approx(diag, abs=1e-9)   # tap (-1, -1): dy = dx = +diag
    assert float(o[0, 0, 1]) == pytest.approx(diag, abs=1e-9)
    assert float(o[2, 2, 0]) == pytest.approx(-diag, abs=1e-9)


def test_calibrated_offsets_grow_with_radius_on_f195():
    cam = resolve_camera("kb_f195").resized(135, 120)
    off, mask = compute_sampling(cam, (120, 135), 3, 3, 1)     # anchors at multiples of 3
    ho, wo = off.shape[-2:]
    mag = off[0].reshape(9, 2, ho, wo).norm(dim=1).amax(0)
    row = mag[20, 22:]                                          # anchor row 60, columns from 66 (centre 67.5)
    ok = mask[0].all(0)[20, 22:]
    r = row[ok]
    assert float(r[0]) < 1e-3 and float(r[-1]) > 0.2
    assert bool((r[1:] >= r[:-1] - 1e-6).all())
