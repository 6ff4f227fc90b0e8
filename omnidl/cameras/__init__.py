"""Camera models of thesis chapter 2 behind one interface (see :mod:`omnidl.cameras.base`)."""
from .base import Camera, Rays, ResizedCamera, pixel_grid
from .registry import build, get_camera_class, list_cameras, register_camera
from .equirectangular import Equirectangular
from .pinhole import Pinhole
from .fisheye import Fisheye
from .kannala_brandt import KannalaBrandt, read_kb_calibration
from .catadioptric import Catadioptric, Unified
from .scaramuzza import Scaramuzza, read_ocamcalib
from .noncentral_panorama import NonCentralPanorama
from .noncentral_catadioptric import NonCentralCatadioptric
from .resolve import CAMERA_CONFIG_DIR, check_image_size, resolve_camera

__all__ = ["Camera", "Rays", "ResizedCamera", "pixel_grid", "build", "get_camera_class", "list_cameras",
           "register_camera", "Equirectangular", "Pinhole", "Fisheye", "KannalaBrandt", "read_kb_calibration",
           "Catadioptric", "Unified", "Scaramuzza", "read_ocamcalib",
           "NonCentralPanorama", "NonCentralCatadioptric", "resolve_camera", "check_image_size", "CAMERA_CONFIG_DIR"]
