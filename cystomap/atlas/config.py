"""Settings of the ``atlas`` stage (the ``atlas:`` section of the config)."""

from __future__ import annotations

from dataclasses import dataclass

from cystomap.atlas.projection import PROJECTIONS
from cystomap.settings import setting, validate

EXPOSURE_MODES = ("model", "gain", "none")


@dataclass(frozen=True)
class AtlasConfig:
    """Settings of the ``atlas`` stage."""

    # Atlas projection: equirectangular (column → azimuth, row → elevation) or equal_area
    # (Lambert cylindrical equal-area: row → sin elevation, every pixel the same solid angle).
    projection: str = setting("equirectangular", choices=PROJECTIONS)
    # Atlas size in pixels (also the texture of the 3-D model).
    width: int = setting(2048, ">= 16")
    height: int = setting(1024, ">= 8")
    # A frame sees a wall point only when cos(angle between the wall normal and the view ray)
    # is at least this (defines coverage too; grazing views get little blending weight).
    min_cos_incidence: float = setting(0.02, "[0, 1)")
    # Blending weight = cos(incidence)^a · (d_ref / distance)^b · sharpness^c · centrality
    # · mask-edge ramp; these are a, b, c.
    weight_cos_power: float = setting(2.0, ">= 0")
    weight_distance_power: float = setting(2.0, ">= 0")
    weight_sharpness_power: float = setting(1.0, ">= 0")
    # The weight ramps from 0 at the field-of-view mask edge to full over this many pixels.
    edge_feather_px: float = setting(40.0, ">= 0")
    # Occlusion test: depth map of the mesh per frame at this fraction of the frame size, and
    # the relative depth tolerance.
    occlusion_scale: float = setting(0.125, "(0, 1]")
    occlusion_tolerance: float = setting(0.03, ">= 0")
    # Exposure compensation from the overlaps: "model" (per-frame gain and illumination
    # falloff with distance, incidence and image radius), "gain" (per-frame gain only), "none".
    exposure: str = setting("model", choices=EXPOSURE_MODES)
    # Two-band blending: detail from weights raised to this power (1 = plain weighted mean),
    # low frequencies (Gaussian sigma in atlas pixels) from the plain weighted mean.
    detail_power: float = setting(6.0, ">= 1")
    base_sigma_px: float = setting(4.0, ">= 0")
    # Specular glints: a sample whose darkest colour channel exceeds the frame's median by
    # more than this fraction loses weight (none left at twice the fraction); 0 = off.
    glint_rel: float = setting(0.2, ">= 0")
    # View-dependent brightening (glints, flare): a sample brighter than the robust (median
    # over views) brightness of its coarse cell by more than this fraction loses weight
    # (almost none left at 2.5 times the fraction); 0 = off.
    outlier_rel: float = setting(0.12, ">= 0")
    # Pixels that no frame shows free of glints (best view's glint/outlier weight below this)
    # are inpainted from their surroundings; 0 = off.
    inpaint_below: float = setting(0.3, "[0, 1)")
    # Frames with more than this share of their field of view clipped (the preprocess stage's
    # clipped/ masks: a colour channel at its ceiling) are overexposed and not painted: the
    # little wall they show unclipped is their darkest, too biased a sample to fit their
    # exposure by (the frames stage's max_saturated, per channel); 1 = paint them all.
    max_clipped: float = setting(0.3, "(0, 1]")
    # Coarse cells (block × block atlas pixels) used to find which pixels a frame may see and
    # to estimate the exposure model.
    block: int = setting(8, "[2, 64]")
    # Use at most this many frames (evenly spaced in name order); 0 = all.
    max_views: int = setting(0, ">= 0")
    # Write the textured model (model.obj/.mtl, texture.png, model.glb).
    model: bool = True
    # The model's mesh is cut along meridians every this many degrees for the UVs.
    meridian_step_deg: float = setting(15.0, "[1, 90]")
    # Grey level of the unseen wall in texture.png.
    unseen_grey: int = setting(96, "[0, 255]")
    # coverage.png's colour scale saturates at this many views.
    coverage_max_views: int = setting(20, ">= 1")
    # Frames processed concurrently (threads; numpy/OpenCV/open3d release the GIL).
    threads: int = setting(2, "[1, 64]")
    # Each frame's image pyramid is kept in memory between the two passes, from the finest
    # level its blending samples (a frame whose pixels are finer than the atlas's keeps only
    # the coarser levels), while the kept total fits in this many MB; the rest are read twice.
    frame_cache_mb: int = setting(1024, ">= 0")
    # Atlas frame: "anatomical" = about the session's anatomical frame (cystomap.anatomy: neck
    # at the bottom, dome at the top, patient's right on the left), "model" = the SfM frame's
    # own axes.
    orientation: str = setting("anatomical", choices=("anatomical", "model"))
    # The image's up direction while the scope enters, clockwise from anterior seen from the
    # neck (degrees; 0 = entered upright); the sessions sheet's entry_roll_deg overrides it.
    entry_roll_deg: float = setting(0.0, "[-360, 360]")

    def __post_init__(self) -> None:
        validate(self, "atlas")

    def texture_settings(self) -> AtlasConfig:
        """What texturing reads (:mod:`cystomap.atlas.texture`): these settings themselves."""
        return self
