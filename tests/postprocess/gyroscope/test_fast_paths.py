"""The gyroscope's solvers (prepared sphere images, cached MPP kernels, Gauss-Newton loops in buffers allocated once)
give the results of the reference implementations (``tests/reference/gyroscope.py``): 1e-5 in float32, 1e-12 in
float64."""
import math

import pytest
import torch

from omnidl.geometry.panorama import sample_panorama
from omnidl.geometry.rotations import random_tilt_rotation
from omnidl.postprocess.gyroscope.icosahedron import icosahedron_vertices
from omnidl.postprocess.gyroscope.mpp import mpp_field, mpp_table, mpp_vertex_field, mpp_yaw
from omnidl.postprocess.gyroscope.photometric import SphereImage, rodrigues
from omnidl.postprocess.gyroscope.pvg import pvg_refine
from omnidl.postprocess.gyroscope.scene import procedural_panorama
from omnidl.utils.threads import limit_threads
from tests.reference.gyroscope import (apply_update, blur, mpp_table_reference, mpp_yaw_reference,
                                       pvg_refine_reference, rotation_jacobian, spherical_gradient)

TOL = {torch.float32: 1e-5, torch.float64: 1e-12}


def _frames(dtype, size=(64, 128), n=2):
    R = random_tilt_rotation(n, math.radians(30), generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    ref = procedural_panorama(None, *size, seed=1).to(dtype)
    cur = procedural_panorama(R, *size, seed=1).to(dtype)
    return R.to(dtype), ref, cur


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_mpp_table_and_vertex_field_match_mpp_field(dtype):
    X = icosahedron_vertices(2, dtype)
    I = torch.rand(2, X.shape[0], generator=torch.Generator().manual_seed(2), dtype=dtype)
    I = I / I.sum(-1, keepdim=True)
    from omnidl.cameras.equirectangular import Equirectangular
    d = Equirectangular(width=32, height=16).unproject_grid(dtype).direction.reshape(-1, 3)
    G, grad = mpp_field(X, I, d.unsqueeze(0).expand(2, -1, -1), 0.325, with_grad=True)
    expect = torch.cat([G.unsqueeze(-1), grad], -1).transpose(1, 2).reshape(2, 4, 16, 32)
    got = mpp_table(X, I, 0.325, 16)
    scale = expect.abs().max()
    torch.testing.assert_close(got / scale, expect / scale, rtol=0, atol=TOL[dtype])
    Gx = mpp_field(X, I, X.unsqueeze(0), 0.325)[0]
    torch.testing.assert_close(mpp_vertex_field(X, I, 0.325) / scale, Gx / scale, rtol=0, atol=TOL[dtype])
    # not an icosahedron: the exact evaluation
    torch.testing.assert_close(mpp_table(X.clone()[:-1], I[:, :-1], 0.325, 16).shape, torch.Size([2, 4, 16, 32]))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("kw", [dict(tries=4), dict(tries=1), dict(tries=1, grid_height=0, max_iter=6)])
def test_mpp_matches_reference(dtype, kw):
    R, ref, cur = _frames(dtype)
    fast = mpp_yaw(cur, ref, R, level=2, **kw)
    slow = mpp_yaw_reference(cur, ref, R, level=2, **kw)
    tol = TOL[dtype]
    torch.testing.assert_close(fast.yaw, slow.yaw, rtol=0, atol=tol)
    torch.testing.assert_close(fast.rotation, slow.rotation, rtol=0, atol=tol)
    torch.testing.assert_close(fast.cost, slow.cost, rtol=tol, atol=0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("start", ["near", "identity"])
def test_pvg_matches_reference(dtype, start):
    R, ref, cur = _frames(dtype)
    R0 = R if start == "near" else None
    fast = pvg_refine(cur, ref, R0, level=3, max_iter=8)
    slow = pvg_refine_reference(cur, ref, R0, level=3, max_iter=8)
    tol = TOL[dtype]
    assert fast.iterations == slow.iterations
    torch.testing.assert_close(fast.rotation, slow.rotation, rtol=0, atol=tol)
    torch.testing.assert_close(fast.cost, slow.cost, rtol=0, atol=tol)
    partial = dict(dofs=(False, True, False), blur_px=(1.0,))
    torch.testing.assert_close(pvg_refine(cur, ref, R0, level=3, max_iter=5, **partial).rotation,
                               pvg_refine_reference(cur, ref, R0, level=3, max_iter=5, **partial).rotation,
                               rtol=0, atol=tol)


def test_limit_threads_restores():
    before = torch.get_num_threads()
    with limit_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
    with limit_threads(None):
        assert torch.get_num_threads() == before


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_rodrigues_matches_apply_update(dtype):
    g = torch.Generator().manual_seed(3)
    w = torch.randn(60, 3, generator=g, dtype=dtype) * torch.logspace(-12, 0.5, 60, dtype=dtype)[:, None]
    w = torch.cat([w, torch.zeros(1, 3, dtype=dtype)])
    eye = torch.eye(3, dtype=dtype).expand(61, 3, 3)
    torch.testing.assert_close(rodrigues(w), apply_update(eye, w), rtol=0, atol=TOL[dtype])
    assert torch.equal(rodrigues(torch.zeros(2, 3, dtype=dtype)), torch.eye(3, dtype=dtype).expand(2, 3, 3))


def test_pipeline_thread_policy_does_not_change_the_estimate(monkeypatch):
    """photometric_threads only changes how many intra-op threads run (1 when the CPUs are oversubscribed)."""
    from omnidl.utils import threads as T
    from omnidl.postprocess.gyroscope.pipeline import Gyroscope, GyroscopeOptions
    R, ref, cur = _frames(torch.float32, n=1)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        out = {}
        for policy in ("auto", 1, None):
            monkeypatch.setattr(T, "runnable_tasks", lambda: 10 ** 6)  # "auto" -> 1 thread
            g = Gyroscope(None, GyroscopeOptions(work_height=64, mpp_level=2, pvg_level=3, pvg_max_iter=5,
                                                 photometric_threads=policy))
            g.set_reference(ref[0])
            out[policy] = g.estimate(cur)["rotation"]
            assert torch.get_num_threads() == 2
        assert GyroscopeOptions().photometric_threads == "auto"
        torch.testing.assert_close(out["auto"], out[None], rtol=0, atol=1e-5)
        assert torch.equal(out["auto"], out[1])
    finally:
        torch.set_num_threads(before)


def test_model_horizon_fn_thread_policy(monkeypatch):
    from omnidl.models import create_model
    from omnidl.utils import threads as T
    from omnidl.postprocess.gyroscope.pipeline import model_horizon_fn
    torch.manual_seed(0)
    m = create_model("holinet", backbone="resnet18", width=0.125, conv="standard")
    x = torch.rand(1, 3, 64, 128)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        ref = model_horizon_fn(m, 32, threads=None)(x)
        monkeypatch.setattr(T, "runnable_tasks", lambda: 10 ** 6)
        got = model_horizon_fn(m, 32)(x)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    for a, b in zip(got, ref):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-5)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_read_xyz_reads_like_sample_panorama(dtype):
    """Component-row reads (the solvers' layout), poles and near-poles included, batch 1 broadcast."""
    g = torch.Generator().manual_seed(4)
    img = procedural_panorama(None, 32, 64, seed=3).to(dtype).expand(2, -1, -1, -1)
    d = torch.randn(2, 300, 3, generator=g, dtype=dtype)
    poles = torch.tensor([[0, 1.0, 0], [0, -1.0, 0], [1e-17, 1, 0], [0, 0, -1], [-1e-7, 0, -1]], dtype=dtype)
    d = torch.cat([d, poles[None].expand(2, -1, -1)], 1)
    si = SphereImage(img)
    expect = sample_panorama(img, d)
    torch.testing.assert_close(si.read_xyz(*d.transpose(1, 2).unbind(1)), expect, rtol=0, atol=TOL[dtype])
    no_pole = d[:1, :300].transpose(1, 2)  # (1, 3, M): broadcast over the image batch, the no-pole branch
    torch.testing.assert_close(si.read_xyz(*no_pole.unbind(1)), sample_panorama(img, d[0, :300]), rtol=0,
                               atol=TOL[dtype])
    torch.testing.assert_close(si.read_grid(*no_pole.unbind(1))[:, :, 0], si.read_xyz(*no_pole.unbind(1)))
    many = torch.randn(1, 20000, 3, generator=g, dtype=dtype)  # >= 16384 points: the pole check branch
    for dd in (many, torch.cat([many, poles[None]], 1)):
        torch.testing.assert_close(si.read_xyz(*dd.transpose(1, 2).unbind(1)), sample_panorama(img, dd[0]), rtol=0,
                                   atol=TOL[dtype])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("sigma", [0.5, 1.5, 2.8, 4.0, 0.0])
def test_blur_fast_matches_blur(dtype, sigma):
    from omnidl.postprocess.gyroscope.photometric import blur_fast
    img = torch.rand(2, 1, 16, 32, generator=torch.Generator().manual_seed(5), dtype=dtype)
    torch.testing.assert_close(blur_fast(img, sigma), blur(img, sigma), rtol=0, atol=TOL[dtype])
    small = torch.rand(1, 1, 4, 8, generator=torch.Generator().manual_seed(6), dtype=dtype)  # radius > W:
    with pytest.raises(RuntimeError):  # the padded convolutions cannot wrap more than once
        blur(small, 4.0)
    if sigma:  # the matrices wrap the taps around as often as needed: still a weighted mean
        flat = blur_fast(torch.full_like(small, 0.3), sigma * 4)
        torch.testing.assert_close(flat, torch.full_like(small, 0.3), rtol=0, atol=TOL[dtype])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("height", [16, 15])  # 16: the octant kernels + 8 sign flips in float32; 15: no octant
def test_mpp_table_matches_the_full_kernels(dtype, height):
    from omnidl.postprocess.gyroscope.mpp import _symmetric_kernels
    X = icosahedron_vertices(2, dtype)
    I = torch.rand(3, X.shape[0], generator=torch.Generator().manual_seed(7), dtype=dtype)
    I = I / I.sum(-1, keepdim=True)
    expect = mpp_table_reference(X, I, 0.325, height)
    scale = expect.abs().max()
    torch.testing.assert_close(mpp_table(X, I, 0.325, height) / scale, expect / scale, rtol=0, atol=TOL[dtype])
    assert (_symmetric_kernels(2, 0.325, height, torch.float32, "cpu") is None) == (height % 2 == 1)
    Y = X.clone()[:-1]  # not an icosahedron: the exact evaluation, as the reference table
    assert torch.equal(mpp_table(Y, I[:, :-1], 0.325, 16), mpp_table_reference(Y, I[:, :-1], 0.325, 16))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_pvg_terms_give_the_reference_jacobian(dtype):
    """PVGTerms rows u with R u = (R grad) x X (the reference Jacobian) and e = I_cur(R.T X) - I_ref."""
    from omnidl.postprocess.gyroscope.pvg import PVGTerms
    R, ref, cur = _frames(dtype)
    gray = cur.mean(1, keepdim=True)
    X = icosahedron_vertices(3, dtype)
    I_ref = torch.rand(1, X.shape[0], generator=torch.Generator().manual_seed(8), dtype=dtype)
    out = PVGTerms(X, 2)(SphereImage(gray), R, I_ref).clone()
    p = torch.einsum("bji,nj->bni", R, X)
    v, grad = spherical_gradient(gray, p)
    J = rotation_jacobian(grad, R, X)
    torch.testing.assert_close((R @ out[:, :3]).transpose(1, 2), J, rtol=0, atol=100 * TOL[dtype])
    torch.testing.assert_close(out[:, 3], v - I_ref, rtol=0, atol=TOL[dtype])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_prepared_references_match(dtype):
    """pvg_reference_values / mpp_vertex_field prepared once give the results of the unprepared calls."""
    from omnidl.postprocess.gyroscope.mpp import mpp_samples
    from omnidl.postprocess.gyroscope.pvg import pvg_reference_values
    from omnidl.postprocess.gyroscope.photometric import to_gray
    R, ref, cur = _frames(dtype)
    vals = pvg_reference_values(ref, 3, (2.0, 0.5))
    X = icosahedron_vertices(3, dtype)
    for k, s in enumerate((2.0, 0.5)):
        torch.testing.assert_close(vals[k], sample_panorama(blur(to_gray(ref), s), X)[:, 0], rtol=0, atol=TOL[dtype])
    a = pvg_refine(cur, ref, R, level=3, max_iter=5, blur_px=(2.0, 0.5))
    b = pvg_refine(cur, None, R, level=3, max_iter=5, blur_px=(2.0, 0.5), reference_values=vals)
    assert torch.equal(a.rotation, b.rotation) and torch.equal(a.cost, b.cost)
    with pytest.raises(ValueError, match="do not fit"):
        pvg_refine(cur, None, R, level=3, blur_px=(1.0,), reference_values=vals)
    Xm, Ir = mpp_samples(ref, 2)
    field = mpp_vertex_field(Xm, Ir, 0.325)
    c = mpp_yaw(cur, ref, R, level=2)
    d = mpp_yaw(cur, None, R, level=2, reference_field=field)
    assert torch.equal(c.rotation, d.rotation) and torch.equal(c.cost, d.cost)
