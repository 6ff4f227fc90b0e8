"""Fixtures of the native-kernel tests: the library built for other CPUs than this one's."""
from __future__ import annotations

import os

import pytest
import torch

from omnidl.nn import native

#: float32 tolerance of the native paths against their references, relative to the reference's largest value
TOL = 1e-5


def close_to_scale(a: torch.Tensor, b: torch.Tensor, name: str, tol: float = TOL) -> None:
    """``a`` equals ``b`` (same shape) within ``tol`` of ``max(1, max |b|)``."""
    assert a.shape == b.shape, name
    assert (a - b).abs().max() <= tol * max(1.0, float(b.detach().abs().max())), name


def native_calls(monkeypatch, *names: str) -> list[str]:
    """The names of the native library's functions ``names`` in the order they are called from now on (each still
    runs)."""
    calls: list[str] = []
    lib = native.library()
    for name in names:
        real = getattr(lib, name)
        monkeypatch.setattr(lib, name, lambda *a, real=real, name=name: calls.append(name) or real(*a))
    return calls


def _build_for(monkeypatch, tmp_path, march: str):
    """Build the native library with ``-march=<march>`` into a fresh cache (instead of ``-march=native``)."""
    if os.uname().machine != "x86_64":
        pytest.skip("x86-64 only")
    monkeypatch.setattr(native, "FLAGS", [f if f != "-march=native" else f"-march={march}" for f in native.FLAGS])
    monkeypatch.setenv("OMNIDL_CACHE_DIR", str(tmp_path))
    native.reset()


@pytest.fixture
def generic_x86_build(monkeypatch, tmp_path):
    """The native library built for plain x86-64 (no AVX2/FMA: the BLAS and scalar paths) into a fresh cache;
    the usual build is found again afterwards."""
    _build_for(monkeypatch, tmp_path, "x86-64")
    yield
    native.reset()


@pytest.fixture
def avx2_build(monkeypatch, tmp_path):
    """The native library built for AVX2/FMA without AVX-512 (``-march=haswell``: the 6x16 kernel), so that
    kernel is tested on AVX-512 machines too; skipped on CPUs without Haswell's instructions."""
    flags = set()
    if os.path.exists("/proc/cpuinfo"):
        for line in open("/proc/cpuinfo"):
            if line.startswith("flags"):
                flags = set(line.split(":", 1)[1].split())
                break
    if not {"avx2", "fma", "bmi2", "f16c", "movbe"} <= flags:
        pytest.skip("the CPU lacks AVX2/FMA (Haswell's instructions)")
    _build_for(monkeypatch, tmp_path, "haswell")
    yield
    native.reset()
