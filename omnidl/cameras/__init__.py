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
from .double_sphere import DoubleSphere
from .eucm import EUCM
from .fov import FOVCamera
from .woodscape import WoodScape, read_woodscape_json
from .opencv import OpenCVPinhole
from .fisheye624 import Fisheye624
from .resolve import CAMERA_CONFIG_DIR, SIZE_POLICIES, check_image_size, fit_camera_to_image, resolve_camera
from .fitting import FitReport, fit
from .io import load, save

__all__ = ["Camera", "Rays", "ResizedCamera", "pixel_grid", "build", "get_camera_class", "list_cameras",
           "register_camera", "Equirectangular", "Pinhole", "Fisheye", "KannalaBrandt", "read_kb_calibration",
           "Catadioptric", "Unified", "Scaramuzza", "read_ocamcalib", "NonCentralPanorama", "NonCentralCatadioptric",
           "DoubleSphere", "EUCM", "FOVCamera", "WoodScape", "read_woodscape_json", "OpenCVPinhole", "Fisheye624",
           "resolve_camera", "check_image_size", "fit_camera_to_image", "SIZE_POLICIES", "CAMERA_CONFIG_DIR",
           "FitReport", "fit", "load", "save"]
