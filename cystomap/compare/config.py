"""Settings of the ``compare`` stage (the ``compare:`` section of the config)."""

from __future__ import annotations

from dataclasses import dataclass

from cystomap.settings import setting, validate

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
    min_track_length: int = setting(2, ">= 1")
    max_reprojection_error_px: float = setting(4.0, ">= 0")
    # SIFT keypoint size on the wall (model units): every observation is described at the
    # same physical scale (size in the image = focal length × this / depth), so the two
    # sessions' descriptors compare whatever the camera distance; the SIFT window spans about
    # 6 × this
    keypoint_size_mm: float = setting(1.2, "> 0")
    # at most this many observations per point are described (the closest views)
    max_observations: int = setting(6, ">= 1")
    # at most this many points per session take part, spread evenly over the wall (one per
    # cell of a voxel grid, the longest track); densified SfM clouds hold 20k+ points, which
    # cost time (descriptors, matching, MSAC, spline) but add no accuracy (0 = all)
    max_points: int = setting(6000, ">= 0")

    # --- matching and robust transform ---
    # Lowe's ratio test on the nearest / second nearest descriptor distance; matches must
    # also be mutual nearest neighbours
    ratio: float = setting(0.85, "(0, 1]")
    # "similarity" (rotation, translation, scale) or "rigid" (scale fixed at 1)
    transform: str = setting("similarity", choices=TRANSFORMS)
    # MSAC: a match is an inlier within this distance (model units) after the transform
    inlier_mm: float = setting(3.0, "> 0")
    msac_iterations: int = setting(3000, ">= 10")
    seed: int = 0
    # registration fails (plainly reported, atlases shown side by side) below this many
    # inliers or this share of inliers among the matches
    min_inliers: int = setting(25, ">= 4")
    min_inlier_ratio: float = setting(0.15, "[0, 1)")
    # the non-rigid thin-plate spline re-collects matches within inlier_mm of its prediction
    # this many times (deformed sessions: the rigid MSAC keeps only the least deformed part)
    spline_rounds: int = setting(3, ">= 0")
    # thin-plate spline smoothing: negative = chosen by k-fold cross-validation on the
    # inliers, else this value (scipy RBFInterpolator smoothing)
    spline_smoothing: float = -1.0
    # the spline uses at most this many inliers (farthest-point subsample)
    spline_max_points: int = setting(600, ">= 10")

    # --- dense residual alignment of the textures ---
    # after the spline, DIS optical flow between B's atlas and A's warped texture corrects the
    # remaining misalignment (forward-backward checked, smoothed on the wall by
    # flow_smooth_mm, at most flow_max_mm): smooth corrections only, so new texture is not
    # flowed away
    flow_refine: bool = True
    flow_smooth_mm: float = setting(1.5, "> 0")
    flow_max_mm: float = setting(4.0, ">= 0")

    # --- difference ---
    # the comparison grid is session B's atlas projection with pixels of about this size on
    # the wall at the equator (model units), whatever the atlas size (0 = the atlas's own)
    grid_mm: float = setting(0.35, ">= 0")
    # the colour difference is compared after Gaussian smoothing of this sigma on the wall
    # (model units): registration jitter of fine texture cancels, coloured patches remain
    smooth_mm: float = setting(0.8, ">= 0")
    # resolution tolerance: the significance is the least over comparing B with A, with A
    # blurred (σ = t/2, t) and with B blurred, so a difference of sharpness between the
    # atlases (frames from other distances) is not taken for a change (0 = off)
    blur_tolerance_mm: float = setting(0.6, ">= 0")
    # illumination: A's colours are quantile-matched to B's on the jointly seen wall, then a
    # smooth per-channel gain of this Gaussian scale (model units) removes slow exposure
    # differences (0 = global matching only)
    illumination_mm: float = setting(15.0, ">= 0")
    # only wall painted from at least this many frames in both sessions is compared (texture
    # from a single, often grazing, view is unreliable; needs the atlases' coverage.png)
    min_views: int = setting(2, ">= 0")
    # only wall within this distance (model units) of an inlier match is compared: farther,
    # the spline extrapolates (0 = no limit)
    support_mm: float = setting(30.0, ">= 0")
    # only wall within this distance (model units) of a 3-D point of its own session's SfM
    # model is compared, in both sessions: elsewhere the mesh is interpolated over a hole
    # (the aperture to the urethra, unseen wall) and the texture there is not the wall's
    # (0 = no limit)
    point_support_mm: float = setting(0.0, ">= 0")
    # jointly seen wall closer than this to the edge of either session's coverage is left out
    # (blending seams, extrapolated texture)
    edge_margin_mm: float = setting(2.0, ">= 0")

    # --- changes ---
    # expected number of false regions per pair (regions the detector would report on the pair
    # if nothing had changed). The threshold comes from the pair's own null: candidate
    # clusters of the significance (excursions above its median + 2 MADs on the compared
    # wall) are scored by their peak and by the root of their excess mass on the wall; most
    # are noise, and exponential tails fitted to the strongest of them (the strongest 10 %
    # counted only by their number, the changes taken out, iteratively) give each cluster the
    # expected number of noise clusters at least as strong that would be reported (times
    # the share of them that pass the checks below when measured as they are,
    # photo-consistency aside); clusters at or below this rate are changes. A cluster
    # holding several changes is split at the saddles of the significance where each side
    # is a change above the saddle and the saddle is not
    # (changes.csv: expected_false). 0.1 = one false region in ten pairs
    false_alarm_rate: float = setting(0.1, "(0, 100]")
    # the smallest change reported: regions smaller than a disc of this diameter (model
    # units) are dropped, whatever their significance (a physical size, not a noise threshold)
    min_diameter_mm: float = setting(3.0, ">= 0")
    # a change must change its patch, not the wall around it (applied after the null's
    # decision): the change between the sessions (A illumination-matched) of the region's mean
    # colour relative to its ring's (ring_mm of compared wall around it),
    # ‖(B_region − B_ring) − (A_region − A_ring)‖ in L*a*b* (CIE76 ΔE*ab; changes.csv:
    # local_delta_e, frame_local_delta_e), must be at least this. Smooth photometric residue
    # the illumination matching leaves (exposure, white balance varying over the wall), which
    # the null passes by its size, shifts region and ring alike and cancels; a lesion changes
    # its patch only. 2.3: the just-noticeable difference (was 3.5, what an untrained observer
    # notices, measured on one of the two values only; it dropped flat CIS and scars of ΔE
    # 2.6-3.4; docs/measurements.md, "The local colour check on both the atlases and the
    # frames"). 0 = no check
    min_local_delta_e: float = setting(2.3, ">= 0")
    # where the region's ΔE relative to its ring is measured for min_local_delta_e: true =
    # on the atlases (local_delta_e) and in the frames that saw it (the region's mean colour
    # minus its ring's in each of up to consistency_views frames of a session,
    # exposure-normalised on the ring, the median over the frames; B's against A's at the
    # same site; changes.csv: frame_local_delta_e), the lesser of the two deciding: the
    # atlases' blend of many frames keeps what each frame's exposure and white balance left,
    # the few frames have sampling noise of their own, and residue seldom fools both; false
    # (or fewer than 3 such frames in a session) = on the atlases only. The null's share of
    # noise clusters that pass the checks is measured on the atlases either way
    local_colour_in_frames: bool = setting(True)
    # an optional floor on the region's own mean colour change (CIE76 ΔE*ab of B's mean vs
    # A's, illumination-matched; changes.csv: delta_e) whatever its ring does: it moves with
    # the residue (lesions and residue overlapped at 3.8-4.3 on the phantom pairs), so it is
    # off by default (0 = no check)
    min_delta_e: float = setting(0.0, ">= 0")
    # a piece too weak to be a change on its own within this distance (model units) of
    # another is part of it (fragments of one change); two pieces that are each a change
    # stay apart, whatever their distance
    merge_mm: float = setting(4.0, ">= 0")
    # a change cut by a strip of wall that one session did not film (a gap between two
    # sweeps of the scan) narrower than this (model units; the edge_margin_mm left out on
    # both sides of the strip is added) is one region, and its outline is closed across the
    # strip; the region's observed_share says how much of it both sessions saw (0 = off)
    gap_fill_mm: float = setting(6.0, ">= 0")
    # a change that runs into wall B saw but A did not (or the edge margin) is followed there
    # on B's colours (where they are at least half-way from the surrounding wall's to the
    # region's, up to twice the compared part's diameter further): its size and centroid are B's,
    # not only those of the compared part; observed_share says how much was compared
    extend_into_unseen: bool = True
    # a change must lie on reconstructed wall: the median distance from its pixels to the
    # nearest SfM point of each session at most this (model units; elsewhere the mesh is
    # interpolated over a hole and its texture is not the wall's; 0 = no check)
    max_point_distance_mm: float = setting(12.0, ">= 0")
    # a change is a patch: regions longer than this many times their width on the wall are a
    # vessel or an edge left misaligned (0 = no check)
    max_elongation: float = setting(3.5, ">= 0")
    # a change must be surrounded by compared wall: at least this share of a ring of ring_mm
    # around it must be jointly seen (else it lies on the edge of one session's coverage or
    # of a hole such as the aperture, where the texture is not comparable)
    min_enclosed: float = setting(0.3, "[0, 1]")
    ring_mm: float = setting(2.0, "> 0")
    # where session A shows an opening (lumen: the urethra, an orifice; median luminance
    # below this share of the compared wall's), B's view into it is not comparable: a new
    # change must appear on wall that A showed as wall. Pixels either session shows this dark
    # are also left out of the tone curve that matches A's colours to B's
    min_luminance_a: float = setting(0.35, "[0, 1)")
    # the bladder neck: registered cameras at or beyond the wall (the scope entering, either
    # session) point to it; the mesh caps the opening and the texture there (the urethra
    # seen through the cap) differs between sessions. With neck_chroma off, the wall within
    # this angle (degrees, from B's barycentre) of such a camera's direction is cut out of
    # the changed clusters (a lesion beside the neck is not joined to the cap) and regions
    # still centred within it are dropped (0 = off); with neck_chroma on (the default) the
    # angle is measured on the pair instead
    opening_deg: float = setting(30.0, "[0, 90)")
    # a raised lesion's centroid: the mesh (a smooth fit) runs under a papillary tumour, so a
    # region's centroid cast onto it lies at the lesion's base. Where session B's SfM points
    # about the centroid stand out of the mesh into the cavity by more than this many standard
    # errors of their median (the scatter measured on a ring of points about the region), the
    # centroid is moved onto them and changes.csv's relief_mm says by how much (0 = centroids
    # stay on the mesh; see cystomap.compare.relief). Papillary lesions from 10 mm, centroid
    # error: 36 seen FROC pairs median 4.90 -> 1.68 mm; 5 fresh held-out pairs 4.3-5.7 ->
    # 1.8-2.9 mm (docs/measurements.md, "A raised change's centroid on the points"); nothing found or lost
    relief_z: float = setting(3.0, ">= 0")
    # experimental, off: the wall around the neck is filmed rarely and at grazing angles, on a
    # mesh several mm off; its noise level is measured ring by ring around the neck and its
    # significance scaled to the rest of the wall's (see cystomap.compare.neck; with
    # opening_deg 0 it found small lesions near the neck on some held-out pairs but lost a
    # 24.8 mm CIS and added a false region on others: docs/measurements.md, "The wall around the neck")
    neck_levelling: bool = setting(False)
    # the brightness and colour of the wall around the neck, B against A, are matched ring by
    # ring around it (rings 2 x smooth_mm wide, out to 90 degrees; the wall-area weighted
    # median of each ring's log colour ratio), after the illumination field: that field is
    # too wide for the steep shading of the funnel, and each session paints it from other
    # grazing views (see cystomap.compare.neck). Opt-in: on fresh family-C pairs 124-131
    # (2026-12-05) 19/24 lesions with it and without, 0 false regions either way: no gain
    # shown (docs/measurements.md, "The neck band's cause")
    neck_ratio: bool = setting(False)
    # the wall around the neck, whose brightness the levelling's halo changes from frame to
    # frame (docs/measurements.md, "The neck band's cause"): ring by ring around the neck, the cap cut out
    # is the opening, out to where the colour (the part of the difference no brightness
    # change explains) is as quiet as on the rest of the wall; beyond it, where the
    # brightness part is still noisier than the rest's, only the colour is tested (a
    # lesion's hue or saturation); a region beside the cap is followed into it where it
    # stands out against the cap's own noise (ring by ring), so a lesion at the neck is
    # measured whole. Replaces the fixed cone of opening_deg (see
    # cystomap.compare.neck.chroma_band). Held-out family-C pairs: from 5 mm 111 -> 113 of
    # 121 lesions, from 10 mm 79 -> 80 of 80, false regions unchanged (docs/measurements.md, "The neck
    # band tested on its colour")
    neck_chroma: bool = setting(True)
    # photo-consistency in session B's own frames (see cystomap.compare.consistency): a
    # region whose colours spread across the frames that see it more than this many times
    # as much as its ring's is not on the wall (aperture, mesh far off) and is dropped,
    # unless session A's frames agree at the same site (at most this much spread): then the
    # wall's relief changed there (a raised lesion the mesh does not follow) and the region
    # is kept (0 = no check); at most consistency_views frames are read per region
    max_inconsistency: float = setting(2.5, ">= 0")
    consistency_views: int = setting(12, ">= 3")
    # morphological opening / closing radius (model units)
    morphology_mm: float = setting(0.8, ">= 0")
    # the textured model and atlas show regions with this outline width (atlas pixels)
    outline_px: int = setting(3, ">= 1")
    # write changes.glb (B's model with the regions highlighted)
    model: bool = True
    # threads for descriptors and ray casting
    threads: int = setting(2, "[1, 64]")
    # --- find-back (findback.csv, findback/) ---
    # per change and session, the best frame of at most this many separate visits of the
    # site (runs of consecutive frames that see it) are listed (0 = no find-back)
    findback_frames: int = setting(3, ">= 0")
    # side (pixels) of the square crops of both atlases and of the best frame of each session
    findback_crop_px: int = setting(256, "[32, 2048]")

    def __post_init__(self) -> None:
        validate(self, "compare")
