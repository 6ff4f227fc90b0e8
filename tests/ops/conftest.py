"""Fixtures of the op tests: the native CPU kernels built for other CPUs than this one's, into fresh caches."""
from __future__ import annotations

import os

import pytest

from omnidl.ops import _native


def _cpu_flags() -> set[str]:
    if os.path.exists("/proc/cpuinfo"):
        for line in open("/proc/cpuinfo"):
            if line.startswith("flags"):
                return set(line.split(":", 1)[1].split())
    return set()


def _build_for(monkeypatch, tmp_path, march: str) -> None:
    """The next :func:`omnidl.ops._native.load` builds with ``-march=<march>`` (instead of ``-march=native``)."""
    if os.uname().machine != "x86_64":
        pytest.skip("x86-64 only")
    monkeypatch.setattr(_native, "FLAGS", tuple(f if f != "-march=native" else f"-march={march}"
                                                for f in _native.FLAGS))
    monkeypatch.setenv("OMNIDL_CACHE_DIR", str(tmp_path))
    _native.reset()


@pytest.fixture(params=["native", "x86-64", "haswell"])
def kernel_build(request, monkeypatch, tmp_path):
    """Each build of the native kernels this machine can run: ``-march=native`` (the usual one), plain x86-64 (no
    AVX2/FMA: the BLAS product and scalar loops) and Haswell (AVX2/FMA without AVX-512: the 6x16 kernel, tested on
    AVX-512 machines too). The usual build is found again afterwards."""
    if request.param != "native":
        if request.param == "haswell" and not {"avx2", "fma", "bmi2", "f16c", "movbe"} <= _cpu_flags():
            pytest.skip("the CPU lacks AVX2/FMA (Haswell's instructions)")
        _build_for(monkeypatch, tmp_path, request.param)
    yield request.param
    _native.reset()
