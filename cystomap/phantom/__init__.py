"""Synthetic bladder phantom: two cystoscopy sessions of one bladder with exact ground truth.

Imitates the paper phantom (170 x 130 x 110 mm anatomical bladder, 40 mm aperture to the
urethra, printed mucosa texture; six lesions of 5-30 mm added before session 2).

World frame (both sessions): millimetres, origin = session-1 barycentre (volume centroid,
aperture capped), x = long axis (patient's right +x), y = anterior, z up towards the dome,
aperture and urethra tube at the bottom along -z. Session 2 is the same bladder, deformed in place when
``cfg.deformation > 0``; the texture is attached to the material so it moves with the wall.

Files written per session (``generate_session``):

* ``video.mp4``  mp4v (FFV1, lossless, with ``PhantomConfig(lossless_video=True)``),
  ``cfg.fps``, camera.width x camera.height, lens distortion applied.
* ``poses.csv``  ``frame,qw,qx,qy,qz,tx,ty,tz``: camera-to-world rotation (unit quaternion,
  qw >= 0) and camera centre (mm); frame = 0-based index in the video; OpenCV camera axes.
* ``camera.json``  ``Camera.save`` of the lens rendered (with distortion): the given camera,
  its k1 replaced by ``cfg.lens_k1`` when set (truth.json ``lens`` compares the two).
* ``surface.ply``  the wall of this session (urethra tube excluded, open at the aperture),
  binary PLY, mm, with vertex normals and albedo vertex colours.
* ``albedo.png``  equirectangular albedo about ``truth.json["barycentre"]``, 2H x H; column j
  → azimuth -180 + (j + .5) * 360 / W, row i → elevation 90 - (i + .5) * 180 / H; direction
  (cos el cos az, cos el sin az, sin el); aperture directions black. Session 2 has lesions.
* ``seen.png``  same grid: 255 where the wall was in the image and unoccluded in >= 1 good
  frame, else 0.
* ``lesions.csv``  ``id,x,y,z,nx,ny,nz,diameter_mm,azimuth_deg,elevation_deg,kind,site,
  height_mm,region,clock,distance_from_neck_mm`` (session 2's frame; az/el about its
  barycentre; kind/site see ``cystomap.phantom.lesions``; height_mm = relief of papillary
  lesions, their centre is on top of it; region, clock and distance in its anatomical frame,
  :mod:`cystomap.anatomy`); header only for session 1.
* ``truth.json``  seed, session, sizes, barycentre, anatomy (origin, neck, anterior: the
  patient's anterior is world +y, the scope enters upright), extent_mm, area_mm2, volume_ml,
  seen_fraction (area-weighted), aperture, deformation, gain, bad frames, per-frame
  distances / exposure / blur, rotation per frame, render seconds, the config; ``lens``
  (rendered vs given camera), ``photometry`` (per-session draws), ``texture`` (mode, family,
  parameters, mosaic tiles).
"""

from cystomap.phantom.config import PhantomConfig
from cystomap.phantom.render import default_camera, pixel_rays
from cystomap.phantom.session import bladder_extent_mm, generate_session

__all__ = ["PhantomConfig", "bladder_extent_mm", "default_camera", "generate_session",
           "pixel_rays"]
