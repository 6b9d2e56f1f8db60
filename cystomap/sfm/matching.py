"""Match SIFT features of the chosen pairs and verify them geometrically (COLMAP)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from cystomap.sfm.config import SfmConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MatchStats:
    """Verified pairs per frame, from the database after matching."""

    num_pairs: int
    num_verified: int
    verified_per_image: dict[str, int]  # name -> verified pairs it is part of
    mean_inliers: float


def match(
    database: Path, names: list[str], pairs: set[tuple[int, int]], work_dir: Path, cfg: SfmConfig
) -> dict[tuple[int, int], int]:
    """Match and verify ``pairs`` (indices into ``names``); returns their verified inliers."""
    import pycolmap

    if not pairs:
        return {}
    ordered = sorted(pairs)
    pairs_file = work_dir / "pairs.txt"
    pairs_file.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in ordered))
    mopts = pycolmap.FeatureMatchingOptions()
    mopts.num_threads = cfg.num_threads
    mopts.guided_matching = cfg.guided_matching
    mopts.sift.max_ratio = cfg.max_ratio
    mopts.sift.max_distance = cfg.max_distance
    popts = pycolmap.ImportedPairingOptions()
    popts.match_list_path = str(pairs_file)
    vopts = pycolmap.TwoViewGeometryOptions()
    vopts.min_num_inliers = cfg.min_num_inliers
    vopts.ransac.max_error = cfg.ransac_max_error_px
    vopts.ransac.random_seed = cfg.seed
    pycolmap.match_image_pairs(
        database, matching_options=mopts, pairing_options=popts,
        verification_options=vopts, device=pycolmap.Device.cpu,
    )
    verified = read_verified(database, names, cfg.min_num_inliers)
    return {p: verified.get(p, 0) for p in ordered}


def read_verified(database: Path, names: list[str], min_inliers: int) -> dict[tuple[int, int], int]:
    """Verified inlier matches of every pair in the database, keyed by name indices (i < j)."""
    from cystomap.sfm.consistency import read_geometries

    return {p: len(g.matches) for p, g in read_geometries(database, names, None, min_inliers).items()}


def match_sequence(
    database: Path, names: list[str], work_dir: Path, cfg: SfmConfig
) -> tuple[dict[tuple[int, int], int], int]:
    """Match each frame with its ``sequential_overlap`` successors, then extend the window:
    (i, i + 2g) is tried when (i, i + g) had at least ``extend_min_inliers`` inliers, up to
    ``sequential_max_gap`` (see :func:`gap_schedule`). Dense video thus gets wide baselines
    between keyframes, sparse video no useless pairs. Returns the verified inliers of all
    tried pairs and how many pairs were tried."""
    from cystomap.sfm.pairs import extension_pairs, gap_schedule, sequential_pairs

    first = sequential_pairs(len(names), cfg.sequential_overlap)
    verified = match(database, names, first, work_dir, cfg)
    tried = set(first)
    prev = 2 if cfg.sequential_overlap >= 2 else 1
    for gap, every in gap_schedule(cfg.sequential_overlap, cfg.sequential_max_gap):
        base = gap // 2 if gap // 2 >= prev else prev
        new = extension_pairs(verified, len(names), base, gap, cfg.extend_min_inliers,
                              every) - tried
        if not new:
            break
        verified.update(match(database, names, new, work_dir, cfg))
        tried |= new
        log.info("matching: gap %d, %d pairs, %d verified", gap, len(new),
                 sum(1 for p in new if verified.get(p, 0) >= cfg.min_num_inliers))
        prev = gap
    return verified, len(tried)


def read_stats(database: Path, num_pairs: int, min_inliers: int) -> MatchStats:
    """Verified pairs per frame and mean inliers, over all pairs in the database."""
    import pycolmap

    db = pycolmap.Database.open(str(database))
    try:
        names = {im.image_id: im.name for im in db.read_all_images()}
        pair_ids, geoms = db.read_two_view_geometries()
    finally:
        db.close()
    per_image = dict.fromkeys(names.values(), 0)
    inliers = []
    for pair_id, geom in zip(pair_ids, geoms, strict=True):
        n = len(geom.inlier_matches)
        if n < min_inliers:
            continue
        inliers.append(n)
        for image_id in pycolmap.pair_id_to_image_pair(pair_id):
            per_image[names[image_id]] += 1
    mean = float(sum(inliers) / len(inliers)) if inliers else 0.0
    log.info("matching: %d of %d pairs verified, %.0f inlier matches on average",
             len(inliers), num_pairs, mean)
    return MatchStats(num_pairs, len(inliers), per_image, mean)
