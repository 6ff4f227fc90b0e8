"""Whether PyTorch is capturing a graph (``torch.jit`` tracing or scripting, ``torch.compile``/``torch.export``).

omnidl's shortcuts (native kernels called through ``ctypes``, autograd functions with their own backward, caches
keyed by tensors, data-dependent branches) cannot be captured; while :func:`capturing` is true every such path
takes its plain torch operations instead, which trace and compile."""
from __future__ import annotations

import torch


def capturing() -> bool:
    """``torch.jit.is_tracing() or torch.jit.is_scripting() or torch.compiler.is_compiling()``."""
    return torch.jit.is_tracing() or torch.jit.is_scripting() or torch.compiler.is_compiling()


__all__ = ["capturing"]
