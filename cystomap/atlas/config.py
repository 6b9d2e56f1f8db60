"""Settings of the ``atlas`` stage (the ``atlas:`` section of the config)."""

from __future__ import annotations

from dataclasses import dataclass

from cystomap.atlas.projection import PROJECTIONS
from cystomap.atlas.texture import TextureSettings

EXPOSURE_MODES = ("model", "gain", "none")


@dataclass(frozen=True)
class AtlasConfig:
    """Settings of the ``atlas`` stage."""

    # Atlas projection: equirectangular (column → azimuth, row → elevation) or equal_area
    # (Lambert cylindrical equal-area: row → sin elevation, every pixel the same solid angle).
    projection: str = "equirectangular"
    # Atlas size in pixels (also the texture of the 3-D model).
    width: int = 2048
    height: int = 1024
    # A frame sees a wall point only when cos(angle between the wall normal and the view ray)
    # is at least this (defines coverage too; grazing views get little blending weight).
    min_cos_incidence: float = 0.02
    # Blending weight = cos(incidence)^a · (d_ref / distance)^b · sharpness^c · centrality
    # · mask-edge ramp; these are a, b, c.
    weight_cos_power: float = 2.0
    weight_distance_power: float = 2.0
    weight_sharpness_power: float = 1.0
    # The weight ramps from 0 at the field-of-view mask edge to full over this many pixels.
    edge_feather_px: float = 40.0
    # Occlusion test: depth map of the mesh per frame at this fraction of the frame size, and
    # the relative depth tolerance.
    occlusion_scale: float = 0.125
    occlusion_tolerance: float = 0.03
    # Exposure compensation from the overlaps: "model" (per-frame gain and illumination
    # falloff with distance, incidence and image radius), "gain" (per-frame gain only), "none".
    exposure: str = "model"
    # Two-band blending: detail from weights raised to this power (1 = plain weighted mean),
    # low frequencies (Gaussian sigma in atlas pixels) from the plain weighted mean.
    detail_power: float = 6.0
    base_sigma_px: float = 4.0
    # Specular glints: a sample whose darkest colour channel exceeds the frame's median by
    # more than this fraction loses weight (none left at twice the fraction); 0 = off.
    glint_rel: float = 0.2
    # View-dependent brightening (glints, flare): a sample brighter than the robust (median
    # over views) brightness of its coarse cell by more than this fraction loses weight
    # (almost none left at 2.5 times the fraction); 0 = off.
    outlier_rel: float = 0.12
    # Pixels that no frame shows free of glints (best view's glint/outlier weight below this)
    # are inpainted from their surroundings; 0 = off.
    inpaint_below: float = 0.3
    # Coarse cells (block × block atlas pixels) used to find which pixels a frame may see and
    # to estimate the exposure model.
    block: int = 8
    # Use at most this many frames (evenly spaced in name order); 0 = all.
    max_views: int = 0
    # Write the textured model (model.obj/.mtl, texture.png, model.glb).
    model: bool = True
    # The model's mesh is cut along meridians every this many degrees for the UVs.
    meridian_step_deg: float = 15.0
    # Grey level of the unseen wall in texture.png.
    unseen_grey: int = 96
    # coverage.png's colour scale saturates at this many views.
    coverage_max_views: int = 20
    # Frames processed concurrently (threads; numpy/OpenCV/open3d release the GIL).
    threads: int = 2
    # Decoded frames are kept in memory between the two passes when they fit in this many MB
    # (else they are read twice).
    frame_cache_mb: int = 1024
    # Atlas frame: "anatomical" = about the session's anatomical frame (cystomap.anatomy: neck
    # at the bottom, dome at the top, patient's right on the left), "model" = the SfM frame's
    # own axes.
    orientation: str = "anatomical"
    # The image's up direction while the scope enters, clockwise from anterior seen from the
    # neck (degrees; 0 = entered upright); the sessions sheet's entry_roll_deg overrides it.
    entry_roll_deg: float = 0.0

    def __post_init__(self) -> None:
        if self.projection not in PROJECTIONS:
            known = ", ".join(PROJECTIONS)
            raise ValueError(f"projection {self.projection!r} is not one of {known}")
        if self.exposure not in EXPOSURE_MODES:
            known = ", ".join(EXPOSURE_MODES)
            raise ValueError(f"exposure {self.exposure!r} is not one of {known}")
        checks = {
            "width >= 16": self.width >= 16,
            "height >= 8": self.height >= 8,
            "0 <= min_cos_incidence < 1": 0 <= self.min_cos_incidence < 1,
            "weight powers >= 0": min(self.weight_cos_power, self.weight_distance_power,
                                      self.weight_sharpness_power) >= 0,
            "edge_feather_px >= 0": self.edge_feather_px >= 0,
            "0 < occlusion_scale <= 1": 0 < self.occlusion_scale <= 1,
            "occlusion_tolerance >= 0": self.occlusion_tolerance >= 0,
            "detail_power >= 1": self.detail_power >= 1,
            "base_sigma_px >= 0": self.base_sigma_px >= 0,
            "glint_rel >= 0": self.glint_rel >= 0,
            "outlier_rel >= 0": self.outlier_rel >= 0,
            "0 <= inpaint_below < 1": 0 <= self.inpaint_below < 1,
            "2 <= block <= 64": 2 <= self.block <= 64,
            "max_views >= 0": self.max_views >= 0,
            "1 <= meridian_step_deg <= 90": 1 <= self.meridian_step_deg <= 90,
            "0 <= unseen_grey <= 255": 0 <= self.unseen_grey <= 255,
            "coverage_max_views >= 1": self.coverage_max_views >= 1,
            "1 <= threads <= 64": 1 <= self.threads <= 64,
            "frame_cache_mb >= 0": self.frame_cache_mb >= 0,
            "orientation in (anatomical, model)": self.orientation in ("anatomical", "model"),
            "-360 <= entry_roll_deg <= 360": -360 <= self.entry_roll_deg <= 360,
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise ValueError(f"invalid atlas settings: need {', '.join(bad)}")

    def texture_settings(self) -> TextureSettings:
        return TextureSettings(
            min_cos_incidence=self.min_cos_incidence,
            weight_cos_power=self.weight_cos_power,
            weight_distance_power=self.weight_distance_power,
            weight_sharpness_power=self.weight_sharpness_power,
            edge_feather_px=self.edge_feather_px,
            occlusion_scale=self.occlusion_scale,
            occlusion_tolerance=self.occlusion_tolerance,
        )
