"""The ``horizon`` post-processing hook: HoLiNet outputs -> horizon normal, roll, pitch.

The fit itself (vertical direction + RANSAC great circle on the heat maps) is
:func:`omnidl.geometry.horizon.fit_horizon`; the hook applies the sigmoid and renames the results.
"""
from __future__ import annotations

import torch

from omnidl.geometry.horizon import fit_horizon
from omnidl.postprocess.registry import register_hook


@register_hook("horizon")
def horizon_hook(outputs: dict, batch: dict | None = None, logits: bool = True, **options) -> dict:
    """Post-processing hook: HoLiNet outputs ``{"horizon", "vp"}`` -> horizon normal, roll, pitch.

    ``logits=True`` applies a sigmoid first (HoLiNet returns logits). Options are
    :class:`~omnidl.geometry.horizon.HorizonFitOptions` fields, e.g. ``coherence: reference``. Returns ``{"horizon_normal": (B, 3),
    "roll": (B,), "pitch": (B,), "horizon_valid": (B,) bool}`` (radians, camera frame).
    """
    for key in ("horizon", "vp"):
        if key not in outputs:
            raise KeyError(f"horizon hook: model outputs lack {key!r} (have {sorted(outputs)})")
    hl, vp = outputs["horizon"].detach(), outputs["vp"].detach()
    if logits:
        hl, vp = torch.sigmoid(hl), torch.sigmoid(vp)
    res = fit_horizon(hl, vp, **options)
    return {"horizon_normal": res["up"], "roll": res["roll"], "pitch": res["pitch"], "horizon_valid": res["valid"]}
