"""Settings of the structure-from-motion stage (the ``sfm:`` section of the config)."""

from __future__ import annotations

from dataclasses import dataclass

INTRINSICS_MODES = ("auto", "fixed", "refine")
#: COLMAP camera models of self-calibration; all but SIMPLE_PINHOLE estimate lens distortion.
SELF_CALIBRATION_MODELS = ("RADIAL", "SIMPLE_RADIAL", "OPENCV", "SIMPLE_PINHOLE")


@dataclass(frozen=True)
class SfmConfig:
    """How camera poses and the sparse cloud are estimated from the preprocessed frames.

    Pixel thresholds are in pixels of the full-size preprocessed frames, whatever
    ``max_image_size`` the features are detected at.
    """

    # --- features (SIFT on the enhanced grey frames, inside mask.png) ---
    # longest side (px) of the lit field of view (the bounding box of mask.png; the frame
    # without one) at the size the frames are resized to for SIFT; 0 = full size. 640 (half of
    # 1280x720) makes SIFT ~4x and matching >10x faster than full size, at about twice the
    # trajectory error on the fine-textured phantom (0.23 vs 0.10 mm); 800: 0.15 mm
    max_image_size: int = 640
    # at most this many SIFT features per frame (the strongest are kept)
    max_num_features: int = 2048
    # first SIFT octave: -1 doubles the image first (more, finer features, ~3x slower), 0 = no
    first_octave: int = 0
    # number of SIFT octaves
    num_octaves: int = 4
    # SIFT peak (contrast) threshold; lower finds more features on low-texture mucosa
    # (COLMAP's default is 0.0067)
    peak_threshold: float = 0.004
    # SIFT edge threshold (COLMAP's default)
    edge_threshold: float = 10.0
    # affine-covariant SIFT (slower; helps under strong foreshortening)
    estimate_affine_shape: bool = False
    # domain-size pooling of SIFT descriptors (slower; sometimes better on weak texture)
    domain_size_pooling: bool = False
    # features closer than this to the edge of the field-of-view mask are dropped (px)
    mask_erode_px: int = 4

    # --- image pairs ---
    # each frame is matched with this many following frames in video order ...
    sequential_overlap: int = 3
    # ... and with frames further on (gaps doubling, up to this many frames) while the
    # previous gap still had ``extend_min_inliers`` verified matches
    sequential_max_gap: int = 32
    extend_min_inliers: int = 40
    # loop closure: each keyframe is also matched with this many retrieval neighbours (most
    # similar keyframes outside its sequential window), found by VLAD on the session's own
    # SIFT descriptors (no vocabulary tree); 0 = none
    retrieval_neighbors: int = 6
    # number of visual words (k-means clusters) of the VLAD descriptor
    retrieval_words: int = 32
    # SIFT descriptors sampled per frame to train the visual words
    retrieval_train_per_image: int = 200
    # retrieval pairs closer than this many keyframes are left to the sequential pairs, and
    # the neighbours of one keyframe are this far apart from each other (0 = sequential_overlap)
    retrieval_min_gap: int = 0
    # dense video: only every s-th frame (keyframes) is mapped incrementally, s the largest
    # power of two up to this for which this share of keyframes has strong pairs to the next
    # two keyframes; the other frames are registered to that model afterwards
    keyframe_max_stride: int = 16
    keyframe_min_share: float = 0.9

    # --- matching and two-view geometry ---
    # Lowe's ratio test
    max_ratio: float = 0.8
    # largest descriptor distance of a match (COLMAP's default)
    max_distance: float = 0.7
    # re-match each verified pair guided by its epipolar geometry (more, better matches; slower)
    guided_matching: bool = False
    # a pair needs this many geometrically verified matches
    min_num_inliers: int = 15
    # RANSAC inlier threshold of two-view geometry (px, full size)
    ransac_max_error_px: float = 4.0

    # --- mapping ---
    # camera intrinsics in bundle adjustment: fixed, refine, or auto = fixed when
    # camera.json is calibrated, self-calibrated (focal length and distortion, see
    # self_calibration_model) when it is only a FOV guess
    intrinsics: str = "auto"
    # COLMAP camera model of refined intrinsics (self-calibration on the frames as they are):
    # RADIAL = one focal length and radial k1, k2; SIMPLE_RADIAL = k1 only; OPENCV = fx, fy,
    # k1, k2, p1, p2; SIMPLE_PINHOLE = one focal length, no distortion. The principal point
    # stays at the prior's. With distortion the model is made pinhole after mapping and the
    # frames undistorted with the estimate (sfm/undistorted/, used by the later stages)
    self_calibration_model: str = "RADIAL"
    # the initial pair needs this many verified matches and this triangulation angle (deg)
    init_min_num_inliers: int = 50
    init_min_tri_angle: float = 4.0
    # RANSAC threshold (px) and minimum inliers to register a frame by absolute pose. 15
    # (COLMAP: 30): blurred, weakly textured stretches of lossy video give 15-25 2D-3D
    # matches; at 25, 3 of 4 mp4v phantom sessions split into 2-4 models, at 15 all four
    # gave one model of every frame (the final adjustment re-checks every observation)
    abs_pose_max_error_px: float = 12.0
    abs_pose_min_num_inliers: int = 15
    # global bundle adjustment after the model grew by this ratio (COLMAP's default 1.1);
    # larger = fewer global adjustments, faster
    ba_global_ratio: float = 1.3
    # iterations of each local / global bundle adjustment (COLMAP: up to 100 / 50)
    ba_local_max_iterations: int = 25
    ba_global_max_iterations: int = 50
    # observations with a reprojection error above this are dropped (px); mapping and final
    max_reproj_error_px: float = 4.0
    # after mapping: drop observations above this error (px) and re-adjust; 0 = skip
    final_filter_error_px: float = 2.0
    # iterations of the final global bundle adjustment
    final_ba_max_iterations: int = 100
    # smaller models (separate pieces) are reported; only the largest is written
    min_model_frames: int = 5
    # self-check by independent halves: the registered frames are mapped again in two
    # alternating halves, each on its own; a stretch of frames that both put further from the
    # model's poses than the model's step between frames is drift the pair tests cannot see:
    # warn = flag it (quality.json consistency, log, report), fail = fail the stage, off = skip
    # (the check costs about one more incremental mapping)
    halves_check: str = "warn"
    # frames whose median verified inliers with their video neighbours fall below this share
    # of the typical (median within sequential_max_gap) are "weak" (motion blur, defocus):
    # they are not mapped incrementally but registered to the model of the others
    # afterwards, so a blurred stretch cannot split the model; 0 = map every frame together.
    # Off by default: on a full-size phantom with glints, blur up to 16 px and bad frames
    # (seed 3) 0.5 gave one model of every usable frame but 5-7 mm trajectory error, against
    # 0.36-0.40 mm with every frame mapped together
    weak_frame_rel: float = 0.0

    # --- densification at full size (after mapping, before the final adjustment) ---
    # corners detected (cv2.goodFeaturesToTrack) at full size in each registered frame are
    # aligned into the next ``densify_neighbors`` frames where the model predicts them and
    # added as new tracks (see cystomap/sfm/densify.py): long, precise tracks that SIFT at
    # max_image_size misses. On the fine-textured phantom (124 frames): trajectory error
    # 0.30-0.35 -> 0.075-0.10 mm (seeds 0-2) for ~+10-15 s; 200 corners without loop
    # closure were not enough (0.24 mm). 0 = off. With keyframes every s frames, each frame
    # gets 1/s of the corners and is aligned to every s-th frame.
    densify_corners: int = 400
    densify_neighbors: int = 6
    # loop closure: each (key)frame's corners are also aligned into this many later frames
    # beyond that window that share the most (at least densify_loop_min_shared) model points
    densify_loop_neighbors: int = 3
    densify_loop_min_shared: int = 15
    # minimum distance between corners and their quality level (share of the best corner)
    densify_min_distance_px: float = 10.0
    densify_quality: float = 0.01
    # side of the aligned square patches (full-size px, odd) and Gauss-Newton iterations
    densify_patch_px: int = 15
    densify_iterations: int = 10
    # patches with a grey-level standard deviation below this are not aligned
    densify_min_contrast: float = 2.0
    # a corner's depth is the median depth of this many nearest model points in its frame
    densify_depth_neighbors: int = 5
    # an alignment counts when the patches correlate (ZNCC) at least this well and the
    # point moved at most this far from its prediction (px)
    densify_min_zncc: float = 0.8
    densify_max_shift_px: float = 4.0
    # a new track needs this many frames (its own included) and must reproject within this
    # error (px) in all of them after triangulation
    densify_min_views: int = 3
    densify_max_reproj_error_px: float = 2.0

    # --- failure ---
    # the stage fails when fewer frames than this, or than this share of the frames, register
    min_registered_frames: int = 5
    min_registered_fraction: float = 0.3

    # --- metric scale ---
    # statistical outlier removal of points before measuring the extent or volume:
    # neighbours considered, and the distance (in standard deviations) a point may lie out
    outlier_neighbors: int = 16
    outlier_std_ratio: float = 2.0
    # each inlier point is averaged with this many nearest points before measuring (removes
    # the outward bias of depth noise: measured -1..+0.6 % instead of +3..+6 % on phantoms)
    scale_smooth_neighbors: int = 16
    # points must be seen in at least this many frames to count for the scale
    scale_min_track_length: int = 3
    # volume_ml: "hull" = convex hull of the inlier points, "star" = star-shaped estimate
    # (radial distance from the centroid, median per direction bin)
    volume_method: str = "hull"

    # --- outputs ---
    # point colours come from at most this many colour frames (chosen to cover most points;
    # decoding every full-size frame is slow); the rest take their nearest point's colour
    colour_max_frames: int = 48

    # --- run ---
    # threads for feature extraction and matching (their results do not depend on it)
    num_threads: int = 2
    # threads for incremental mapping and bundle adjustment. Multi-threaded Ceres sums in a
    # varying order, and on weak input the tiny differences change which frames register:
    # two identical runs at 2 threads gave 118 and 116 frames, cameras up to 8.7 mm apart
    # (mp4v phantom session, loaded machine); at 1 thread the outputs are byte-identical,
    # for about 2-3 s more on 124 frames (densification is single-threaded anyway)
    mapping_threads: int = 1
    # seed of every random choice (RANSAC, k-means, mapping): equal inputs give equal outputs
    seed: int = 0

    def __post_init__(self) -> None:
        problems = []
        if self.max_image_size < 0 or 0 < self.max_image_size < 64:
            problems.append("max_image_size must be 0 (full size) or >= 64")
        if self.max_num_features < 16:
            problems.append("max_num_features must be >= 16")
        if self.first_octave not in (-1, 0, 1):
            problems.append("first_octave must be -1, 0 or 1")
        if not 1 <= self.num_octaves <= 8:
            problems.append("num_octaves must be in 1..8")
        if self.peak_threshold <= 0 or self.edge_threshold <= 0:
            problems.append("peak_threshold and edge_threshold must be > 0")
        if self.mask_erode_px < 0:
            problems.append("mask_erode_px must be >= 0")
        if self.sequential_overlap < 1:
            problems.append("sequential_overlap must be >= 1")
        if self.sequential_max_gap < self.sequential_overlap:
            problems.append("sequential_max_gap must be >= sequential_overlap")
        if self.keyframe_max_stride < 1 or not 0 < self.keyframe_min_share <= 1:
            problems.append("keyframe_max_stride must be >= 1, keyframe_min_share in (0, 1]")
        if self.extend_min_inliers < 1:
            problems.append("extend_min_inliers must be >= 1")
        if self.retrieval_neighbors < 0 or self.retrieval_min_gap < 0:
            problems.append("retrieval_neighbors and retrieval_min_gap must be >= 0")
        if self.retrieval_words < 2 or self.retrieval_train_per_image < 1:
            problems.append("retrieval_words must be >= 2 and retrieval_train_per_image >= 1")
        if not 0 < self.max_ratio <= 1 or not 0 < self.max_distance <= 1:
            problems.append("max_ratio and max_distance must be in (0, 1]")
        if self.min_num_inliers < 8 or self.init_min_num_inliers < 8:
            problems.append("min_num_inliers and init_min_num_inliers must be >= 8")
        if self.abs_pose_min_num_inliers < 6:
            problems.append("abs_pose_min_num_inliers must be >= 6")
        for name in ("ransac_max_error_px", "abs_pose_max_error_px", "max_reproj_error_px",
                     "init_min_tri_angle"):
            if getattr(self, name) <= 0:
                problems.append(f"{name} must be > 0")
        if self.final_filter_error_px < 0:
            problems.append("final_filter_error_px must be >= 0")
        if self.intrinsics not in INTRINSICS_MODES:
            problems.append(f"intrinsics must be one of {', '.join(INTRINSICS_MODES)}")
        if self.halves_check not in ("warn", "fail", "off"):
            problems.append("halves_check must be one of warn, fail, off")
        if self.self_calibration_model not in SELF_CALIBRATION_MODELS:
            problems.append("self_calibration_model must be one of "
                            f"{', '.join(SELF_CALIBRATION_MODELS)}")
        if self.ba_global_ratio < 1.0:
            problems.append("ba_global_ratio must be >= 1")
        if min(self.ba_local_max_iterations, self.ba_global_max_iterations,
               self.final_ba_max_iterations) < 1:
            problems.append("bundle adjustment iterations must be >= 1")
        if self.densify_loop_neighbors < 0 or self.densify_loop_min_shared < 1:
            problems.append("densify_loop_neighbors must be >= 0, densify_loop_min_shared >= 1")
        if self.densify_corners < 0 or not 0 < self.densify_quality < 1:
            problems.append("densify_corners must be >= 0 and densify_quality in (0, 1)")
        if self.densify_patch_px < 3 or self.densify_patch_px % 2 == 0:
            problems.append("densify_patch_px must be odd and >= 3")
        if self.densify_iterations < 1 or self.densify_min_contrast < 0:
            problems.append("densify_iterations must be >= 1 and densify_min_contrast >= 0")
        if (self.densify_neighbors < 1 or self.densify_depth_neighbors < 1
                or self.densify_min_views < 2):
            problems.append("densify_neighbors and densify_depth_neighbors must be >= 1, "
                            "densify_min_views >= 2")
        if min(self.densify_min_distance_px, self.densify_max_shift_px,
               self.densify_max_reproj_error_px) <= 0 or not -1 <= self.densify_min_zncc <= 1:
            problems.append("densify distances must be > 0 and densify_min_zncc in [-1, 1]")
        if not 0 <= self.weak_frame_rel < 1:
            problems.append("weak_frame_rel must be in [0, 1)")
        if self.min_model_frames < 2 or self.min_registered_frames < 2:
            problems.append("min_model_frames and min_registered_frames must be >= 2")
        if not 0 <= self.min_registered_fraction <= 1:
            problems.append("min_registered_fraction must be in [0, 1]")
        if self.outlier_neighbors < 2 or self.outlier_std_ratio <= 0:
            problems.append("outlier_neighbors must be >= 2 and outlier_std_ratio > 0")
        if self.scale_smooth_neighbors < 0:
            problems.append("scale_smooth_neighbors must be >= 0")
        if self.scale_min_track_length < 2:
            problems.append("scale_min_track_length must be >= 2")
        if self.volume_method not in ("hull", "star"):
            problems.append("volume_method must be hull or star")
        if self.colour_max_frames < 1:
            problems.append("colour_max_frames must be >= 1")
        if self.num_threads < 1 or self.mapping_threads < 1:
            problems.append("num_threads and mapping_threads must be >= 1")
        if problems:
            raise ValueError("; ".join(problems))
