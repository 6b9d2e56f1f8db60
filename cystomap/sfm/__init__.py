"""Structure from motion: camera poses, sparse cloud and metric scale of one session."""

from cystomap.sfm.config import SfmConfig
from cystomap.sfm.pipeline import run_sfm

__all__ = ["SfmConfig", "run_sfm"]
