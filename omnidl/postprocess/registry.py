"""Post-processing hooks: callables run on model outputs, registered by name and listed in configs
(``postprocess: [layout_atlanta]``).

A hook is ``hook(outputs: dict, batch: dict, **options) -> dict`` returning named results
(e.g. ``{"layout": [...]}``) that evaluation merges into its per-image records.
"""
from __future__ import annotations

from typing import Any, Callable

_HOOKS: dict[str, Callable[..., dict]] = {}


def register_hook(name: str):
    """Decorator: register a post-processing hook under ``name``."""
    def deco(fn):
        if name in _HOOKS and _HOOKS[name] is not fn:
            raise ValueError(f"post-processing hook {name!r} is registered twice")
        _HOOKS[name] = fn
        return fn
    return deco


def list_hooks() -> list[str]:
    import omnidl.postprocess  # noqa: F401
    return sorted(_HOOKS)


def get_hook(name: str) -> Callable[..., dict]:
    import omnidl.postprocess  # noqa: F401
    if name not in _HOOKS:
        raise KeyError(f"unknown post-processing hook {name!r}; registered: {sorted(_HOOKS)}")
    return _HOOKS[name]


def run_hooks(names: list[str], outputs: dict, batch: dict, options: dict[str, Any] | None = None) -> dict:
    """Run hooks in order; ``options[name]`` are keyword arguments for hook ``name``."""
    results: dict = {}
    for n in names:
        results.update(get_hook(n)(outputs, batch, **(options or {}).get(n, {})))
    return results
