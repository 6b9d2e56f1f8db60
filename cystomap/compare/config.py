"""Settings of the ``compare`` stage (the ``compare:`` section of the config)."""

from __future__ import annotations

from dataclasses import dataclass

TRANSFORMS = ("similarity", "rigid")


@dataclass(frozen=True)
class CompareConfig:
    """How two sessions are co-registered, differenced and their changes measured.

    Lengths are in the units of the SfM models (mm when the sessions were given a metric
    scale). No default is tuned to one phantom: the detection threshold comes from the null
    distribution of the pair itself at a chosen false-alarm rate (see ``false_alarm_rate``).
    """

    # --- descriptors of the 3-D points (SIFT at every observation of a track, averaged) ---
    # SfM points seen in fewer frames than this, or with a larger mean reprojection error
    # (px), take no part in the co-registration
    min_track_length: int = 2
    max_reprojection_error_px: float = 4.0
    # SIFT keypoint size on the wall (model units): every observation is described at the
    # same physical scale (size in the image = focal length × this / depth), so the two
    # sessions' descriptors compare whatever the camera distance; the SIFT window spans about
    # 6 × this
    keypoint_size_mm: float = 1.2
    # at most this many observations per point are described (the closest views)
    max_observations: int = 6
    # at most this many points per session take part, spread evenly over the wall (one per
    # cell of a voxel grid, the longest track); densified SfM clouds hold 20k+ points, which
    # cost time (descriptors, matching, MSAC, spline) but add no accuracy (0 = all)
    max_points: int = 6000

    # --- matching and robust transform ---
    # Lowe's ratio test on the nearest / second nearest descriptor distance; matches must
    # also be mutual nearest neighbours
    ratio: float = 0.85
    # "similarity" (rotation, translation, scale) or "rigid" (scale fixed at 1)
    transform: str = "similarity"
    # MSAC: a match is an inlier within this distance (model units) after the transform
    inlier_mm: float = 3.0
    msac_iterations: int = 3000
    seed: int = 0
    # registration fails (plainly reported, atlases shown side by side) below this many
    # inliers or this share of inliers among the matches
    min_inliers: int = 25
    min_inlier_ratio: float = 0.15
    # the non-rigid thin-plate spline re-collects matches within inlier_mm of its prediction
    # this many times (deformed sessions: the rigid MSAC keeps only the least deformed part)
    spline_rounds: int = 3
    # thin-plate spline smoothing: negative = chosen by k-fold cross-validation on the
    # inliers, else this value (scipy RBFInterpolator smoothing)
    spline_smoothing: float = -1.0
    # the spline uses at most this many inliers (farthest-point subsample)
    spline_max_points: int = 600

    # --- dense residual alignment of the textures ---
    # after the spline, DIS optical flow between B's atlas and A's warped texture corrects the
    # remaining misalignment (forward-backward checked, smoothed on the wall by
    # flow_smooth_mm, at most flow_max_mm): smooth corrections only, so new texture is not
    # flowed away
    flow_refine: bool = True
    flow_smooth_mm: float = 1.5
    flow_max_mm: float = 4.0

    # --- difference ---
    # the comparison grid is session B's atlas projection with pixels of about this size on
    # the wall at the equator (model units), whatever the atlas size (0 = the atlas's own)
    grid_mm: float = 0.35
    # the colour difference is compared after Gaussian smoothing of this sigma on the wall
    # (model units): registration jitter of fine texture cancels, coloured patches remain
    smooth_mm: float = 0.8
    # resolution tolerance: the significance is the least over comparing B with A, with A
    # blurred (σ = t/2, t) and with B blurred, so a difference of sharpness between the
    # atlases (frames from other distances) is not taken for a change (0 = off)
    blur_tolerance_mm: float = 0.6
    # illumination: A's colours are quantile-matched to B's on the jointly seen wall, then a
    # smooth per-channel gain of this Gaussian scale (model units) removes slow exposure
    # differences (0 = global matching only)
    illumination_mm: float = 15.0
    # only wall painted from at least this many frames in both sessions is compared (texture
    # from a single, often grazing, view is unreliable; needs the atlases' coverage.png)
    min_views: int = 2
    # only wall within this distance (model units) of an inlier match is compared: farther,
    # the spline extrapolates (0 = no limit)
    support_mm: float = 30.0
    # only wall within this distance (model units) of a 3-D point of its own session's SfM
    # model is compared, in both sessions: elsewhere the mesh is interpolated over a hole
    # (the aperture to the urethra, unseen wall) and the texture there is not the wall's
    # (0 = no limit)
    point_support_mm: float = 0.0
    # jointly seen wall closer than this to the edge of either session's coverage is left out
    # (blending seams, extrapolated texture)
    edge_margin_mm: float = 2.0

    # --- changes ---
    # expected number of false regions per pair (regions the detector would report on the pair
    # if nothing had changed). The threshold comes from the pair's own null: candidate
    # clusters of the significance (excursions above its median + 2 MADs on the compared
    # wall) are scored by their peak and by the root of their excess mass on the wall; most
    # are noise, and exponential tails fitted to the strongest of them (the strongest 10 %
    # counted only by their number, the changes taken out, iteratively) give each cluster the
    # expected number of noise clusters at least as strong; clusters at or below this rate
    # are changes. A cluster holding several changes is split at the saddles of the
    # significance where each side is a change above the saddle and the saddle is not
    # (changes.csv: expected_false). 0.1 = one false region in ten pairs
    false_alarm_rate: float = 0.1
    # the smallest change reported: regions smaller than a disc of this diameter (model
    # units) are dropped, whatever their significance (a physical size, not a noise threshold)
    min_diameter_mm: float = 3.0
    # a change must be visible (a perceptual floor of the change of interest, applied after
    # the null's decision, not a noise threshold): the mean colour of the region in B differs
    # from A's (both illumination-matched) by at least this CIE76 ΔE*ab. 2.3 is the
    # just-noticeable difference, 3.5-5 one an untrained observer notices. The pair's null
    # alone passes large, smooth photometric residue of low-noise pairs (significant by its
    # size; ΔE 1.3-3.8 on the phantom pairs), while lesions change their patch (ΔE 4.3-13).
    # 0 = no check
    min_delta_e: float = 4.0
    # a piece too weak to be a change on its own within this distance (model units) of
    # another is part of it (fragments of one change); two pieces that are each a change
    # stay apart, whatever their distance
    merge_mm: float = 4.0
    # a change cut by a strip of wall that one session did not film (a gap between two
    # sweeps of the scan) narrower than this (model units; the edge_margin_mm left out on
    # both sides of the strip is added) is one region, and its outline is closed across the
    # strip; the region's observed_share says how much of it both sessions saw (0 = off)
    gap_fill_mm: float = 6.0
    # a change that runs into wall B saw but A did not (or the edge margin) is followed there
    # on B's colours (where they are at least half-way from the surrounding wall's to the
    # region's, up to twice the compared part's diameter further): its size and centroid are B's,
    # not only those of the compared part; observed_share says how much was compared
    extend_into_unseen: bool = True
    # a change must lie on reconstructed wall: the median distance from its pixels to the
    # nearest SfM point of each session at most this (model units; elsewhere the mesh is
    # interpolated over a hole and its texture is not the wall's; 0 = no check)
    max_point_distance_mm: float = 12.0
    # a change is a patch: regions longer than this many times their width on the wall are a
    # vessel or an edge left misaligned (0 = no check)
    max_elongation: float = 3.5
    # a change must be surrounded by compared wall: at least this share of a ring of ring_mm
    # around it must be jointly seen (else it lies on the edge of one session's coverage or
    # of a hole such as the aperture, where the texture is not comparable)
    min_enclosed: float = 0.3
    ring_mm: float = 2.0
    # where session A shows an opening (lumen: the urethra, an orifice; median luminance
    # below this share of the compared wall's), B's view into it is not comparable: a new
    # change must appear on wall that A showed as wall
    min_luminance_a: float = 0.35
    # the bladder neck: registered cameras at or beyond the wall (the scope entering, either
    # session) point to it; the mesh caps the opening and the texture there (the urethra
    # seen through the cap) differs between sessions. Regions centred within this angle
    # (degrees, from B's barycentre) of such a camera's direction are dropped (0 = off)
    opening_deg: float = 30.0
    # photo-consistency in session B's own frames (see cystomap.compare.consistency): a
    # region whose colours spread across the frames that see it more than this many times
    # as much as its ring's is not on the wall (aperture, mesh far off) and is dropped
    # (0 = no check); at most consistency_views frames are read per region
    max_inconsistency: float = 2.5
    consistency_views: int = 12
    # morphological opening / closing radius (model units)
    morphology_mm: float = 0.8
    # the textured model and atlas show regions with this outline width (atlas pixels)
    outline_px: int = 3
    # write changes.glb (B's model with the regions highlighted)
    model: bool = True
    # threads for descriptors and ray casting
    threads: int = 2
    # --- find-back (findback.csv, findback/) ---
    # per change and session, the best frame of at most this many separate visits of the
    # site (runs of consecutive frames that see it) are listed (0 = no find-back)
    findback_frames: int = 3
    # side (pixels) of the square crops of both atlases and of the best frame of each session
    findback_crop_px: int = 256

    def __post_init__(self) -> None:
        if self.transform not in TRANSFORMS:
            raise ValueError(f"transform {self.transform!r} is not one of {', '.join(TRANSFORMS)}")
        checks = {
            "min_track_length >= 1": self.min_track_length >= 1,
            "max_reprojection_error_px >= 0": self.max_reprojection_error_px >= 0,
            "keypoint_size_mm > 0": self.keypoint_size_mm > 0,
            "max_observations >= 1": self.max_observations >= 1,
            "max_points >= 0": self.max_points >= 0,
            "0 < ratio <= 1": 0 < self.ratio <= 1,
            "inlier_mm > 0": self.inlier_mm > 0,
            "msac_iterations >= 10": self.msac_iterations >= 10,
            "min_inliers >= 4": self.min_inliers >= 4,
            "0 <= min_inlier_ratio < 1": 0 <= self.min_inlier_ratio < 1,
            "spline_rounds >= 0": self.spline_rounds >= 0,
            "spline_max_points >= 10": self.spline_max_points >= 10,
            "flow_smooth_mm > 0": self.flow_smooth_mm > 0,
            "flow_max_mm >= 0": self.flow_max_mm >= 0,
            "grid_mm >= 0": self.grid_mm >= 0,
            "smooth_mm >= 0": self.smooth_mm >= 0,
            "blur_tolerance_mm >= 0": self.blur_tolerance_mm >= 0,
            "illumination_mm >= 0": self.illumination_mm >= 0,
            "edge_margin_mm >= 0": self.edge_margin_mm >= 0,
            "min_views >= 0": self.min_views >= 0,
            "support_mm >= 0": self.support_mm >= 0,
            "point_support_mm >= 0": self.point_support_mm >= 0,
            "0 < false_alarm_rate <= 100": 0 < self.false_alarm_rate <= 100,
            "min_diameter_mm >= 0": self.min_diameter_mm >= 0,
            "min_delta_e >= 0": self.min_delta_e >= 0,
            "max_point_distance_mm >= 0": self.max_point_distance_mm >= 0,
            "merge_mm >= 0": self.merge_mm >= 0,
            "gap_fill_mm >= 0": self.gap_fill_mm >= 0,
            "max_elongation >= 0": self.max_elongation >= 0,
            "0 <= min_enclosed <= 1": 0 <= self.min_enclosed <= 1,
            "ring_mm > 0": self.ring_mm > 0,
            "max_inconsistency >= 0": self.max_inconsistency >= 0,
            "0 <= opening_deg < 90": 0 <= self.opening_deg < 90,
            "0 <= min_luminance_a < 1": 0 <= self.min_luminance_a < 1,
            "consistency_views >= 3": self.consistency_views >= 3,
            "morphology_mm >= 0": self.morphology_mm >= 0,
            "outline_px >= 1": self.outline_px >= 1,
            "1 <= threads <= 64": 1 <= self.threads <= 64,
            "findback_frames >= 0": self.findback_frames >= 0,
            "32 <= findback_crop_px <= 2048": 32 <= self.findback_crop_px <= 2048,
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise ValueError(f"invalid compare settings: need {', '.join(bad)}")
