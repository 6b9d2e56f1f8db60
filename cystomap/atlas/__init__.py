"""Stage ``atlas``: 2-D atlas of the bladder wall, its coverage, and the textured 3-D model.

* :mod:`cystomap.atlas.projection`: atlas pixel ↔ direction ↔ wall point (equirectangular,
  equal-area), the contract written to ``atlas.json``;
* :mod:`cystomap.atlas.texture`: visibility, exposure compensation and blending of the frames;
* :mod:`cystomap.atlas.model`: UVs (seam and poles cut), OBJ/MTL and glTF 2.0 GLB writers;
* :mod:`cystomap.atlas.config`: :class:`AtlasConfig`;
* :mod:`cystomap.atlas.paint`: the two passes over the frames that paint the atlas;
* :mod:`cystomap.atlas.stage`: :func:`build_atlas` (inputs, outputs, coverage).
"""

from cystomap.atlas.config import AtlasConfig
from cystomap.atlas.projection import Projection, SurfaceRays, pixel_to_point, point_to_pixel
from cystomap.atlas.stage import build_atlas

__all__ = [
    "AtlasConfig",
    "Projection",
    "SurfaceRays",
    "build_atlas",
    "pixel_to_point",
    "point_to_pixel",
]
