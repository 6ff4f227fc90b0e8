"""Model registry and every model of omnidl. Each module in this package that defines a model
registers it with ``@register_model``; importing this package imports them all."""
import importlib
import pkgutil

from .registry import create_model, list_models, register_model

for _m in pkgutil.iter_modules(__path__):
    if not _m.name.startswith("_") and _m.name != "registry":
        importlib.import_module(f"{__name__}.{_m.name}")

__all__ = ["create_model", "list_models", "register_model"]
