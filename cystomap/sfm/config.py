"""Settings of the structure-from-motion stage (the ``sfm:`` section of the config)."""

from __future__ import annotations

from dataclasses import dataclass

from cystomap.settings import setting, validate

INTRINSICS_MODES = ("auto", "fixed", "refine")
HALVES_CHECK_MODES = ("warn", "fail", "off")
#: COLMAP camera models of self-calibration; all but SIMPLE_PINHOLE estimate lens distortion.
SELF_CALIBRATION_MODELS = ("RADIAL", "SIMPLE_RADIAL", "OPENCV", "SIMPLE_PINHOLE")
#: how the keyframes are mapped: COLMAP's incremental mapper, or its global one (GLOMAP)
MAPPERS = ("incremental", "global")


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
    max_image_size: int = setting(640, ">= 0")
    # at most this many SIFT features per frame (the strongest are kept)
    max_num_features: int = setting(2048, ">= 16")
    # first SIFT octave: -1 doubles the image first (more, finer features, ~3x slower), 0 = no
    first_octave: int = setting(0, choices=(-1, 0, 1))
    # plain frames: when the median frame has fewer keypoints than this share of
    # max_num_features, every frame is detected again on the image doubled (one octave finer
    # than first_octave; the whole session, as frames detected at different octaves match
    # worse), which finds the fine vessel detail that the working size blurs away. The rule
    # follows the mapping's need: about a quarter of a frame's keypoints become verified
    # inliers with its neighbour (0.22-0.34 measured on phantom texture families A and B), so
    # below 1/8 of the 2048 budget (256) a pair gives little more than the
    # init_min_num_inliers (50) a model needs to start. Pale, coarse-textured walls at 640x360
    # (family B) had medians of 200-245 per frame and split into pieces; family A and the
    # default wall 400-500 (unchanged: nothing detected again). Costs 4-12x the stage's CPU
    # when it applies (guided matching included; 105-272 CPU-s against ~23 s on 640x360
    # family-B sessions). 0 = never
    plain_keypoints_share: float = setting(0.125, "[0, 1]")
    # plain sessions (see plain_keypoints_share) are matched with guided_matching: the
    # verified pairs re-matched along their epipolar geometry, which gives them several times
    # the inliers of the ratio test alone (family-B session 302:1 at 640x360: 56 -> 215 per
    # pair on average)
    plain_guided_matching: bool = True
    # number of SIFT octaves
    num_octaves: int = setting(4, "[1, 8]")
    # SIFT peak (contrast) threshold; lower finds more features on low-texture mucosa
    # (COLMAP's default is 0.0067)
    peak_threshold: float = setting(0.004, "> 0")
    # SIFT edge threshold (COLMAP's default)
    edge_threshold: float = setting(10.0, "> 0")
    # affine-covariant SIFT (slower; helps under strong foreshortening)
    estimate_affine_shape: bool = False
    # domain-size pooling of SIFT descriptors (slower; sometimes better on weak texture)
    domain_size_pooling: bool = False
    # features closer than this to the edge of the field-of-view mask are dropped (px)
    mask_erode_px: int = setting(4, ">= 0")

    # --- image pairs ---
    # each frame is matched with this many following frames in video order ...
    sequential_overlap: int = setting(3, ">= 1")
    # ... and with frames further on (gaps doubling, up to this many frames) while the
    # previous gap still had ``extend_min_inliers`` verified matches
    sequential_max_gap: int = setting(32, ">= 1")
    extend_min_inliers: int = setting(40, ">= 1")
    # loop closure: each keyframe is also matched with this many retrieval neighbours (most
    # similar keyframes outside its sequential window), found by VLAD on the session's own
    # SIFT descriptors (no vocabulary tree); 0 = none
    retrieval_neighbors: int = setting(6, ">= 0")
    # number of visual words (k-means clusters) of the VLAD descriptor
    retrieval_words: int = setting(32, ">= 2")
    # SIFT descriptors sampled per frame to train the visual words
    retrieval_train_per_image: int = setting(200, ">= 1")
    # retrieval pairs closer than this many keyframes are left to the sequential pairs, and
    # the neighbours of one keyframe are this far apart from each other (0 = sequential_overlap)
    retrieval_min_gap: int = setting(0, ">= 0")
    # dense video: only every s-th frame (keyframes) is mapped incrementally, s the largest
    # power of two up to this for which this share of keyframes has strong pairs to the next
    # two keyframes; the other frames are registered to that model afterwards
    keyframe_max_stride: int = setting(16, ">= 1")
    keyframe_min_share: float = setting(0.9, "(0, 1]")

    # --- matching and two-view geometry ---
    # Lowe's ratio test
    max_ratio: float = setting(0.8, "(0, 1]")
    # largest descriptor distance of a match (COLMAP's default)
    max_distance: float = setting(0.7, "(0, 1]")
    # re-match each verified pair guided by its epipolar geometry (more, better matches; slower)
    guided_matching: bool = False
    # a pair needs this many geometrically verified matches
    min_num_inliers: int = setting(15, ">= 8")
    # RANSAC inlier threshold of two-view geometry (px, full size)
    ransac_max_error_px: float = setting(4.0, "> 0")

    # --- mapping ---
    # how the keyframes are mapped before the other frames are registered to them:
    # incremental = COLMAP's incremental mapper (frame by frame, local and global bundle
    # adjustments); global = COLMAP's global mapper (GLOMAP: rotation averaging of every
    # verified pair at once, then global positioning and bundle adjustment), which spreads a
    # loop's disagreement over the whole chain instead of leaving it where the loop closes.
    # Opt-in: on held-out phantom seeds 10-12 it folded two of three mosaic (repeated texture)
    # sessions (the self-check failed the stage) and put glints:11 5.3 mm off (flagged), where
    # the incremental mapper kept every mosaic session within 0.06 mm; on the 3-minute 1080p
    # recording it gave 0.106 mm against 0.197 (docs/measurements.md, "Tracks merged up to 15 px")
    mapper: str = setting("incremental", choices=MAPPERS)
    # camera intrinsics in bundle adjustment: fixed, refine, or auto = fixed when
    # camera.json is calibrated, self-calibrated (focal length and distortion, see
    # self_calibration_model) when it is only a FOV guess
    intrinsics: str = setting("auto", choices=INTRINSICS_MODES)
    # COLMAP camera model of refined intrinsics (self-calibration on the frames as they are):
    # RADIAL = one focal length and radial k1, k2; SIMPLE_RADIAL = k1 only; OPENCV = fx, fy,
    # k1, k2, p1, p2; SIMPLE_PINHOLE = one focal length, no distortion. The principal point
    # stays at the prior's. With distortion the model is made pinhole after mapping and the
    # frames undistorted with the estimate (sfm/undistorted/, used by the later stages)
    self_calibration_model: str = setting("RADIAL", choices=SELF_CALIBRATION_MODELS)
    # the initial pair needs this many verified matches and this triangulation angle (deg)
    init_min_num_inliers: int = setting(50, ">= 8")
    init_min_tri_angle: float = setting(4.0, "> 0")
    # RANSAC threshold (px) to register a frame by absolute pose
    abs_pose_max_error_px: float = setting(12.0, "> 0")
    # minimum inliers to register a frame by absolute pose (COLMAP: 30): blurred, weakly textured
    # stretches of lossy video give 15-25 2D-3D matches; at 25, 3 of 4 mp4v phantom sessions split
    # into 2-4 models, at 15 all four gave one model of every frame (the final adjustment
    # re-checks every observation)
    abs_pose_min_num_inliers: int = setting(15, ">= 6")
    # global bundle adjustment after the model grew by this ratio (COLMAP's default 1.1);
    # larger = fewer global adjustments, faster
    ba_global_ratio: float = setting(1.3, ">= 1")
    # iterations of each local / global bundle adjustment (COLMAP: up to 100 / 50)
    ba_local_max_iterations: int = setting(25, ">= 1")
    ba_global_max_iterations: int = setting(50, ">= 1")
    # rounds of retriangulation + global bundle adjustment each time the mapper adjusts globally
    # (COLMAP's ba_global_max_refinements). 1 round saved ~7-13 % of the stage's CPU (30 s
    # recording: 101 -> 88 CPU-s with ba_global_after_registering off) but let drift through on
    # a plain family-B session (FROC dev seed 300, session 2, 640x360: trajectory RMSE 0.62 mm
    # with 5 rounds, 5.56 mm with 1; 131 vs 123 CPU-s)
    ba_global_refinements: int = setting(5, ">= 1")
    # global bundle adjustment after the other frames were registered to the keyframe model (when
    # they grew it by ba_global_ratio): off = leave it to the final adjustment, which adjusts
    # every frame and point again after densification
    ba_global_after_registering: bool = False
    # observations with a reprojection error above this are dropped (px); mapping and final
    max_reproj_error_px: float = setting(4.0, "> 0")
    # largest reprojection error (px) at which the mapper merges two tracks (of one scene
    # point, linked by verified matches) or extends a track to another frame; the bundle
    # adjustment that follows decides, and max_reproj_error_px filters after it. COLMAP's
    # incremental mapper gates at 4 px, so where the model drifted by more than that (a long
    # sweep before the scope returns) the returning frames start new tracks beside the old
    # ones and the loop is never pulled closed; its global mapper merges up to 15 px. At 15 the
    # 3-minute 1080p recording's trajectory RMSE went 0.197 -> 0.113 mm and a development
    # session with a badly placed stretch (clean:8) 0.86 -> 0.12 mm, for 8-27 % more sfm
    # time (docs/measurements.md, "Tracks merged up to 15 px"); 4 = COLMAP's incremental default
    track_merge_error_px: float = setting(15.0, "> 0")
    # after mapping: drop observations above this error (px) and re-adjust; 0 = skip
    final_filter_error_px: float = setting(2.0, ">= 0")
    # iterations of the final global bundle adjustment
    final_ba_max_iterations: int = setting(100, ">= 1")
    # after the final adjustment, a registered frame posed from fewer 3-D points than this
    # share of the median over the model's frames is taken out of the model (quality.json:
    # dropped_frames, "posed from too few points"): such a frame (a plain or blurred stretch
    # of wall, a frame beside a gap) is placed by a few dozen points where the others have
    # hundreds. On the 53 FROC sessions of 2026-12-07 the 13 frames below 0.1 were 4.6 mm off
    # (median; 11 over 1 mm) against 0.05 mm for the rest (docs/measurements.md, "Frames posed
    # from too few points"); 0 = keep every frame
    min_frame_points_rel: float = setting(0.1, "[0, 1)")
    # smaller models (separate pieces) are reported; only the largest is written
    min_model_frames: int = setting(5, ">= 2")
    # self-check by independent halves: the registered frames are mapped again in two
    # alternating halves, each on its own; a stretch of frames that both put further from the
    # model's poses than the model's step between frames is drift the pair tests cannot see:
    # warn = flag it (quality.json consistency, log, report), fail = fail the stage, off = skip
    # (the check costs about one more incremental mapping)
    halves_check: str = setting("warn", choices=HALVES_CHECK_MODES)
    # self-check of loop rotations: each verified loop pair with parallax, on wall the model
    # also puts in both frames, measures the rotation the model has between its two frames;
    # neighbouring pairs that agree on one (more than sign-flipped noise does, p <= 0.01) are
    # rotation drift the epipolar tests cannot see: warn = flag it (quality.json consistency,
    # log, report), fail = fail the stage, off = skip (cystomap/sfm/rotation.py; about a second)
    rotation_check: str = setting("warn", choices=HALVES_CHECK_MODES)
    # frames whose median verified inliers with their video neighbours fall below this share
    # of the typical (median within sequential_max_gap) are "weak" (motion blur, defocus):
    # they are not mapped incrementally but registered to the model of the others
    # afterwards, so a blurred stretch cannot split the model; 0 = map every frame together.
    # Off by default: on a full-size phantom with glints, blur up to 16 px and bad frames
    # (seed 3) 0.5 gave one model of every usable frame but 5-7 mm trajectory error, against
    # 0.36-0.40 mm with every frame mapped together
    weak_frame_rel: float = setting(0.0, "[0, 1)")

    # --- densification at full size (after mapping, before the final adjustment) ---
    # corners detected (cv2.goodFeaturesToTrack) at full size in each registered frame are
    # aligned into the next ``densify_neighbors`` frames where the model predicts them and
    # added as new tracks (see cystomap/sfm/densify.py): long, precise tracks that SIFT at
    # max_image_size misses. On the fine-textured phantom (124 frames): trajectory error
    # 0.30-0.35 -> 0.075-0.10 mm (seeds 0-2) for ~+10-15 s; 200 corners without loop
    # closure were not enough (0.24 mm). 0 = off. With keyframes every s frames, each frame
    # gets 1/s of the corners and is aligned to every s-th frame.
    densify_corners: int = setting(400, ">= 0")
    # following frames each corner is aligned into
    densify_neighbors: int = setting(6, ">= 1")
    # loop closure: each (key)frame's corners are also aligned into this many later frames
    # beyond that window that share the most (at least densify_loop_min_shared) model points
    densify_loop_neighbors: int = setting(3, ">= 0")
    densify_loop_min_shared: int = setting(15, ">= 1")
    # minimum distance between the corners of a frame (px)
    densify_min_distance_px: float = setting(10.0, "> 0")
    # corner quality level (share of the frame's best corner)
    densify_quality: float = setting(0.01, "(0, 1)")
    # side of the aligned square patches (full-size px, odd)
    densify_patch_px: int = setting(15, ">= 3")
    # Gauss-Newton iterations of each alignment
    densify_iterations: int = setting(10, ">= 1")
    # patches with a grey-level standard deviation below this are not aligned
    densify_min_contrast: float = setting(2.0, ">= 0")
    # a corner's depth is the median depth of this many nearest model points in its frame
    densify_depth_neighbors: int = setting(5, ">= 1")
    # an alignment counts when the patches correlate (ZNCC) at least as well as all but
    # densify_null_rate of wrong alignments do, in this video: the corners of
    # densify_null_frames sampled frames aligned from starts one to two patch sides away from
    # their predicted places (cystomap/sfm/densify.py, zncc_threshold), and the point moved at
    # most densify_max_shift_px. Plain, low-contrast walls correlate less even where right: on
    # seven family-A/B FROC sessions the former fixed 0.8 gave trajectory RMSE 0.08-0.24 mm
    # (median 0.20), the null's thresholds (0.57-0.61) 0.09-0.22 (median 0.13)
    # (docs/measurements.md, "Densification's ZNCC from the video's own wrong alignments").
    # 0 = densify_max_zncc alone.
    densify_null_rate: float = setting(0.05, "[0, 1)")
    densify_null_frames: int = setting(24, ">= 1")
    # floor under that threshold
    densify_min_zncc: float = setting(0.5, "[-1, 1]")
    # ceiling over it (the former fixed threshold; the threshold itself when densify_null_rate
    # is 0): in motion blur wrong alignments correlate well too, the null's quantile rose to
    # 0.90-0.93 on glints:10 and :12 (1280x720) and cost them 0.01-0.03 mm; the triangulation
    # check (densify_max_reproj_error_px in densify_min_views frames) backs the ZNCC up
    densify_max_zncc: float = setting(0.8, "[-1, 1]")
    # largest shift (px) of an aligned corner from its predicted place (see densify_null_rate)
    densify_max_shift_px: float = setting(4.0, "> 0")
    # a new track needs this many frames (its own included) and must reproject within
    # densify_max_reproj_error_px in all of them after triangulation
    densify_min_views: int = setting(3, ">= 2")
    # largest reprojection error (px) of a new track in any of its frames after triangulation
    densify_max_reproj_error_px: float = setting(2.0, "> 0")
    # SIFT points whose frames all lie within one densification window are dropped before the
    # final adjustment where the corner tracks cover those frames (cystomap/sfm/densify.py,
    # drop_short_sift); loop and long SIFT tracks stay. With the ZNCC from the null, on 12
    # FROC sessions not used to choose either (5 family B, 3 A, 4 held-out C): within 0.15 mm
    # 6 -> 10 of 12, median 0.17 -> 0.07 mm (docs/measurements.md, "Densification's ZNCC from
    # the video's own wrong alignments")
    densify_drop_short_sift: bool = True

    # --- failure ---
    # the stage fails when fewer frames than this, or than this share of the frames, register
    min_registered_frames: int = setting(5, ">= 2")
    min_registered_fraction: float = setting(0.3, "[0, 1]")
    # a model holding fewer than this share of the frames, one a self-check flags, or a failed
    # mapping is mapped again with features at twice max_image_size (at most the lit field's
    # size) when they were detected below it; at full size already, a short model or a failed
    # mapping is mapped again on the image doubled (first_octave one finer, guided matching)
    # unless plain_keypoints_share detected it so. The better model is kept: the one that maps; of
    # two, the larger when the other holds less than this share of its frames, else the one
    # the self-checks pass, then the larger. A model handed on that still holds fewer than
    # this share is named in the log and quality.json (short_model), and compare and the
    # report name its session beside the comparison. 0 = never
    retry_registered_share: float = setting(0.95, "[0, 1]")
    # a flag of the rotation self-check alone (rotation_check) calls for the second mapping
    # too. Off: where measured on the phantom (glints:4, glints:8, uncal:8, deformed:8) that
    # flag was false and the second mapping (160-250 CPU-s; 270 on a 60 s 1080p recording)
    # gave the same or a worse model; the flag stays a warning in quality.json, the log and
    # the report (docs/measurements.md, "Rotation flags no longer map again")
    retry_on_rotation_flag: bool = setting(False)

    # --- metric scale ---
    # statistical outlier removal of points before measuring the extent or volume:
    # neighbours considered, and the distance (in standard deviations) a point may lie out
    outlier_neighbors: int = setting(16, ">= 2")
    outlier_std_ratio: float = setting(2.0, "> 0")
    # each inlier point is averaged with this many nearest points before measuring (removes
    # the outward bias of depth noise: measured -1..+0.6 % instead of +3..+6 % on phantoms)
    scale_smooth_neighbors: int = setting(16, ">= 0")
    # points must be seen in at least this many frames to count for the scale
    scale_min_track_length: int = setting(3, ">= 2")
    # volume_ml: "hull" = convex hull of the inlier points, "star" = star-shaped estimate
    # (radial distance from the centroid, median per direction bin)
    volume_method: str = setting("hull", choices=("hull", "star"))

    # --- outputs ---
    # point colours come from at most this many colour frames (chosen to cover most points;
    # decoding every full-size frame is slow); the rest take their nearest point's colour
    colour_max_frames: int = setting(48, ">= 1")

    # --- run ---
    # threads for feature extraction, matching and densification (their results do not
    # depend on it)
    num_threads: int = setting(2, ">= 1")
    # threads for incremental mapping and bundle adjustment. Multi-threaded Ceres sums in a
    # varying order, and on weak input the tiny differences change which frames register:
    # two identical runs at 2 threads gave 118 and 116 frames, cameras up to 8.7 mm apart
    # (mp4v phantom session, loaded machine); at 1 thread the outputs are byte-identical,
    # for about 2-3 s more on 124 frames (densification is single-threaded anyway)
    mapping_threads: int = setting(1, ">= 1")
    # seed of every random choice (RANSAC, k-means, mapping): equal inputs give equal outputs
    seed: int = setting(0, ">= 0")

    def __post_init__(self) -> None:
        validate(self, "sfm", {
            "max_image_size 0 (full size) or >= 64": not 0 < self.max_image_size < 64,
            "sequential_max_gap >= sequential_overlap": self.sequential_max_gap >= self.sequential_overlap,
            "densify_patch_px odd": self.densify_patch_px % 2 == 1,
            "densify_min_zncc <= densify_max_zncc": self.densify_min_zncc <= self.densify_max_zncc,
        })
