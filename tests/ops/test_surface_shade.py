"""``omnidl::surface_shade``: the registered op (``torch.library.opcheck``), and its native CPU kernel against its
PyTorch implementation on whole renders.

Labels, validity, depth and layout keys must be equal; the camera-frame normal to 1e-5, the image to 1e-5 but for
a few pixels (see ``_assert_image_close``; on an MKL build on Intel CPUs they are bit-identical: the native kernel
sums the three matrix products as sgemm does there). Scenes are varied so that every texture kind, emissive
materials, wall openings, boxes, shadows and pixels without a hit are exercised.
"""
import dataclasses
import sys

import numpy as np
import pytest
import torch

from omnidl.cameras import build, resolve_camera
from omnidl.ops import surface_shade as S
from omnidl.synth import materials as M
from omnidl.synth import place_camera, render, sample_room

native = pytest.mark.skipif(S.native_library() is None, reason="the native CPU kernel cannot be built here")

CAMERAS = {
    "equirect": lambda: build({"type": "equirect", "width": 96, "height": 48}),
    "noncentral_pano": lambda: build({"type": "noncentral_pano", "width": 96, "height": 48, "rc": 0.8}),
    "fisheye": lambda: resolve_camera("fisheye_equiangular", 48, 48),      # pixels without a ray
    "pinhole": lambda: build({"type": "pinhole", "width": 48, "height": 36, "fx": 30.0, "fy": 30.0,
                              "cx": 24.0, "cy": 18.0}),
}


def _both(scene, cam, pose, monkeypatch, **kw):
    """The render with the native CPU kernel and with the op's PyTorch implementation."""
    assert S.native_library() is not None
    fast = render(scene, cam, pose, **kw)
    with monkeypatch.context() as m:
        m.setattr(S, "native_library", lambda: None)                   # as on a machine without a compiler
        slow = render(scene, cam, pose, **kw)
    return fast, slow


def _assert_same(a, b, what):
    assert a.keys() == b.keys() and a["meta"] == b["meta"], what
    for k in a:
        if k == "meta":
            continue
        assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, (what, k)
        if k == "image":
            _assert_image_close(a[k], b[k], f"{what} {k}")
        elif k == "normal":
            torch.testing.assert_close(a[k], b[k], rtol=1e-5, atol=1e-5, msg=f"{what} {k}")
        else:
            assert torch.equal(a[k], b[k]), (what, k)


def _assert_image_close(a, b, what):
    """Images ``(3, H, W)`` equal to 1e-5 but for at most 0.1 % of the pixels (at least one), off by at most 1e-3:
    where the shading is steep in the surface coordinates, the last bits of those coordinates (the products with
    ``R^T`` and the lights, summed in the BLAS's order, which differs between CPUs: MKL on an AMD EPYC host moved
    one pixel of seed 10's rooms by 1.1e-4) move the colour by more than float32 rounding. A wrong texture cell,
    surface or light would move far more pixels, or by more."""
    d = (a - b).abs().amax(0)
    off = d > 1e-5 * (1 + b.abs().amax(0))
    assert int(off.sum()) <= max(1, off.numel() // 1000) and float(d.max()) <= 1e-3, \
        f"{what}: {int(off.sum())} of {off.numel()} pixels off by up to {float(d.max()):.3g}"


def _with_texture(scene, kind, scale=None):
    """``scene`` with every material's texture set to ``kind`` (and its scale to ``scale`` if given)."""
    m = {k: np.array(v, copy=True) for k, v in scene.materials.items()}
    m["texture"][:] = kind
    if scale is not None:
        m["scale"][:] = scale
    return dataclasses.replace(scene, materials=m)


@native
@pytest.mark.parametrize("name", list(CAMERAS))
@pytest.mark.parametrize("seed", [3, 10])
def test_every_output_matches_the_pytorch_implementation(name, seed, monkeypatch):
    cam = CAMERAS[name]()
    sc = sample_room(seed)
    for rotation in ("upright", "random"):
        try:
            pose = place_camera(sc, cam, seed, rotation=rotation)
        except RuntimeError:
            continue
        _assert_same(*_both(sc, cam, pose, monkeypatch), f"{name} {seed} {rotation}")


@native
@pytest.mark.parametrize("kind", [M.PLAIN, M.STRIPES, M.CHECKER, M.NOISE, M.PLANKS, M.PANEL, 9])
def test_every_texture_kind_matches(kind, monkeypatch):
    """Kind 9 is not a named texture: texture_mix's last branch (planks) takes it, as the native kernel does."""
    cam = CAMERAS["equirect"]()
    sc = sample_room(4)
    pose = place_camera(sc, cam, 4)
    for scale in (None, 1e-5, 0.37):       # 1e-5: clamped to 1e-3, thousands of cells, negative cell indices
        _assert_same(*_both(_with_texture(sc, kind, scale), cam, pose, monkeypatch), f"kind {kind} scale {scale}")


@native
def test_emissive_materials_and_a_room_without_objects(monkeypatch):
    cam = CAMERAS["noncentral_pano"]()
    sc = sample_room(6)
    m = {k: np.array(v, copy=True) for k, v in sc.materials.items()}
    m["emissive"][::2] = True
    lit = dataclasses.replace(sc, materials=m)
    _assert_same(*_both(lit, cam, place_camera(lit, cam, 6), monkeypatch), "emissive")
    bare = sample_room(2, furniture=False)
    assert len(bare.boxes) == 0
    _assert_same(*_both(bare, cam, place_camera(bare, cam, 2), monkeypatch), "no boxes")


@native
def test_overlapping_panel_openings_keep_the_pytorch_implementations_order(monkeypatch):
    """A later opening over an earlier PANEL one takes the surface but keeps the panel's coordinates unless it is a
    panel too: the order of the PyTorch implementation's loop."""
    cam = CAMERAS["equirect"]()
    sc = sample_room(8)
    assert len(sc.decals)
    dec = np.concatenate([sc.decals, sc.decals[:1]])
    dec[-1, 1:5] = dec[0, 1] - 0.2, dec[0, 2] - 0.3, dec[0, 3] + 0.1, dec[0, 4] + 0.4
    m = {k: np.array(v, copy=True) for k, v in sc.materials.items()}
    first = int(sc.decal_material[0])
    m["texture"][first] = M.PANEL
    over = dataclasses.replace(sc, decals=dec, decal_material=np.append(sc.decal_material, sc.floor_material),
                               materials=m)
    fast, slow = _both(over, cam, place_camera(over, cam, 8), monkeypatch)
    _assert_same(fast, slow, "overlapping openings")


def test_threads_do_not_change_the_result():
    cam = CAMERAS["noncentral_pano"]()
    sc = sample_room(11)
    pose = place_camera(sc, cam, 11)
    a = render(sc, cam, pose, threads=1)
    b = render(sc, cam, pose, threads=3)
    for k in a:
        if k != "meta":
            assert torch.equal(a[k], b[k]), k


@native
@pytest.mark.parametrize("name", ["equirect", "noncentral_pano"])
def test_shadows_match(name, monkeypatch):
    cam = CAMERAS[name]()
    sc = sample_room(5)
    _assert_same(*_both(sc, cam, place_camera(sc, cam, 5), monkeypatch, shadows=True), f"{name} shadows")


def _captured(seed=5, name="noncentral_pano", **kw):
    """The arguments the renderer passes to the op for one frame."""
    calls = []
    module = sys.modules["omnidl.synth.render"]
    real = module.surface_shade
    module.surface_shade = lambda *a: calls.append(a) or real(*a)
    try:
        cam = CAMERAS[name]()
        sc = sample_room(seed)
        render(sc, cam, place_camera(sc, cam, seed), **kw)
    finally:
        module.surface_shade = real
    assert len(calls) == 1
    return calls[0]


@pytest.mark.parametrize("kw", [{}, {"shadows": True}, {"dtype": torch.float64}])
def test_opcheck(kw):
    """Schema, fake kernel (torch.compile / torch.export) and dispatch of the op, on a frame's real operands."""
    args = _captured(**kw)
    assert (args[-1] is not None) == bool(kw.get("shadows"))
    torch.library.opcheck(torch.ops.omnidl.surface_shade.default, args)


def test_opcheck_small_operands():
    pixels, tables = _operands(P=5, K=1, B=1, M=2, L=2)
    pixels["point"] = torch.rand(3, 5)
    pixels["box_id"] = torch.tensor([-1, 0, -1, -1, 0])
    pixels["kind"] = torch.tensor([2, 2, 1, 3, 0])
    torch.library.opcheck(torch.ops.omnidl.surface_shade.default,
                          (*pixels.values(), *tables, torch.eye(3), torch.rand(2, 5)))


def test_the_op_under_torch_compile_gives_the_eager_result():
    args = _captured(seed=3, name="equirect")
    eager = S.surface_shade(*args)
    compiled = torch.compile(lambda *a: torch.ops.omnidl.surface_shade(*a), fullgraph=True, backend="eager")(*args)
    for a, b in zip(eager, compiled):
        assert torch.equal(a, b)


def test_the_cpu_kernel_runs_the_pytorch_implementation_for_float64(monkeypatch):
    monkeypatch.setattr(S, "native_library", lambda: pytest.fail("the native kernel was asked for"))
    cam = CAMERAS["equirect"]()
    sc = sample_room(5)
    render(sc, cam, place_camera(sc, cam, 5), dtype=torch.float64)


def _operands(P=4, K=1, B=1, M=2, L=1, n_walls=4):
    S_ = n_walls + 2 + K + B
    tables = S.SurfaceTables(
        n_walls, torch.zeros(K, 6), torch.zeros(K, dtype=torch.int64), torch.zeros(K, dtype=torch.bool),
        torch.zeros(B, 8), torch.zeros(S_, dtype=torch.int64), torch.zeros(S_, dtype=torch.int64),
        torch.zeros(S_, dtype=torch.int64), torch.zeros(n_walls + 2 + K, 3), torch.zeros(M, 6),
        torch.zeros(M, dtype=torch.int64), torch.ones(M), torch.zeros(M, dtype=torch.bool), torch.zeros(L, 4), 0.3)
    pixels = dict(point=torch.zeros(3, P), direction=torch.ones(3, P), hit=torch.ones(P, dtype=torch.bool),
                  box_id=torch.full((P,), -1), kind=torch.full((P,), 2), wall=torch.zeros(P, dtype=torch.int64),
                  wall_s=torch.zeros(P))
    return pixels, tables


@pytest.mark.parametrize("field, value, message", [
    ("point", torch.zeros(3, 4, dtype=torch.int64), "point must be a floating-point tensor"),
    ("direction", torch.zeros(3, 4, dtype=torch.float64), "direction must be a torch.float32"),
    ("hit", torch.ones(4), "hit must be a torch.bool"),
    ("box_id", torch.zeros(5, dtype=torch.int64), r"box_id must be .* shape \(4,\)"),
    ("wall_s", torch.zeros(4, 1), r"wall_s must be .* shape \(4,\)"),
    ("boxes", torch.zeros(1, 9), r"boxes must be .* shape \(1, 8\)"),
    ("normal", torch.zeros(8, 3), r"normal must be .* shape \(7, 3\)"),
    ("scale", torch.ones(2, dtype=torch.float64), "scale must be a torch.float32"),
    ("semantic", torch.zeros(7, dtype=torch.int64), r"semantic must be .* shape \(8,\)"),
    ("material", torch.full((8,), 2), r"material holds an index outside \[0, 2\)"),
    ("box_id", torch.tensor([-1, 1, -1, -1]), "box_id holds a box index of 1 or more"),
    ("wall", torch.tensor([0, 4, 0, 0]), r"wall outside \[0, 4\)"),
    ("wall", torch.tensor([0, -1, 0, 0]), r"wall outside \[0, 4\)"),
])
@pytest.mark.parametrize("kernel", ["native", "pytorch"])
def test_bad_operands_are_named_errors(field, value, message, kernel, monkeypatch):
    if kernel == "pytorch":
        monkeypatch.setattr(S, "native_library", lambda: None)
    elif S.native_library() is None:
        pytest.skip("the native CPU kernel cannot be built here")
    pixels, tables = _operands()
    if field in pixels:
        pixels[field] = value
    else:
        tables = tables._replace(**{field: value})
    with pytest.raises(ValueError, match=message):
        S.surface_shade(*pixels.values(), *tables, torch.eye(3))


@pytest.mark.parametrize("kernel", ["native", "pytorch"])
def test_a_pixel_on_a_box_gets_the_face_normal_and_the_box_labels(kernel, monkeypatch):
    """One pixel by hand: a hit on the +x face of a box yawed by 90 degrees (outward normal +y in the world)."""
    if kernel == "pytorch":
        monkeypatch.setattr(S, "native_library", lambda: None)
    elif S.native_library() is None:
        pytest.skip("the native CPU kernel cannot be built here")
    pixels, tables = _operands(P=1, K=0, B=1)
    c, s = float(np.cos(np.pi / 2)), float(np.sin(np.pi / 2))
    tables = tables._replace(boxes=torch.tensor([[0.0, 0.0, 1.0, 0.5, 0.2, 0.3, c, s]], dtype=torch.float32),
                             semantic=torch.arange(7), instance=torch.arange(7) + 10,
                             colour=torch.tensor([[0.5, 0.5, 0.5, 0.0, 0.0, 0.0]] * 2),
                             lights=torch.tensor([[0.0, 3.0, 1.0, 1.0]]))
    pixels.update(point=torch.tensor([[0.0], [0.5], [1.0]]), direction=torch.tensor([[0.0], [-1.0], [0.0]]),
                  box_id=torch.tensor([0]))
    image, sem, inst, normal = S.surface_shade(*pixels.values(), *tables, torch.eye(3))
    assert sem.tolist() == [6] and inst.tolist() == [16]                   # surface n_walls + 2 + K + 0
    torch.testing.assert_close(normal[:, 0], torch.tensor([0.0, 1.0, 0.0]), atol=1e-6, rtol=0)
    light = 0.3 + 1.0 * (2.5 / 2.5) / (1 + 0.25 * 2.5 ** 2)               # ambient + power * cos / (1 + d^2 / 4)
    torch.testing.assert_close(image[:, 0], torch.full((3,), 0.5 * 1.25 * light / (1 + 0.25 * light)))
    half = S.surface_shade(*pixels.values(), *tables, torch.eye(3), torch.tensor([[0.5]]))[0]  # a shadow factor
    light = 0.3 + 0.5 * (2.5 / 2.5) / (1 + 0.25 * 2.5 ** 2)
    torch.testing.assert_close(half[:, 0], torch.full((3,), 0.5 * 1.25 * light / (1 + 0.25 * light)))


def test_every_build_of_the_kernel_matches(kernel_build, monkeypatch):
    """The kernel built for plain x86-64 and for Haswell (no AVX-512) gives the PyTorch implementation's frame too:
    it has no intrinsics, and ISO C keeps the compiler from contracting products into fused multiply-adds."""
    if S.native_library() is None:
        pytest.skip("the native CPU kernel cannot be built here")
    cam = CAMERAS["noncentral_pano"]()
    sc = sample_room(10)
    _assert_same(*_both(sc, cam, place_camera(sc, cam, 10, rotation="random"), monkeypatch, shadows=True),
                 f"{kernel_build} build")
