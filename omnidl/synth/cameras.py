"""Camera specs of the data engine: :func:`omnidl.cameras.resolve_camera` (re-exported here)."""
from omnidl.cameras.resolve import CAMERA_CONFIG_DIR, resolve_camera

__all__ = ["CAMERA_CONFIG_DIR", "resolve_camera"]
