"""The native fused path (CPU float32) equals the column GEMM path and deform_conv2d at float32 rounding; its
build is cached, and without a compiler the layer falls back to the tiled path with one clear warning."""
from __future__ import annotations

import os
import re
import warnings

import pytest
import torch

from omnidl.cameras import Equirectangular, get_camera_class
from omnidl.nn import ProjectedConv2d, fixed_offset_conv2d, native
from omnidl.nn import fused as fused_module
from omnidl.nn.fused import _FusedConv, block_positions, fused_conv2d, fused_supported
from omnidl.nn.projected_conv import get_plan
from omnidl.nn.sampling import _FixedOffsetConv
from omnidl.nn.tiled import _TiledConv

from .conftest import close_to_scale

pytestmark = pytest.mark.skipif(native.library() is None, reason="the native kernel cannot be built here: "
                                f"{native.status()['reason']}")


def _camera(name: str):
    return Equirectangular(width=48, height=24) if name == "equirect" else get_camera_class(name).example()


def _outputs(m, x, need=("x", "w", "b")):
    xi = x.clone().requires_grad_("x" in need)
    m.weight.requires_grad_("w" in need)
    y = m(xi)
    g = torch.linspace(-1, 1, y.numel()).view_as(y)
    wrt = [t for t, n in ((xi, "x"), (m.weight, "w"), (m.bias, "b")) if n in need and t is not None]
    return (y, *torch.autograd.grad(y, wrt, g)) if wrt else (y,)


@pytest.mark.parametrize("camera", ["equirect", "kannala_brandt", "scaramuzza"])
@pytest.mark.parametrize("k,s,d", [(3, 1, 1), (3, 2, 1), (5, 1, 2), (7, 2, 1), (2, 1, 1), (1, 1, 1)])
@pytest.mark.parametrize("channels_last", [False, True])
def test_fused_equals_columns_and_deform_conv2d(camera, k, s, d, channels_last):
    torch.manual_seed(k * 10 + s + d)
    cam = _camera(camera)
    H, W = (12, 24) if cam.width >= 2 * cam.height else (14, 14)
    pad = d * (k // 2)
    fused = ProjectedConv2d(3, 5, k, stride=s, padding=pad, dilation=d, camera=cam, backend="fast")
    cols = ProjectedConv2d(3, 5, k, stride=s, padding=pad, dilation=d, camera=cam, backend="fast",
                           chunk_positions=7)  # an explicit chunk length keeps the column GEMM path
    ref = ProjectedConv2d(3, 5, k, stride=s, padding=pad, dilation=d, camera=cam, backend="torchvision")
    cols.load_state_dict(fused.state_dict())
    ref.load_state_dict(fused.state_dict())
    x = torch.randn(2, 3, H, W)
    if channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    outs = [_outputs(m, x) for m in (fused, cols, ref)]
    assert type(fused(x).grad_fn).__name__.startswith(_FusedConv.__name__)
    for name, a, b, c in zip(("output", "input grad", "weight grad", "bias grad"), *outs):
        close_to_scale(a, b, name + " vs columns")
        close_to_scale(a, c, name + " vs deform_conv2d")
    # same memory format as the column path: channels-last in, channels-last out
    assert outs[0][0].is_contiguous(memory_format=torch.channels_last) == channels_last
    assert outs[0][1].stride() == outs[1][1].stride()


def _assert_equals_columns(cin: int, cout: int, seed: int, bias: bool = True, batch: int = 2) -> None:
    """The layer (on whatever kernel build is loaded) against the column path: outputs and all gradients."""
    torch.manual_seed(seed)
    cam = Equirectangular(width=40, height=20)
    m = ProjectedConv2d(cin, cout, 3, padding=1, camera=cam, bias=bias)
    cols = ProjectedConv2d(cin, cout, 3, padding=1, camera=cam, bias=bias, chunk_positions=11)
    cols.load_state_dict(m.state_dict())
    x = torch.randn(batch, cin, 10, 20)
    for name, a, b in zip(("output", "input grad", "weight grad", "bias grad"), _outputs(m, x), _outputs(cols, x)):
        close_to_scale(a, b, name)


@pytest.mark.parametrize("cin,cout", [(1, 1), (7, 17), (16, 16), (33, 40), (64, 64)])
@pytest.mark.parametrize("bias", [True, False])
def test_channel_counts_off_the_kernel_tile(cin, cout, bias):
    """Output channels not a multiple of the kernel's 16 (AVX2) or 32 (AVX-512) columns, positions not of its 6 or
    12 rows, no bias."""
    _assert_equals_columns(cin, cout, seed=cin + cout, bias=bias, batch=1)


@pytest.mark.parametrize("need", [("x",), ("w",), ("b",), ("x", "w"), ()])
def test_only_the_needed_gradients(need):
    """Input only, weight only (the input rows are then the only saved tensor), bias only, none."""
    torch.manual_seed(len(need))
    cam = Equirectangular(width=32, height=16)
    m = ProjectedConv2d(4, 6, 3, padding=1, camera=cam)
    cols = ProjectedConv2d(4, 6, 3, padding=1, camera=cam, chunk_positions=9)
    cols.load_state_dict(m.state_dict())
    x = torch.randn(2, 4, 8, 16)
    for a, b in zip(_outputs(m, x, need), _outputs(cols, x, need)):
        close_to_scale(a, b, str(need))


@pytest.mark.parametrize("block", [6, 12, 30, 10_000])
def test_any_block_length_gives_the_same_result(block):
    """Blocks of one kernel tile, of lengths that do not divide the positions (last block shorter), of all."""
    torch.manual_seed(block)
    cam = Equirectangular(width=48, height=24)
    m = ProjectedConv2d(4, 6, 3, padding=1, camera=cam)
    plan = get_plan(m.geometry_key((12, 24)), torch.device("cpu"), torch.float32)
    x = torch.randn(3, 4, 12, 24, requires_grad=True)
    y = fused_conv2d(x, m.weight, m.bias, plan, block=block)
    y_cols = fixed_offset_conv2d(x, m.weight, m.bias, plan)
    close_to_scale(y, y_cols, f"block={block}")
    g = torch.randn_like(y)
    for a, b in zip(torch.autograd.grad(y, [x, m.weight], g), torch.autograd.grad(y_cols, [x, m.weight], g)):
        close_to_scale(a, b, f"gradients, block={block}")


@pytest.mark.parametrize("hw,batch,block,counts", [((12, 24), 3, 12, (1, 2, 3)), ((12, 24), 3, 6, (1, 2, 3)),
                                                   ((4, 8), 3, 24, (1, 2, 3)), ((4, 8), 1, 24, (1, 2, 3)),
                                                   ((2, 4), 1, 6, (1, 5, 16))])
def test_thread_split_equals_one_thread(hw, batch, block, counts):
    """Several threads (positions split across images and mid-image; private gradient copies added in) equal one
    thread; on a small map (fewer positions than 2 blocks per thread) the forward and the weight gradient split
    the output channels; with more threads than positions some threads have nothing to do."""
    torch.manual_seed(5)
    H, W = hw
    cam = Equirectangular(width=2 * W, height=2 * H)
    m = ProjectedConv2d(4, 40, 3, padding=1, camera=cam)  # 40 channels: 3 kernel panels, the last one partial
    plan = get_plan(m.geometry_key(hw), torch.device("cpu"), torch.float32)
    x = torch.randn(batch, 4, H, W)
    g = torch.randn(batch, 40, H, W)
    runs = []
    threads = torch.get_num_threads()
    try:
        for n in counts:
            torch.set_num_threads(n)
            xi = x.clone().requires_grad_(True)
            y = fused_conv2d(xi, m.weight, m.bias, plan, block=block)
            runs.append((y, *torch.autograd.grad(y, [xi, m.weight, m.bias], g)))
    finally:
        torch.set_num_threads(threads)
    y_cols = fixed_offset_conv2d(x, m.weight, m.bias, plan)
    close_to_scale(runs[0][0], y_cols, "one thread vs columns")
    for run in runs[1:]:
        for a, b, name in zip(run, runs[0], ("output", "input grad", "weight grad", "bias grad")):
            close_to_scale(a, b, name)


def test_block_positions_are_whole_kernel_tiles_near_the_target():
    cam = Equirectangular(width=512, height=256)
    m = ProjectedConv2d(64, 64, 3, padding=1, camera=cam)
    plan = get_plan(m.geometry_key((128, 256)), torch.device("cpu"), torch.float32)
    for c in (1, 64, 256, 100_000):
        n = block_positions(plan, c)
        assert n >= fused_module.MIN_BLOCK and n % fused_module.TILE_ROWS == 0
        assert n == fused_module.MIN_BLOCK or n * 9 * c * 4 <= fused_module.BLOCK_BYTES
    # a cache-resident weight keeps the small block; a weight streamed from memory takes all positions at once,
    # up to the cap on the gathered block
    assert block_positions(plan, 256, 256, 32768) == block_positions(plan, 256)
    assert block_positions(plan, 2048, 512, 32) == 36
    big = block_positions(plan, 2048, 512, 10 ** 6)
    t = fused_module.TILE_ROWS
    assert big % t == 0 and big * 9 * 2048 * 4 <= fused_module.BIG_BLOCK_BYTES < (big + t) * 9 * 2048 * 4


def test_layer_dispatch():
    """CPU float32 runs the fused path; float64 and explicit chunks the column path; fused off -> tiled."""
    cam = Equirectangular(width=16, height=8)
    seen = []
    for dtype, chunk in ((torch.float32, None), (torch.float32, 5), (torch.float64, None)):
        m = ProjectedConv2d(2, 3, 3, padding=1, camera=cam, chunk_positions=chunk).to(dtype)
        seen.append(type(m(torch.randn(1, 2, 4, 8, dtype=dtype, requires_grad=True)).grad_fn).__name__)
    assert seen[0].startswith(_FusedConv.__name__)
    assert seen[1].startswith(_FixedOffsetConv.__name__) and seen[2].startswith(_FixedOffsetConv.__name__)
    plan = get_plan(m.geometry_key((4, 8)), torch.device("cpu"), torch.float32)
    x = torch.randn(1, 2, 4, 8)
    assert fused_supported(x, torch.randn(3, 2, 3, 3), plan)
    assert not fused_supported(x.double(), torch.randn(3, 2, 3, 3).double(), plan)


def test_disabled_fused_path_runs_the_tiled_path(monkeypatch):
    monkeypatch.setattr(fused_module, "ENABLED", False)
    m = ProjectedConv2d(2, 3, 3, padding=1, camera=Equirectangular(width=16, height=8))
    y = m(torch.randn(1, 2, 4, 8, requires_grad=True))
    assert type(y.grad_fn).__name__.startswith(_TiledConv.__name__)


def test_a_nan_pixel_reaches_only_the_outputs_that_sample_it():
    """A NaN pixel reaches only outputs with a tap of non-zero weight on it: a subset of deform_conv2d's NaNs
    (which also multiplies in-image corners of weight 0), never the whole map, also for pixel 0, where the plan
    parks the corners that read zero."""
    cam = Equirectangular(width=32, height=16)
    m = ProjectedConv2d(2, 3, 3, padding=1, camera=cam)
    ref = ProjectedConv2d(2, 3, 3, padding=1, camera=cam, backend="torchvision")
    ref.load_state_dict(m.state_dict())
    for y, x in ((4, 5), (0, 0), (7, 15)):
        img = torch.randn(1, 2, 8, 16)
        img[0, 1, y, x] = float("nan")
        with torch.no_grad():
            bad = torch.isnan(m(img))
            assert not (bad & ~torch.isnan(ref(img))).any() and 0 < int(bad.sum()) < bad.numel() // 4


# -- the build --------------------------------------------------------------------------------------------

def test_status_names_the_kernel_and_the_cached_file():
    st = native.status()
    assert st["available"] and st["kernel"] in ("avx512", "avx2", "blas") and st["reason"] == ""
    assert st["openmp"]  # gcc here has OpenMP: the kernel runs on PyTorch's thread team
    assert st["path"].is_file() and st["path"].name.startswith("fixed_conv-")


def test_a_second_build_reuses_the_cached_library(tmp_path, monkeypatch):
    monkeypatch.setenv("OMNIDL_CACHE_DIR", str(tmp_path))
    native.reset()
    try:
        first = native.status()["path"]
        assert first.parent == tmp_path / "native"
        stamp = first.stat().st_mtime_ns
        native.reset()
        assert native.status()["path"] == first and first.stat().st_mtime_ns == stamp
        assert [p.name for p in first.parent.iterdir()] == [first.name]  # no temporary file left behind
    finally:
        native.reset()


def test_no_compiler_warns_once_and_the_layer_runs_the_tiled_path(monkeypatch, tmp_path):
    monkeypatch.setenv("CC", "no-such-compiler-omnidl")
    monkeypatch.setenv("OMNIDL_CACHE_DIR", str(tmp_path))
    native.reset()
    try:
        with pytest.warns(RuntimeWarning, match=r"native .* unavailable \(no C compiler found \(CC=no-such"):
            assert native.library() is None
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # once per process
            m = ProjectedConv2d(2, 3, 3, padding=1, camera=Equirectangular(width=16, height=8))
            y = m(torch.randn(1, 2, 4, 8, requires_grad=True))
        assert type(y.grad_fn).__name__.startswith(_TiledConv.__name__)
        assert native.status()["reason"].startswith("no C compiler")
    finally:
        native.reset()


def test_a_failing_compile_warns_with_the_compiler_message(monkeypatch, tmp_path):
    script = tmp_path / "badcc"
    script.write_text("#!/bin/sh\necho 'fatal: cannot compile here' >&2\nexit 3\n")
    script.chmod(0o755)
    monkeypatch.setenv("CC", str(script))
    monkeypatch.setenv("OMNIDL_CACHE_DIR", str(tmp_path / "cache"))
    native.reset()
    try:
        sources = ", ".join(path.name for path in native.SOURCES)       # fixed_conv.c, lstm.c, ...
        with pytest.warns(RuntimeWarning,
                          match=re.escape(f"failed on {sources} (exit 3): fatal: cannot compile here")):
            assert native.library() is None
        assert not [p for p in (tmp_path / "cache" / "native").iterdir()]  # the temporary file is removed
    finally:
        native.reset()


def test_disabled_by_environment_without_warning(monkeypatch):
    monkeypatch.setenv("OMNIDL_NATIVE", "0")
    native.reset()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert native.library() is None
        assert native.status() == {"available": False, "kernel": None, "openmp": False, "path": None,
                                   "reason": "disabled by OMNIDL_NATIVE"}
    finally:
        native.reset()


def test_the_source_ships_with_the_package():
    assert all(src.is_file() and os.access(src, os.R_OK) for src in native.SOURCES)


def test_the_blas_build_for_cpus_without_avx2(generic_x86_build):
    """Built for plain x86-64 (no AVX2/FMA) the kernel's products call BLAS sgemm_; same results."""
    assert native.status()["kernel"] == "blas"
    _assert_equals_columns(7, 17, seed=3)


@pytest.mark.parametrize("cin,cout", [(7, 17), (33, 40)])
def test_the_avx2_kernel(avx2_build, cin, cout):
    """Built for AVX2/FMA without AVX-512 (the 6x16 kernel on 16-column panels): same results."""
    assert native.status()["kernel"] == "avx2"
    _assert_equals_columns(cin, cout, seed=5)


def test_packings_of_one_build_are_not_used_by_another(avx2_build, monkeypatch):
    """A weight packed (and kept) for one build's panels is packed again for another build's kernel (AVX2's
    16-column panels, then this CPU's own build: 32 columns with AVX-512)."""
    native_flags = [f if not f.startswith("-march=") else "-march=native" for f in native.FLAGS]
    torch.manual_seed(9)
    cam = Equirectangular(width=40, height=20)
    m = ProjectedConv2d(8, 40, 3, padding=1, camera=cam).eval()
    cols = ProjectedConv2d(8, 40, 3, padding=1, camera=cam, chunk_positions=11).eval()
    cols.load_state_dict(m.state_dict())
    x = torch.randn(1, 8, 10, 20)
    with torch.no_grad():
        ref = cols(x)
        close_to_scale(m(x), ref, "AVX2 build")
        monkeypatch.setattr(native, "FLAGS", native_flags)
        native.reset()
        close_to_scale(m(x), ref, "this CPU's build")


def test_a_compiler_without_openmp_builds_the_single_threaded_kernel(monkeypatch, tmp_path):
    script = tmp_path / "cc-no-openmp"
    script.write_text('#!/bin/sh\nfor a in "$@"; do [ "$a" = -fopenmp ] && { echo "unsupported option" >&2; exit 1; }; '
                      'done\nexec cc "$@"\n')
    script.chmod(0o755)
    monkeypatch.setenv("CC", str(script))
    monkeypatch.setenv("OMNIDL_CACHE_DIR", str(tmp_path / "cache"))
    native.reset()
    try:
        st = native.status()
        assert st["available"] and not st["openmp"]
        _assert_equals_columns(5, 9, seed=4)
    finally:
        native.reset()


def test_an_unexpected_build_error_still_falls_back(monkeypatch, tmp_path):
    """Whatever goes wrong while building or loading (here: the cached library is not a shared object), the
    layer warns and runs the tiled path instead of failing."""
    def broken(cc, torch_lib):
        bad = tmp_path / "fixed_conv-broken.so"
        bad.write_text("not a library")
        return bad
    monkeypatch.setattr(native, "_build", broken)
    native.reset()
    try:
        with pytest.warns(RuntimeWarning, match=r"native .* unavailable \(OSError: "):
            assert native.library() is None
        m = ProjectedConv2d(2, 3, 3, padding=1, camera=Equirectangular(width=16, height=8))
        assert type(m(torch.randn(1, 2, 4, 8, requires_grad=True)).grad_fn).__name__.startswith(_TiledConv.__name__)
    finally:
        native.reset()


# (name, sysfs cache entries as (level, type, size), expected L2 bytes)
L2_CASES = [
    ("a 2 MB unified L2", [("1", "Data", "48K"), ("1", "Instruction", "64K"), ("2", "Unified", "2048K"),
                           ("3", "Unified", "491520K")], 2 * 2 ** 20),
    ("in megabytes", [("2", "Unified", "1M")], 2 ** 20),
    ("no level-2 entry", [("1", "Data", "32K"), ("3", "Unified", "8192K")], None),
    ("an instruction-only L2 is not counted", [("2", "Instruction", "512K")], None),
    ("unreadable size", [("2", "Unified", "")], None),
]


@pytest.mark.parametrize("name,entries,expected", L2_CASES, ids=[c[0] for c in L2_CASES])
def test_l2_cache_size_from_sysfs(name, entries, expected, tmp_path):
    for i, (level, kind, size) in enumerate(entries):
        d = tmp_path / f"index{i}"
        d.mkdir()
        (d / "level").write_text(level + "\n")
        (d / "type").write_text(kind + "\n")
        (d / "size").write_text(size + "\n")
    assert fused_module.l2_cache_bytes(str(tmp_path)) == expected
    assert fused_module.l2_cache_bytes(str(tmp_path / "missing")) is None


@pytest.mark.parametrize("machine,cpuinfo,expected", [
    ("x86_64", "flags\t: fpu sse2 avx2 fma avx512f avx512bw\n", ["-mprefer-vector-width=512"]),
    ("x86_64", "flags\t: fpu sse2 avx2 fma\n", []),
    ("aarch64", "Features\t: fp asimd sve\n", []),
], ids=["AVX-512", "AVX2 only", "ARM"])
def test_wide_vectors_only_on_avx512_x86(machine, cpuinfo, expected, monkeypatch):
    """The 512-bit auto-vectorization flag is passed only where the compiler and CPU have it."""
    real_read = native.Path.read_text
    monkeypatch.setattr(native.platform, "machine", lambda: machine)
    monkeypatch.setattr(native.Path, "read_text",
                        lambda self, *a, **k: cpuinfo if str(self) == "/proc/cpuinfo" else real_read(self, *a, **k))
    assert native._wide_vectors() == expected


@pytest.mark.parametrize("cout", [17, 64])
def test_a_channels_last_weight_is_packed_as_it_lies(cout):
    """A channels-last weight ((Cout, kh, kw, C) memory) gives the contiguous weight's results: inference (kept
    packing), training (forward and transposed packing) and a weight gradient in the weight's own layout."""
    torch.manual_seed(cout)
    cam = Equirectangular(width=48, height=24)
    m = ProjectedConv2d(24, cout, 3, padding=1, camera=cam)
    m_cl = ProjectedConv2d(24, cout, 3, padding=1, camera=cam)
    m_cl.load_state_dict(m.state_dict())
    m_cl = m_cl.to(memory_format=torch.channels_last)
    assert not m_cl.weight.is_contiguous()
    x = torch.randn(2, 24, 12, 24)
    with torch.no_grad():
        close_to_scale(m_cl(x), m(x), "inference")
    outs = [_outputs(mm, x) for mm in (m_cl, m)]
    for name, a, b in zip(("output", "input grad", "weight grad", "bias grad"), *outs):
        close_to_scale(a, b, name)
    assert outs[0][2].stride() == m_cl.weight.stride()
