"""omnidl's native CPU kernels, built on first use and cached: the fixed-offset convolution (``csrc/fixed_conv.c``),
the batch-1 LSTM recurrence (``csrc/lstm.c``), PReLU's backward (``csrc/prelu.c``), the adjoint of bilinear
up-sampling (``csrc/upsample.c``), the thin 1x1 expansion with batch norm (``csrc/expansion.c``), a panorama's
wrap into channels-last memory and back (``csrc/wrap_layout.c``), the photometric gyroscopes' reads of a
panorama at directions with their Gauss-Newton sums (``csrc/sphere_terms.c``) and the synthetic renderer's box slab
tests, per-pixel surface and shading pass and layout maps (``csrc/box_slabs.c``, ``csrc/surface_shade.c``,
``csrc/layout_maps.c``), a weight's products on few columns (``csrc/narrow_gemm.c``), batch norm in training
(``csrc/batch_norm.c``), im2col / col2im (``csrc/unfold.c``) and the decoders' up-sampling by 2 with a skip map
(``csrc/upsample2x.c``), one shared library.

The kernels are plain C (no torch headers, so it compiles in about a second) and is loaded with :mod:`ctypes`.
Each call runs on OpenMP threads: built with ``-fopenmp``, the library resolves ``libgomp.so.1`` to the copy
PyTorch has already loaded, so its parallel regions use PyTorch's own intra-op thread team (no second pool
competing for the cores with spinning threads). On x86-64 with AVX-512 (or AVX2/FMA) its products run on its own
register-blocked kernel; elsewhere they call the BLAS ``sgemm_`` that PyTorch's CPU library exports (MKL in
the x86 wheels).

Build: the C compiler of ``$CC`` (default ``cc``), ``-O3 -march=native -fno-math-errno -fno-trapping-math
-fopenmp`` (without ``-fopenmp`` where the compiler lacks it: then single-threaded; plus
``-mprefer-vector-width=512`` on AVX-512 CPUs), linked against ``libtorch_cpu``. The shared library is cached
under ``$OMNIDL_CACHE_DIR/native`` (default ``$XDG_CACHE_HOME/omnidl/native``, else ``~/.cache/omnidl/native``),
named by a hash of the source, compiler, flags, torch build and CPU, and written atomically (compiled to a
temporary name, then renamed), so concurrent processes never load a half-written file. ``OMNIDL_NATIVE=0``
disables the kernel.

When the kernel cannot be built (no compiler, no ``sgemm_`` symbol), :func:`library` returns ``None``, warns
once with the compiler's message, and :class:`~omnidl.nn.ProjectedConv2d` keeps its portable tiled path;
:func:`status` says which path runs and why.
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shlex
import shutil
import subprocess
import tempfile
import threading
import warnings
from pathlib import Path

import torch

SOURCE = Path(__file__).with_name("csrc") / "fixed_conv.c"
#: every source compiled into the library
SOURCES = tuple(SOURCE.with_name(name) for name in ("fixed_conv.c", "lstm.c", "prelu.c", "upsample.c",
                                                                 "expansion.c", "wrap_layout.c", "sphere_terms.c",
                                                                 "surface_shade.c", "box_slabs.c",
                                                                 "layout_maps.c", "narrow_gemm.c", "batch_norm.c",
                                                                 "unfold.c", "upsample2x.c"))
#: tried first: the kernel's calls then run on PyTorch's own OpenMP thread team (same libgomp, loaded once)
OPENMP = ["-fopenmp"]

DISABLED = "disabled by OMNIDL_NATIVE"

_LOCK = threading.Lock()
_STATE: dict = {}


def cache_dir() -> Path:
    """Where built kernels are kept (see the module docstring)."""
    root = os.environ.get("OMNIDL_CACHE_DIR")
    if root:
        return Path(root) / "native"
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "omnidl" / "native"


def _compiler() -> list[str] | None:
    cc = shlex.split(os.environ.get("CC", "") or "cc")
    return cc if cc and shutil.which(cc[0]) else None


def _cpu_id() -> str:
    """The CPU's model and feature flags (``-march=native`` code is only valid on such a CPU)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.processor() or platform.machine()
    keep = [ln for ln in text.splitlines() if ln.split(":")[0].strip() in ("model name", "flags", "Features")]
    return "\n".join(dict.fromkeys(keep))


def _wide_vectors() -> list[str]:
    """On x86-64 CPUs with AVX-512, ask the compiler to auto-vectorize with 512-bit vectors (GCC and Clang prefer
    256 bits there): the gather of the taps, bias, ReLU and scatter loops. Measured: the 64-channel
    ``ProjectedConv2d`` forward 1.24-1.33x ``nn.Conv2d`` against 1.42x without (same kernel, 2 threads)."""
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return []
    return ["-mprefer-vector-width=512"] if " avx512f" in _cpu_id() else []


#: ``-fno-math-errno -fno-trapping-math``: no kernel reads errno or floating-point traps, and a square root that may
#: set errno, or a comparison that may trap, is a branch that keeps a loop scalar (the gyroscopes' point loops ran
#: 6x slower); every result is the same
FLAGS = ["-O3", "-march=native", *_wide_vectors(), "-fno-math-errno", "-fno-trapping-math", "-std=c11", "-fPIC",
         "-shared"]


def _build(cc: list[str], torch_lib: str) -> Path:
    """Compile :data:`SOURCES` unless a matching cached build exists (with OpenMP where the compiler has it, else
    without); the path of the shared library."""
    version = subprocess.run([*cc, "--version"], capture_output=True, text=True, timeout=60).stdout
    link = [f"-L{torch_lib}", "-ltorch_cpu", f"-Wl,-rpath,{torch_lib}", "-lm"]
    user = os.getuid() if hasattr(os, "getuid") else os.environ.get("USERNAME", "user")  # no getuid on Windows
    folders = (cache_dir(), Path(tempfile.gettempdir()) / f"omnidl-native-{user}")
    common = [*(src.read_text() for src in SOURCES), " ".join(cc), version, torch.__version__, _cpu_id(),
              platform.machine()]
    variants = []
    for flags in (FLAGS + OPENMP, FLAGS):
        key = hashlib.sha256("\0".join(common + [" ".join(flags + link)]).encode()).hexdigest()[:16]
        variants.append((flags, f"fixed_conv-{key}.so"))
        for folder in folders:
            if (folder / variants[-1][1]).is_file():
                return folder / variants[-1][1]
    error = ""
    for folder in folders:
        try:
            folder.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=".build-", suffix=".so", dir=folder)
            os.close(fd)
        except OSError:
            continue  # not writable: try the next folder
        try:
            for flags, name in variants:
                run = subprocess.run([*cc, *flags, *map(str, SOURCES), "-o", tmp, *link], capture_output=True,
                                     text=True, timeout=300)
                if run.returncode == 0:
                    os.replace(tmp, folder / name)
                    return folder / name
                error = (f"{' '.join(cc)} failed on {', '.join(src.name for src in SOURCES)} (exit {run.returncode}): "
                         f"{(run.stderr or run.stdout).strip()[-800:]}")
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
        raise RuntimeError(error)
    raise RuntimeError(f"no writable folder for the built kernel (tried {folders[0]} and {folders[1]})")


def _load(path: Path) -> ctypes.CDLL:
    lib = ctypes.CDLL(str(path))
    p, i, n = ctypes.c_void_p, ctypes.c_int, ctypes.c_int64
    lib.omnidl_fc_forward.argtypes = [p, n, i, p, p, i, n, i, p, p, i, p, p, n, n, n, i]
    lib.omnidl_fc_forward.restype = i
    lib.omnidl_fc_backward.argtypes = [p, n, i, p, p, i, n, i, p, p, i, p, n, n, p, n, p, n, i]
    lib.omnidl_fc_backward.restype = i
    lib.omnidl_fc_pack.argtypes = [p, i, i, i, i, i, p, i]
    lib.omnidl_fc_pack.restype = i
    lib.omnidl_fc_packed_floats.argtypes = [i, i]
    lib.omnidl_fc_packed_floats.restype = n
    lib.omnidl_fc_gather.argtypes = [p, n, i, p, p, i, n, i, p, i]
    lib.omnidl_fc_gather.restype = i
    lib.omnidl_fc_scatter.argtypes = [p, n, i, p, p, i, n, i, p, i]
    lib.omnidl_fc_scatter.restype = i
    lib.omnidl_dense_forward.argtypes = [p, n, i, n, p, p, i, p, p, n, i, i, n, i]
    lib.omnidl_dense_forward.restype = i
    lib.omnidl_gemm.argtypes = [i, i, i, p, n, n, p, n, n, p, n, i, i]
    lib.omnidl_gemm.restype = i
    lib.omnidl_gemm_narrow.argtypes = [i, i, i, p, n, n, p, n, n, p, n, i, i]
    lib.omnidl_gemm_narrow.restype = i
    lib.omnidl_wino_packed_floats.argtypes = [i, i]
    lib.omnidl_wino_packed_floats.restype = n
    lib.omnidl_wino_pack.argtypes = [p, i, i, p, i]
    lib.omnidl_wino_pack.restype = i
    lib.omnidl_wino_forward.argtypes = [p, i, i, i, i, i, p, i, p, p, i, i, i, i]
    lib.omnidl_wino_forward.restype = i
    lib.omnidl_wino_rows_packed_floats.argtypes = [i, i]
    lib.omnidl_wino_rows_packed_floats.restype = n
    lib.omnidl_wino_rows_pack.argtypes = [p, i, i, p, i]
    lib.omnidl_wino_rows_pack.restype = i
    lib.omnidl_wino_rows_forward.argtypes = [p, i, i, i, i, i, i, p, i, p, p, i, i, i]
    lib.omnidl_wino_rows_forward.restype = i
    lib.omnidl_wino_pack_flip.argtypes = [p, i, i, i, p, i]
    lib.omnidl_wino_pack_flip.restype = i
    lib.omnidl_wino_weight_grad.argtypes = [p, p, i, i, i, i, i, i, p, i, p, i]
    lib.omnidl_wino_weight_grad.restype = i
    lib.omnidl_wino_weight_grad_floats.argtypes = [i, i, i, i, i, i]
    lib.omnidl_wino_weight_grad_floats.restype = n
    lib.omnidl_lstm_layer.argtypes = [n, i, n, p, p, p, p, p, p, p, i]
    lib.omnidl_lstm_layer.restype = i
    lib.omnidl_lstm_padded_width.argtypes = [n]
    lib.omnidl_lstm_padded_width.restype = n
    lib.omnidl_prelu_backward.argtypes = [p, p, p, i, n, n, n, p, p, i]
    lib.omnidl_prelu_backward.restype = i
    lib.omnidl_prelu_backward_cl.argtypes = [p, p, p, i, n, n, n, p, p, i]
    lib.omnidl_prelu_backward_cl.restype = i
    lib.omnidl_affine_prelu_add.argtypes = [p, n, n, n, p, n, n, n, p, n, n, n, n, n, n, p, p, p, i]
    lib.omnidl_affine_prelu_add.restype = i
    lib.omnidl_upsample_adjoint.argtypes = [p, n, n, n, n, n, p, p, p, p, p, p, p, i]
    lib.omnidl_upsample_adjoint.restype = i
    lib.omnidl_upsample_sum.argtypes = [p, n, p, p, p, n, n, n, n, p, p, p, p, p, p, i, n, n, p, i]
    lib.omnidl_upsample_sum.restype = i
    lib.omnidl_expand_forward.argtypes = [p, n, i, n, p, p, i, i, p, i, p, i]
    lib.omnidl_expand_forward.restype = i
    lib.omnidl_expand_sums.argtypes = [p, p, n, i, n, p, p, i, i, p, i, p, i]
    lib.omnidl_expand_sums.restype = i
    lib.omnidl_expand_input_grad.argtypes = [p, p, n, i, n, p, p, i, i, p, i, p, p, p, p, i]
    lib.omnidl_expand_input_grad.restype = i
    d, f = ctypes.c_double, ctypes.c_float
    lib.omnidl_bn_train.argtypes = [p, n, n, n, p, p, d, d, p, p, p, p, p, i, p, i, p, i]
    lib.omnidl_bn_train.restype = i
    lib.omnidl_bn_train_backward.argtypes = [p, p, n, n, n, p, p, p, p, p, p, i, p, i, p, p, i]
    lib.omnidl_bn_train_backward.restype = i
    lib.omnidl_up2_forward.argtypes = [p, n, n, n, p, f, p, i]
    lib.omnidl_up2_forward.restype = i
    lib.omnidl_up2_backward.argtypes = [p, n, n, n, p, f, p, p, p, i]
    lib.omnidl_up2_backward.restype = i
    for name in ("omnidl_im2col", "omnidl_col2im"):
        getattr(lib, name).argtypes = [p, *[n] * 14, p, i]
        getattr(lib, name).restype = i
    lib.omnidl_sphere_read.argtypes = [p, n, i, i, i, p, p, p, n, p, i]
    lib.omnidl_sphere_read.restype = i
    lib.omnidl_pvg_terms.argtypes = [p, n, i, i, p, p, i, p, n, i, f, p, i]
    lib.omnidl_pvg_terms.restype = i
    lib.omnidl_pvg_stage.argtypes = [p, n, i, i, p, p, i, p, n, i, f, i, f, p, i]
    lib.omnidl_pvg_stage.restype = i
    lib.omnidl_mpp_yaw.argtypes = [p, n, i, p, i, p, n, i, i, i, f, p, p]
    lib.omnidl_mpp_yaw.restype = i
    lib.omnidl_surface_shade.argtypes = [n, p, p, p, p, p, p, p, n, n, p, p, p, p, n, p, p, p, p, p, p, p, p, i, p, f,
                                         p, p, p, p, p, i]
    lib.omnidl_surface_shade.restype = i
    lib.omnidl_box_slabs.argtypes = [p, n, p, p, n, p, p, p, p, p, p, i]
    lib.omnidl_box_slabs.restype = i
    lib.omnidl_layout_brackets.argtypes = [p, n, n, p, p, p, p]
    lib.omnidl_layout_brackets.restype = i
    lib.omnidl_layout_edges.argtypes = [p, p, n, n, i, p, i]
    lib.omnidl_layout_edges.restype = i
    for name in ("omnidl_wrap_to_nhwc", "omnidl_wrap_from_nhwc"):
        getattr(lib, name).argtypes = [p, n, n, n, n, n, n, p, i]
        getattr(lib, name).restype = i
    for name in ("omnidl_fc_kernel", "omnidl_fc_openmp"):
        getattr(lib, name).argtypes = []
        getattr(lib, name).restype = i
    return lib


def ptr(t: torch.Tensor | None) -> int | None:
    """``t``'s data pointer for a kernel's optional argument, ``None`` (a NULL pointer) for no tensor."""
    return None if t is None else t.data_ptr()


def library() -> ctypes.CDLL | None:
    """The loaded kernel, built on first call; ``None`` (with one warning per process, unless disabled by
    ``OMNIDL_NATIVE=0``) where it cannot be built."""
    if "lib" in _STATE:
        return _STATE["lib"]
    with _LOCK:
        if "lib" in _STATE:
            return _STATE["lib"]
        lib, path, reason = None, None, ""
        if os.environ.get("OMNIDL_NATIVE", "1").strip().lower() in ("0", "false", "no", "off"):
            reason = DISABLED
        elif (cc := _compiler()) is None:
            reason = f"no C compiler found (CC={os.environ.get('CC', '') or 'cc'})"
        else:
            try:
                path = _build(cc, str(Path(torch.__file__).parent / "lib"))
                lib = _load(path)
            except Exception as e:  # noqa: BLE001 - any failure to build or load means: run the portable path
                reason = f"{type(e).__name__}: {e}" if not isinstance(e, RuntimeError) else str(e)
        if lib is None and reason != DISABLED:
            warnings.warn(f"omnidl: the native CPU kernels are unavailable ({reason}); ProjectedConv2d runs its "
                          "slower portable path on CPU; LSTMs, the products of weight-heavy convolutions, thin 1x1 "
                          "expansions with batch norm, the backwards of PReLU and of up-sampling, the wrap of "
                          "task heads, the photometric gyroscopes' iterations and the renderer's box tests, surface "
                          "pass and layout maps run on PyTorch's own ops",
                          RuntimeWarning, stacklevel=2)
        _STATE.update(lib=lib, path=path, reason=reason)
        return lib


def accepts(*tensors: torch.Tensor, dtype: torch.dtype = torch.float32) -> bool:
    """Whether the native kernels can take these tensors: each a CPU tensor of ``dtype``, and the library built."""
    return all(t.device.type == "cpu" and t.dtype == dtype for t in tensors) and library() is not None


#: what ``omnidl_fc_kernel()`` returns, by name
KERNELS = ("blas", "avx2", "avx512")


def status() -> dict:
    """``{"available", "kernel" ("avx512" | "avx2" | "blas" | None), "openmp", "path", "reason"}`` of the native
    kernel."""
    lib = library()
    kernel = None if lib is None else KERNELS[lib.omnidl_fc_kernel()]
    return {"available": lib is not None, "kernel": kernel, "openmp": lib is not None and bool(lib.omnidl_fc_openmp()),
            "path": _STATE.get("path"), "reason": _STATE["reason"]}


def reset() -> None:
    """Forget the loaded kernel (tests: the next :func:`library` call builds or finds it again)."""
    with _LOCK:
        _STATE.clear()
