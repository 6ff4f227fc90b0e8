"""The gyroscopes' native iterations (``native_terms``) against their tensor-op paths and ``sample_panorama``:
reads 1e-5, normal equations 1e-5 relative to their scale, whole solves 1e-5 (float32)."""
import math

import pytest
import torch

from omnidl.geometry.panorama import sample_panorama
from omnidl.geometry.rotations import random_tilt_rotation
from omnidl.nn import native
from omnidl.postprocess.gyroscope import native_terms
from omnidl.postprocess.gyroscope.icosahedron import icosahedron_vertices
from omnidl.postprocess.gyroscope.mpp import mpp_yaw
from omnidl.postprocess.gyroscope.photometric import SphereImage, blur_fast, to_gray
from omnidl.postprocess.gyroscope.pvg import PVGTerms, pvg_refine
from omnidl.postprocess.gyroscope.scene import procedural_panorama

pytestmark = pytest.mark.skipif(native.library() is None, reason="native kernels unavailable")


@pytest.fixture
def tensor_ops(monkeypatch):
    """Run the solvers on their tensor ops (the path the native calls replace)."""
    monkeypatch.setattr(native_terms, "ENABLED", False)


def _frames(n=2, size=(64, 128)):
    R = random_tilt_rotation(n, math.radians(30), generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    ref = procedural_panorama(None, *size, seed=1).float()
    cur = procedural_panorama(R, *size, seed=1).float()
    return R.float(), ref, cur


def _directions(n=3000, seed=0):
    d = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed))
    poles = torch.tensor([[0.0, 1.0, 0.0], [0.0, -2.0, 0.0], [1e-20, 1.0, 0.0]])  # at the poles: longitude 0
    seam = torch.tensor([[0.0, 0.3, -1.0], [-1e-7, 0.0, -1.0], [1e-7, 0.0, -1.0], [-1.0, 0.0, 0.0]])  # lon = +-pi
    return torch.cat([d, poles, seam])


def test_sphere_read_matches_sample_panorama():
    img = torch.rand(3, 16, 32, generator=torch.Generator().manual_seed(1))
    d = _directions()
    got = native_terms.sphere_read(img, d)
    torch.testing.assert_close(got, sample_panorama(img[None], d)[0], rtol=0, atol=1e-5)
    torch.testing.assert_close(got, SphereImage(img[None]).read(d[None])[0], rtol=0, atol=1e-5)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_sphere_read_of_a_non_finite_direction_is_nan(bad):
    d = torch.tensor([[bad, 0.0, 1.0], [0.0, bad, 1.0], [0.0, 0.0, bad], [0.0, 0.0, 1.0]])
    out = native_terms.sphere_read(torch.rand(1, 8, 16), d)
    assert torch.isnan(out[0, :3]).all() and torch.isfinite(out[0, 3])


def test_pvg_normal_equations_match_pvg_terms():
    R, ref, cur = _frames()
    X = icosahedron_vertices(4, torch.float32)
    img = blur_fast(to_gray(cur), 1.5)
    I_ref = torch.rand(1, X.shape[0], generator=torch.Generator().manual_seed(2))
    h = math.pi / img.shape[-2]
    T = PVGTerms(X, 2)(SphereImage(img), R, I_ref, h).double()
    expect = T @ T.transpose(1, 2)
    got = native_terms.pvg_normal_equations(img, R, X, I_ref, h)
    scale = expect.abs().amax((1, 2), keepdim=True)
    torch.testing.assert_close(got / scale, expect / scale, rtol=0, atol=1e-5)
    # one reference row per image gives the same sums as a shared row
    torch.testing.assert_close(native_terms.pvg_normal_equations(img, R, X, I_ref.expand(2, -1).clone(), h), got)


@pytest.mark.parametrize("start", ["near", "identity"])
def test_pvg_stage_matches_the_tensor_loop(start, monkeypatch):
    R, ref, cur = _frames()
    R0 = R if start == "near" else None
    fast = pvg_refine(cur, ref, R0, level=3, max_iter=8)
    monkeypatch.setattr(native_terms, "ENABLED", False)
    slow = pvg_refine(cur, ref, R0, level=3, max_iter=8)
    assert fast.iterations == slow.iterations
    torch.testing.assert_close(fast.rotation, slow.rotation, rtol=0, atol=1e-5)
    torch.testing.assert_close(fast.cost, slow.cost, rtol=1e-4, atol=1e-7)


def test_pvg_partial_axes_use_the_native_sums(monkeypatch):
    R, ref, cur = _frames()
    kw = dict(level=3, max_iter=5, dofs=(False, True, False), blur_px=(1.0,))
    fast = pvg_refine(cur, ref, R, **kw)
    monkeypatch.setattr(native_terms, "ENABLED", False)
    torch.testing.assert_close(fast.rotation, pvg_refine(cur, ref, R, **kw).rotation, rtol=0, atol=1e-5)


@pytest.mark.parametrize("tries", [1, 4])
def test_mpp_loop_matches_the_tensor_loop(tries, monkeypatch):
    R, ref, cur = _frames()
    fast = mpp_yaw(cur, ref, R, level=3, tries=tries)
    monkeypatch.setattr(native_terms, "ENABLED", False)
    slow = mpp_yaw(cur, ref, R, level=3, tries=tries)
    assert fast.iterations == slow.iterations
    torch.testing.assert_close(fast.yaw, slow.yaw, rtol=0, atol=1e-5)
    torch.testing.assert_close(fast.cost, slow.cost, rtol=1e-5, atol=0)


def test_mpp_without_iterations_keeps_the_starts():
    R, ref, cur = _frames(1)
    r = mpp_yaw(cur, ref, R, level=2, tries=4, max_iter=0)
    assert r.iterations == 0 and torch.isinf(r.cost).all()


def test_non_finite_inputs_give_nan_not_a_plausible_answer():
    R, ref, cur = _frames(1)
    bad = cur.clone()
    bad[..., 10, 20] = float("nan")
    assert torch.isnan(pvg_refine(bad, ref, R, level=3, max_iter=3).cost).all()
    Rn = R.clone()
    Rn[0, 0, 0] = float("nan")
    assert torch.isnan(pvg_refine(cur, ref, Rn, level=3, max_iter=3).rotation).all()


def test_applies_only_to_float32_cpu(tensor_ops):
    assert not native_terms.applies(torch.zeros(2))


def test_without_the_library_the_solvers_keep_their_tensor_ops(monkeypatch):
    R, ref, cur = _frames(1)
    fast = pvg_refine(cur, ref, R, level=3, max_iter=3)
    monkeypatch.setattr(native, "library", lambda: None)
    assert not native_terms.applies(torch.zeros(2))
    slow = pvg_refine(cur, ref, R, level=3, max_iter=3)
    torch.testing.assert_close(fast.rotation, slow.rotation, rtol=0, atol=1e-5)
    assert mpp_yaw(cur, ref, R, level=2, tries=2).iterations > 0


def test_applies_to_float32_not_float64():
    assert native_terms.applies(torch.zeros(2))
    assert not native_terms.applies(torch.zeros(2), torch.zeros(2, dtype=torch.float64))


@pytest.mark.parametrize("call, match", [
    (lambda: native_terms.sphere_read(torch.rand(8, 16), torch.rand(4, 3)), "expected image"),
    (lambda: native_terms.pvg_normal_equations(torch.rand(1, 3, 8, 16), torch.eye(3)[None], torch.rand(5, 3),
                                               torch.rand(1, 5), 0.1), "shape \\(B, 1, H, W\\)"),
    (lambda: native_terms.pvg_normal_equations(torch.rand(1, 1, 8, 16), torch.eye(3)[None], torch.rand(5, 3),
                                               torch.rand(1, 4), 0.1), "I_ref must have shape"),
    (lambda: native_terms.sphere_read(torch.rand(1, 8, 16, dtype=torch.float64), torch.rand(4, 3)),
     "image must be a float32 CPU tensor"),
    (lambda: native_terms.pvg_normal_equations(torch.rand(1, 1, 8, 16), torch.eye(3, dtype=torch.float64)[None],
                                               torch.rand(5, 3), torch.rand(1, 5), 0.1), "R must be a float32"),
    (lambda: native_terms.mpp_yaw_loop(torch.rand(1, 4, 8, 16), torch.rand(1, 3, 12), torch.rand(1, 2),
                                       torch.zeros(1, 1, dtype=torch.float64), 3, 1e-6), "theta must be a float32"),
    (lambda: native_terms.mpp_yaw_loop(torch.rand(1, 4, 8, 8), torch.rand(1, 3, 12), torch.rand(1, 2),
                                       torch.zeros(1, 1), 3, 1e-6), "table must have shape"),
    (lambda: native_terms.mpp_yaw_loop(torch.rand(1, 4, 8, 16), torch.rand(1, 2, 12), torch.rand(1, 2),
                                       torch.zeros(1, 1), 3, 1e-6), "basis must have shape"),
])
def test_bad_operands_are_named(call, match):
    with pytest.raises(ValueError, match=match):
        call()
