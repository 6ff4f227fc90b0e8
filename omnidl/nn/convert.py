"""Swap the convolutions of any network for :class:`ProjectedConv2d`, keeping the weights."""
from __future__ import annotations

from collections.abc import Mapping

from torch import nn

from omnidl.cameras.base import Camera
from omnidl.cameras.resolve import resolve_camera

from .projected_conv import Backend, ProjectedConv2d


def _convertible(m: nn.Module, min_kernel: int) -> bool:
    return (type(m) is nn.Conv2d and max(m.kernel_size) >= min_kernel and m.padding_mode == "zeros"
            and not (isinstance(m.padding, str) and m.padding == "same" and
                     (any(k % 2 == 0 for k in m.kernel_size) or any(s != 1 for s in m.stride))))


def convert_conv2d(model: nn.Module, camera: Camera | Mapping, min_kernel: int = 3, backend: Backend = "auto",
                   **kwargs) -> nn.Module:
    """Replace every ``nn.Conv2d`` with a kernel side ``>= min_kernel`` by :class:`ProjectedConv2d`.

    Weights, biases, stride, padding, dilation, groups, device and dtype are kept (the new
    layer has the same state-dict keys), so pretrained perspective weights load unchanged.
    Convolutions with a non-zero ``padding_mode`` (e.g. ``"circular"``) are left as they
    are, as are subclasses of ``nn.Conv2d`` and existing ``ProjectedConv2d`` layers.
    ``kwargs`` go to :class:`ProjectedConv2d` (``wrap``, ``kernel``, ``image_padding``, ...).
    The model is modified in place and returned. Every layer reads ``camera`` resized to
    its own input, so the camera is the one of the network's input image.
    """
    camera = resolve_camera(camera, default=None, allow_files=False)
    if camera is None:
        raise TypeError("convert_conv2d needs a camera (an omnidl Camera or a camera config mapping), got None")
    if isinstance(model, nn.Conv2d) and _convertible(model, min_kernel):
        return _replace(model, camera, backend, kwargs)
    for name, child in list(model.named_children()):
        if _convertible(child, min_kernel):
            setattr(model, name, _replace(child, camera, backend, kwargs))
        else:
            convert_conv2d(child, camera, min_kernel, backend, **kwargs)
    return model


def _replace(conv: nn.Conv2d, camera: Camera, backend: Backend, kwargs: dict) -> ProjectedConv2d:
    new = ProjectedConv2d(conv.in_channels, conv.out_channels, conv.kernel_size, stride=conv.stride,
                          padding=conv.padding, dilation=conv.dilation, groups=conv.groups,
                          bias=conv.bias is not None, padding_mode=conv.padding_mode,
                          device=conv.weight.device, dtype=conv.weight.dtype, camera=camera, backend=backend,
                          **kwargs)
    new.weight = conv.weight
    if conv.bias is not None:
        new.bias = conv.bias
    new.train(conv.training)
    return new
