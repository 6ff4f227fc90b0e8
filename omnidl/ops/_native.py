"""Build and load omnidl's native CPU kernels: plain C sources (no torch headers) compiled on first use, cached.

A kernel library is named by the op it serves (``load("fixed_offset_conv", sources, signatures)``). It is compiled
with the C compiler of ``$CC`` (default ``cc``) and ``-O3 -march=native -fno-math-errno -fno-trapping-math
-fopenmp`` (without ``-fopenmp`` where the compiler lacks it: then single-threaded), linked against
``libtorch_cpu`` (whose BLAS ``sgemm_`` the kernels call on CPUs without AVX2/FMA). Built with ``-fopenmp``, the
library resolves ``libgomp.so.1`` to the copy PyTorch has loaded, so its parallel regions run on PyTorch's own
intra-op thread team.

The shared library is cached under ``$OMNIDL_CACHE_DIR/native`` (default ``$XDG_CACHE_HOME/omnidl/native``, else
``~/.cache/omnidl/native``; a per-user temporary folder if that is not writable), named by a hash of the sources,
compiler, flags, torch build and CPU, and written atomically (compiled to a temporary name, then renamed), so
concurrent processes never load a half-written file. A build is announced on stderr with its duration.
``OMNIDL_NATIVE=0`` disables the native kernels. Where a library cannot be built, :func:`load` returns ``None`` and
warns once; the op then runs its PyTorch implementation (:func:`status` says which and why).

This module is the only place that touches ``ctypes``; the ops in this package pass it tensors' data pointers.
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shlex
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path
from typing import Mapping, Sequence

import torch

CSRC = Path(__file__).with_name("csrc")
DISABLED = "disabled by OMNIDL_NATIVE=0"
#: ``-fno-math-errno -fno-trapping-math``: no kernel reads errno or floating-point traps, and a call that may set
#: errno is a branch that keeps a loop scalar; every result is the same
FLAGS = ("-O3", "-march=native", "-fno-math-errno", "-fno-trapping-math", "-std=c11", "-fPIC", "-shared")
OPENMP = ("-fopenmp",)

# ctypes argument kinds of the signatures given to :func:`load`
POINTER, INT, INT64, DOUBLE = ctypes.c_void_p, ctypes.c_int, ctypes.c_int64, ctypes.c_double

_LOCK = threading.Lock()
_LOADED: dict[str, dict] = {}


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


def _build(name: str, sources: Sequence[Path], cc: list[str]) -> Path:
    """The path of ``name``'s shared library: a cached build of ``sources``, else a new one (announced)."""
    torch_lib = str(Path(torch.__file__).parent / "lib")
    version = subprocess.run([*cc, "--version"], capture_output=True, text=True, timeout=60).stdout
    link = [f"-L{torch_lib}", "-ltorch_cpu", f"-Wl,-rpath,{torch_lib}", "-lm"]
    user = os.getuid() if hasattr(os, "getuid") else os.environ.get("USERNAME", "user")
    folders = (cache_dir(), Path(tempfile.gettempdir()) / f"omnidl-native-{user}")
    headers = sorted(CSRC.glob("*.h"))
    common = [*(src.read_text() for src in (*sources, *headers)), " ".join(cc), version, torch.__version__,
              _cpu_id(), platform.machine()]
    variants = []
    for flags in ((*FLAGS, *OPENMP), FLAGS):
        key = hashlib.sha256("\0".join(common + [" ".join(flags + tuple(link))]).encode()).hexdigest()[:16]
        variants.append((flags, f"{name}-{key}.so"))
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
        print(f"omnidl: building the native CPU kernel {name!r} (first use on this machine, cached in {folder})",
              file=sys.stderr, flush=True)
        start = time.perf_counter()
        try:
            for flags, lib_name in variants:
                run = subprocess.run([*cc, *flags, *map(str, sources), "-o", tmp, *link], capture_output=True,
                                     text=True, timeout=300)
                if run.returncode == 0:
                    os.replace(tmp, folder / lib_name)
                    print(f"omnidl: built {name!r} in {time.perf_counter() - start:.1f} s", file=sys.stderr,
                          flush=True)
                    return folder / lib_name
                error = (f"{' '.join(cc)} failed on {', '.join(src.name for src in sources)} (exit "
                         f"{run.returncode}): {(run.stderr or run.stdout).strip()[-800:]}")
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
        raise RuntimeError(error)
    raise RuntimeError(f"no writable folder for the built kernel (tried {folders[0]} and {folders[1]})")


def load(name: str, sources: Sequence[str], signatures: Mapping[str, tuple]) -> ctypes.CDLL | None:
    """The library ``name`` built from ``sources`` (file names in ``csrc/``), each function of ``signatures``
    (``{function: (restype, [argtypes])}``) declared; ``None`` where it cannot be built (one warning per process,
    none when disabled by ``OMNIDL_NATIVE=0``)."""
    hit = _LOADED.get(name)
    if hit is not None:
        return hit["lib"]
    with _LOCK:
        if name in _LOADED:
            return _LOADED[name]["lib"]
        lib, path, reason = None, None, ""
        if os.environ.get("OMNIDL_NATIVE", "1").strip().lower() in ("0", "false", "no", "off"):
            reason = DISABLED
        elif (cc := _compiler()) is None:
            reason = f"no C compiler found (CC={os.environ.get('CC', '') or 'cc'})"
        else:
            try:
                path = _build(name, [CSRC / s for s in sources], cc)
                lib = ctypes.CDLL(str(path))
                for fn, (restype, argtypes) in signatures.items():
                    getattr(lib, fn).restype = restype
                    getattr(lib, fn).argtypes = list(argtypes)
            except Exception as e:  # noqa: BLE001 - any failure to build or load means: the PyTorch implementation
                lib, reason = None, str(e) if isinstance(e, RuntimeError) else f"{type(e).__name__}: {e}"
        if lib is None and reason != DISABLED:
            warnings.warn(f"omnidl: the native CPU kernel {name!r} is unavailable ({reason}); its op runs its "
                          "PyTorch implementation on CPU (same results, slower)", RuntimeWarning, stacklevel=3)
        _LOADED[name] = {"lib": lib, "path": path, "reason": reason}
        return lib


def status(name: str) -> dict:
    """``{"available", "path", "reason"}`` of a library :func:`load` has been asked for (``{}`` before that)."""
    hit = _LOADED.get(name)
    if hit is None:
        return {}
    return {"available": hit["lib"] is not None, "path": hit["path"], "reason": hit["reason"]}


def reset(name: str | None = None) -> None:
    """Forget a loaded library (all with ``None``): the next :func:`load` finds or builds it again (tests)."""
    with _LOCK:
        if name is None:
            _LOADED.clear()
        else:
            _LOADED.pop(name, None)


def pointer(t: torch.Tensor | None) -> int | None:
    """``t``'s data pointer for a kernel argument, ``None`` (a NULL pointer) for no tensor."""
    return None if t is None else t.data_ptr()
