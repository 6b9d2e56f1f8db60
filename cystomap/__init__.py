"""cystomap: 3-D model and 2-D atlas of the bladder wall from monocular cystoscopy video."""

from cystomap.errors import CystomapError, InputError

__all__ = ["CystomapError", "InputError"]
__version__ = "0.1.0"
