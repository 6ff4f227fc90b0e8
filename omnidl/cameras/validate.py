"""One validation layer for camera parameters: every family declares its parameter domains, this checks them.

A camera class lists the domains of its fields in ``domains`` (a ``ClassVar`` mapping field name ->
:class:`Domain`); on top of those, every field annotated ``float`` must be a finite real number, every
``tuple[float, ...]`` field a tuple of finite reals, and ``width``/``height`` positive integers (an integral
float such as ``64.0`` or a NumPy integer is stored as ``int``). :class:`~omnidl.cameras.base.Camera` runs
:func:`check_types` before a family's own ``__post_init__`` and :func:`check_domains` after it, so every
family (registered or not) is covered at construction, in ``resized()``, from configs and from calibration
files. Errors are ``ValueError`` naming the family, the field, the value and what was expected.
"""
from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass
from typing import Any

__all__ = ["Domain", "POSITIVE", "NONNEGATIVE", "between", "check_types", "check_domains", "check_size",
           "family_name"]


@dataclass(frozen=True)
class Domain:
    """An interval of the real line; ``lo``/``hi`` may be infinite; ``*_closed`` say whether the end belongs.

    ``label`` replaces the numbers in messages (e.g. ``'in (0, pi/2)'``)."""

    lo: float = -math.inf
    hi: float = math.inf
    lo_closed: bool = False
    hi_closed: bool = False
    label: str = ""

    def contains(self, x: float) -> bool:
        above = x >= self.lo if self.lo_closed else x > self.lo
        below = x <= self.hi if self.hi_closed else x < self.hi
        return above and below

    def describe(self) -> str:
        if self.label:
            return self.label
        if math.isinf(self.hi):
            return f"{'>=' if self.lo_closed else '>'} {self.lo:g}"
        if math.isinf(self.lo):
            return f"{'<=' if self.hi_closed else '<'} {self.hi:g}"
        return f"in {'[' if self.lo_closed else '('}{self.lo:g}, {self.hi:g}{']' if self.hi_closed else ')'}"


POSITIVE = Domain(0.0)
NONNEGATIVE = Domain(0.0, lo_closed=True)


def between(lo: float, hi: float, ends: str = "[]", label: str = "") -> Domain:
    """``Domain`` from ``lo`` to ``hi``; ``ends`` is two characters among ``[]()``, e.g. ``'(]'``."""
    return Domain(lo, hi, ends[0] == "[", ends[1] == "]", label)


def family_name(camera_or_cls: Any) -> str:
    cls = camera_or_cls if isinstance(camera_or_cls, type) else type(camera_or_cls)
    return f"{getattr(cls, 'name', '') or cls.__name__} camera"


def _is_real(value: Any) -> bool:
    if isinstance(value, bool):
        return False
    if isinstance(value, numbers.Real):
        return True
    try:  # 0-dim tensors / arrays
        import torch
        if isinstance(value, torch.Tensor):
            return value.numel() == 1 and not value.is_complex() and value.dtype != torch.bool
    except ImportError:  # pragma: no cover
        pass
    return False


def _show(value: Any) -> str:
    return f"{value!r} ({type(value).__name__})" if not isinstance(value, (int, float)) else repr(value)


def _positive_int(value: Any, who: str, name: str) -> int:
    ok = _is_real(value) and math.isfinite(float(value)) and float(value) == int(float(value)) and float(value) >= 1
    if not ok:
        raise ValueError(f"{who}: {name} must be a positive integer (>= 1 pixel), got {_show(value)}")
    return int(float(value))


def check_size(who: str, width: Any, height: Any) -> tuple[int, int]:
    """``(width, height)`` as ints, or ``ValueError`` naming ``who`` and the bad side."""
    return _positive_int(width, who, "width"), _positive_int(height, who, "height")


def _annotation(f: dataclasses.Field) -> str:
    t = f.type
    return t if isinstance(t, str) else getattr(t, "__name__", str(t))


def check_types(camera: Any) -> None:
    """Image size positive integers (stored as ``int``), ``float`` fields finite reals, tuples of finite reals."""
    who = family_name(camera)
    for f in dataclasses.fields(camera):
        value = getattr(camera, f.name)
        kind = _annotation(f).replace(" ", "")
        if f.name in ("width", "height"):
            n = _positive_int(value, who, f.name)
            if not (type(value) is int):
                object.__setattr__(camera, f.name, n)
        elif kind == "float":
            if not _is_real(value) or not math.isfinite(float(value)):
                raise ValueError(f"{who}: {f.name} must be finite (a real number), got {_show(value)}")
        elif kind.startswith("tuple[float"):
            try:
                items = tuple(value)
            except TypeError:
                raise ValueError(f"{who}: {f.name} must be a sequence of finite numbers, got {_show(value)}") from None
            bad = [v for v in items if not _is_real(v) or not math.isfinite(float(v))]
            if bad:
                raise ValueError(f"{who}: {f.name} must hold finite numbers only, got {_show(bad[0])} in "
                                 f"{f.name}={list(items)}")


def check_domains(camera: Any) -> None:
    """Every field named in the class's ``domains`` lies in its :class:`Domain`."""
    who = family_name(camera)
    for name, domain in getattr(type(camera), "domains", {}).items():
        value = getattr(camera, name)
        if not domain.contains(float(value)):
            raise ValueError(f"{who}: {name} must be {domain.describe()}, got {value!r}")
