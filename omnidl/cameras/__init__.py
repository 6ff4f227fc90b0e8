"""Camera models of thesis chapter 2 behind one interface (see :mod:`omnidl.cameras.base`)."""
from .base import Camera, Rays, ResizedCamera, pixel_grid
from .registry import build, get_camera_class, list_cameras, register_camera
from .equirectangular import Equirectangular
from .pinhole import Pinhole

__all__ = ["Camera", "Rays", "ResizedCamera", "pixel_grid", "build", "get_camera_class", "list_cameras",
           "register_camera", "Equirectangular", "Pinhole"]
