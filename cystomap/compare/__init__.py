"""Stage ``compare``: what changed between two sessions of the same bladder.

Following the reference study's inter-session comparison:

* :mod:`cystomap.compare.features`: mean SIFT descriptor of every 3-D point of a session's
  SfM model (descriptors at the track's keypoints on the enhanced frames, at a fixed size on
  the wall);
* :mod:`cystomap.compare.registration`: mutual nearest-neighbour matches with a ratio test,
  MSAC similarity (3 mm inliers), regularised 3-D thin-plate spline (smoothing by
  cross-validation);
* :mod:`cystomap.compare.difference`: session A's texture warped into session B's atlas
  frame, dense residual alignment, illumination matching, whitened colour difference;
* :mod:`cystomap.compare.changes`: data-derived threshold, cleaning, regions measured on the
  wall (centroid, area, equivalent diameter);
* :mod:`cystomap.compare.landmarks`: sites marked in session A found back in session B;
* :mod:`cystomap.compare.findback`: each change found back in the videos: the frames of B
  that see it best and of A that saw the same site, crops of both atlases and frames;
* :mod:`cystomap.compare.stage`: :class:`CompareConfig`, :class:`SessionPaths` and
  :func:`compare_sessions` (outputs described there).
"""

from cystomap.compare.config import CompareConfig
from cystomap.compare.landmarks import Landmark, read_landmarks
from cystomap.compare.stage import SessionPaths, compare_sessions

__all__ = ["CompareConfig", "Landmark", "SessionPaths", "compare_sessions", "read_landmarks"]
