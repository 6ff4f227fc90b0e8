"""Fixtures of the native-kernel tests."""
from __future__ import annotations

import os

import pytest

from omnidl.nn import native


@pytest.fixture
def generic_x86_build(monkeypatch, tmp_path):
    """The native library built for plain x86-64 (no AVX2/FMA: the BLAS and scalar paths) into a fresh cache;
    the usual build is found again afterwards."""
    if os.uname().machine != "x86_64":
        pytest.skip("x86-64 only")
    monkeypatch.setattr(native, "FLAGS", [f if f != "-march=native" else "-march=x86-64" for f in native.FLAGS])
    monkeypatch.setenv("OMNIDL_CACHE_DIR", str(tmp_path))
    native.reset()
    yield
    native.reset()
