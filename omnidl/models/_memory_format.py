"""The ``channels_last`` option of the convolutional models: a memory format chosen once, at construction.

``channels_last=True`` converts the parameters to ``torch.channels_last`` once and every input on entry (outputs are
returned contiguous); ``False`` (default) keeps PyTorch's contiguous NCHW format. The choice never depends on the
mode (train, eval, grad): it changes where numbers lie in memory, not what is computed (results equal up to float
rounding). Which is faster depends on the machine and the mode: measure it (``benchmarks/fredsnet.py``).
"""
from __future__ import annotations

import torch
from torch import Tensor, nn


class MemoryFormat:
    """Mixin for an ``nn.Module`` with a ``channels_last`` option: call :meth:`set_memory_format` at the end of
    ``__init__`` and :meth:`to_model_format` on the input in ``forward``."""

    channels_last: bool = False

    def set_memory_format(self, channels_last: bool, model: str) -> None:
        """Record the option (``True``/``False``; a clear error otherwise) and convert the parameters once."""
        if channels_last not in (True, False):
            raise ValueError(f"{model}: channels_last must be true or false, got {channels_last!r}")
        self.channels_last = bool(channels_last)
        if self.channels_last:
            nn.Module.to(self, memory_format=torch.channels_last)  # type: ignore[arg-type]

    def to_model_format(self, x: Tensor) -> Tensor:
        """``x`` in the model's memory format."""
        return x.contiguous(memory_format=torch.channels_last) if self.channels_last else x
