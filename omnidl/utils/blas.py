"""Thread control of the BLAS library behind NumPy (optional ``threadpoolctl``)."""
from __future__ import annotations

import contextlib
from typing import ContextManager

_CONTROLLER: list = []          # one lazily built ThreadpoolController, or None when unavailable


def single_thread_blas() -> ContextManager:
    """Context manager that limits NumPy's BLAS to one thread (a no-op without ``threadpoolctl``).

    For code that runs many tiny matrix products (e.g. the layout pipeline): BLAS threads only
    add overhead there and stall badly on a loaded machine. The controller is built once.
    """
    try:
        if not _CONTROLLER:
            from threadpoolctl import ThreadpoolController
            _CONTROLLER.append(ThreadpoolController())
        if _CONTROLLER[0] is None:
            return contextlib.nullcontext()
        return _CONTROLLER[0].limit(limits=1, user_api="blas")
    except Exception:  # noqa: BLE001  (optional dependency)
        if not _CONTROLLER:
            _CONTROLLER.append(None)
        return contextlib.nullcontext()
