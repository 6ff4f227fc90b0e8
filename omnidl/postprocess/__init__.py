"""Post-processing hooks (layout geometry, horizon/gyroscope). Importing the package imports every
sub-package so their hooks register."""
import importlib
import pkgutil

from .registry import get_hook, list_hooks, register_hook, run_hooks

for _m in pkgutil.iter_modules(__path__):
    if not _m.name.startswith("_") and _m.name != "registry":
        importlib.import_module(f"{__name__}.{_m.name}")

__all__ = ["get_hook", "list_hooks", "register_hook", "run_hooks"]
