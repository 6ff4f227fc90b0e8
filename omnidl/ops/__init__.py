"""omnidl's registered operators (``torch.ops.omnidl.*``): kernels for what PyTorch has no op for.

The ground floor of the package: it imports only ``torch``. Each op is declared once with ``torch.library``
(schema, fake kernel for ``torch.compile``/``torch.export``, autograd, autocast) and has one kernel per device;
a native CPU kernel is plain C built on first use (:mod:`omnidl.ops._native`).

* :func:`fixed_offset_conv2d` - a convolution whose taps sample the input at fixed positions
  (:mod:`omnidl.ops.fixed_offset_conv`), the op of :class:`omnidl.nn.ProjectedConv2d`.
* ``torch.ops.omnidl.surface_shade`` - the synthetic renderer's per-pixel surface and shading pass
  (:mod:`omnidl.ops.surface_shade`), called by the renderer (:func:`omnidl.synth.render.render`).
"""
from . import surface_shade  # noqa: F401  (registers torch.ops.omnidl.surface_shade)
from .fixed_offset_conv import fixed_offset_conv2d, fixed_offset_conv2d_backward

__all__ = ["fixed_offset_conv2d", "fixed_offset_conv2d_backward"]
