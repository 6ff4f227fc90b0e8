"""The one spelling of the model option that picks the convolution type, and its deprecated aliases.

Every model with a distortion-aware variant takes ``conv="standard"`` (``nn.Conv2d``) or
``conv="projected"`` (:class:`~omnidl.nn.ProjectedConv2d` from the camera of the input image: EquiConv on a
panorama, the calibrated convolution on a fisheye). Until the next release each model still accepts the
spelling it used before (FreDSNet/HoLiNet ``"std"``/``"equi"``, U-Net ``"calibrated"``) with a
``DeprecationWarning``; the table of those old spellings lives here and nowhere else.
"""
from __future__ import annotations

import warnings

#: the accepted values of ``conv=``
CONV_CHOICES = ("standard", "projected")
#: model name -> {old spelling: new spelling}, accepted with a DeprecationWarning for one release
DEPRECATED_CONV_SPELLINGS: dict[str, dict[str, str]] = {
    "FreDSNet": {"std": "standard", "equi": "projected"},
    "HoLiNet": {"std": "standard", "equi": "projected"},
    "unet": {"calibrated": "projected"},
}


def conv_choice(conv: str, model: str) -> str:
    """``"standard"`` or ``"projected"`` for the ``conv=`` value given to ``model``.

    Old spellings of ``model`` (:data:`DEPRECATED_CONV_SPELLINGS`) map to the new one with a
    ``DeprecationWarning``; anything else raises ``ValueError`` naming the accepted values.
    """
    old = DEPRECATED_CONV_SPELLINGS.get(model, {})
    if conv in old:
        warnings.warn(f"{model}: conv={conv!r} is deprecated and will be removed in the next release; use "
                      f"conv={old[conv]!r}", DeprecationWarning, stacklevel=3)
        return old[conv]
    if conv not in CONV_CHOICES:
        also = f" (deprecated: {sorted(old)})" if old else ""
        raise ValueError(f"{model}: conv must be 'standard' or 'projected'{also}, got {conv!r}")
    return conv
