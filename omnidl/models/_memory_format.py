"""Memory-format policy of the convolutional models: channels-last or contiguous (NCHW), per mode.

On CPU (oneDNN) a channels-last forward is as fast or faster than NCHW and the ProjectedConv2d fast backend
writes its outputs in place only in channels-last, but the backward of dense convolutions is 1.1-1.6x slower
in channels-last (3x3 convolutions at batch 1, 2 threads: 64 ch 128x256 81 vs 49 ms forward+backward,
1024 ch 4x8 85 vs 63 ms), and a FreDSNet-ResNet-50 training step at 256x128 took 1.71 s against 1.28 s. The
policy ``"auto"`` therefore runs channels-last in eval mode and NCHW in training. Models with ProjectedConv2d
layers had trained channels-last (FreDSNet-Equi 2.00 s against 2.49 s in NCHW) until the weight-heavy layers took
gathered columns (:mod:`omnidl.nn.plan_columns`) and the fused kernel packed channels-last weights as they lie:
since then NCHW is faster for them too (FreDSNet-Equi step at 256x128, 2 threads, interleaved, load 1.0-1.6:
1019 against 1348 ms and 953 against 1165 ms; HoLiNet-ResNet-50-Equi level, 388 against 387-398 ms).
Switching converts the parameters in place (the same ``Parameter`` objects, so optimisers keep them).
"""
from __future__ import annotations

from typing import Literal, Union

import torch
from torch import Tensor, nn


ChannelsLast = Union[bool, Literal["auto"]]


def check_policy(value: ChannelsLast, model: str) -> ChannelsLast:
    if value not in (True, False, "auto"):
        raise ValueError(f"{model}: channels_last must be true, false or 'auto', got {value!r}")
    return value


class MemoryFormatPolicy:
    """Mixin for an ``nn.Module`` with a ``channels_last`` policy attribute (``True``, ``False`` or ``"auto"``).

    Call :meth:`apply_memory_format` at the end of ``__init__``; use :attr:`uses_channels_last` and
    :meth:`to_model_format` in ``forward``.
    """

    channels_last: ChannelsLast
    _format_now: bool | None = None

    def _wants_channels_last(self) -> bool:
        if self.channels_last != "auto":
            return bool(self.channels_last)
        return not self.training  # type: ignore[attr-defined]

    def apply_memory_format(self) -> None:
        """Convert parameters and buffers to the format the policy wants in the current mode (if it changed)."""
        want = self._wants_channels_last()
        if want != self._format_now:
            if want or self._format_now is not None:
                nn.Module.to(self, memory_format=torch.channels_last if want else torch.contiguous_format)  # type: ignore[arg-type]
            self._format_now = want

    @property
    def uses_channels_last(self) -> bool:
        """Whether the model currently runs in channels-last."""
        return bool(self._format_now)

    def train(self, mode: bool = True):
        nn.Module.train(self, mode)  # type: ignore[arg-type]
        self.apply_memory_format()
        return self

    def to_model_format(self, x: Tensor) -> Tensor:
        """``x`` in the memory format the model runs in now (re-checks the mode: ``training`` may have been set
        without ``train()``)."""
        self.apply_memory_format()
        return x.contiguous(memory_format=torch.channels_last) if self._format_now else x
