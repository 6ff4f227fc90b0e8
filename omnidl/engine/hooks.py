"""The configured post-processing hooks, run the same way in validation and in evaluation.

``cfg.postprocess`` names hooks of :mod:`omnidl.postprocess.registry` (a list, or one comma-separated
string); ``cfg.postprocess_options.<name>`` are keyword arguments of hook ``<name>``. Each hook returns
named results (e.g. ``{"layout": [...], "layout_ok": 0.8}``). :meth:`ConfiguredHooks.run` adds them to
the model outputs, so metrics read hook products such as ``outputs["layout"]`` exactly as they read
``outputs["depth"]``; a hook result with the name of a model output replaces it (a refining hook).

By the hooks' convention an option called ``export_dir`` makes a hook write files per image. Those
files describe the evaluated images, so validation and the rotated passes of an evaluation run the
hooks with ``exports=False``, which leaves that option out.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from omegaconf import DictConfig, OmegaConf

#: the hook option that asks a hook to write files (see the module docstring)
EXPORT_OPTION = "export_dir"


@dataclass(frozen=True)
class ConfiguredHooks:
    """Hook names in run order and their options (``name -> {option: value}``)."""

    names: tuple[str, ...] = ()
    options: dict[str, dict[str, Any]] = field(default_factory=dict)

    @classmethod
    def from_config(cls, cfg: DictConfig) -> "ConfiguredHooks":
        """Read ``cfg.postprocess`` and ``cfg.postprocess_options`` (both optional)."""
        names = cfg.get("postprocess") or []
        if isinstance(names, str):
            names = [n.strip() for n in names.split(",") if n.strip()]
        options = cfg.get("postprocess_options")
        options = OmegaConf.to_container(options, resolve=True) if options else {}
        return cls(tuple(str(n) for n in names), dict(options))

    def __bool__(self) -> bool:
        return bool(self.names)

    def run(self, outputs: dict[str, Any], batch: dict[str, Any],
            exports: bool = True) -> tuple[dict[str, Any], dict[str, Any]]:
        """Run the hooks on one batch; returns ``(outputs merged with the results, results)``.

        ``outputs``: the model outputs (float, on the batch's device); ``exports=False`` drops every
        hook's ``export_dir`` option. With no hooks configured: ``(outputs, {})``.
        """
        if not self.names:
            return outputs, {}
        from omnidl.postprocess.registry import run_hooks
        options = self.options
        if not exports:
            options = {n: {k: v for k, v in (o or {}).items() if k != EXPORT_OPTION} for n, o in options.items()}
        results = run_hooks(list(self.names), outputs, batch, options)
        return {**outputs, **results}, results
