"""Calibrated fisheye experiments (thesis ch. 7): the §7.4 protocol (Pers -> F165/F195, standard vs
calibrated convolutions, baseline and fine-tuned) on the engine, the rectification baseline (§7.4.3) and
metrics against the distance to the principal point. See ``docs/fisheye.md``.

Run the protocol with ``python -m omnidl.apps.fisheye.protocol --config configs/fisheye/small_cpu.yaml``.
"""
from .rectified import RectifiedModel, rectification_report, rectified_model

__all__ = ["RectifiedModel", "rectification_report", "rectified_model"]
