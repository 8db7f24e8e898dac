"""gscan: RGB-D object scanning into GMatch templates, and CPU 6DoF pose estimation."""
from gscan.camera import Intrinsics, RGBDFrame
from gscan.errors import GscanError, InputError

__version__ = "0.1.0"
__all__ = ["Intrinsics", "RGBDFrame", "GscanError", "InputError", "__version__"]
