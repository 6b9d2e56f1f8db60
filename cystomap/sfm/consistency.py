"""Loop closures that cannot fold the model, and a self-check that a folded model cannot pass.

Repeated texture (the same patch in many places of the wall) gives retrieval pairs between
frames that do not overlap, with many matches and a consistent but false two-view geometry.
Mapped together with the sequential chain, such pairs can fold the model: part of the video is
placed on the wrong wall. True loop pairs, on the other hand, are often the only link across a
stretch the chain cannot map (the scope turning on the spot: no parallax). So the model is
first mapped with all pairs and then checked (:func:`joint_check`, before densification): it
is kept when no seam is broken (below) and most verified loop pairs agree with it. Otherwise it
is mapped again from the sequential chain (video-order and gap-extension pairs) alone; each
retrieval (loop) pair is then tested against the relative pose that model gives its two
frames, and only the loop pairs that agree are used to merge tracks before densification and
the final adjustment (:func:`close_loops`).

A pair *agrees* with a model when the model's epipolar geometry keeps its verified matches:
the share of its inlier matches within ``ransac_max_error_px`` (Sampson distance) of the
model's epipolar lines is closer to what the sequential pairs of the same model keep (their
median share) than to what the same matches keep when their partners are shuffled (chance,
per pair). No threshold is tuned: both reference levels come from the model and the pair.

The self-check on the final model: each boundary between consecutive registered frames is
crossed by several chain pairs; where most of them (at least two) disagree with the model,
the two sides of the model contradict the matches that link them - a fold or a break - and
the stage fails. The share of loop pairs that agree with the final model is reported, and a
low share (repeated texture) is logged as a warning.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cystomap.errors import StageError
from cystomap.sfm.config import SfmConfig

log = logging.getLogger(__name__)

Pair = tuple[int, int]


@dataclass
class PairGeometry:
    """The verified matches of one image pair (indices into the video-ordered names)."""

    i: int
    j: int
    matches: np.ndarray  # (N, 2) point2D indices in image i and image j
    geometry: Any = None  # the pycolmap.TwoViewGeometry as read (image order of the database)


@dataclass
class Agreement:
    """How well the verified matches of each pair fit a model's relative poses."""

    share: dict[Pair, float]  # inlier matches the model's epipolar geometry keeps
    chance: dict[Pair, float]  # the same with shuffled partners
    error_px: dict[Pair, float]  # median Sampson distance of the matches (px)
    reference: float  # median share over the chain pairs
    agrees: dict[Pair, bool] = field(default_factory=dict)


def read_geometries(database: Path, names: list[str], pairs: Iterable[Pair] | None = None,
                    min_inliers: int = 1) -> dict[Pair, PairGeometry]:
    """Verified inlier matches from ``database``, keyed by name indices (i < j); only
    ``pairs`` when given."""
    import pycolmap

    want = None if pairs is None else set(pairs)
    index = {name: k for k, name in enumerate(names)}
    db = pycolmap.Database.open(str(database))
    try:
        ids = {im.image_id: index[im.name] for im in db.read_all_images() if im.name in index}
        pair_ids, geoms = db.read_two_view_geometries()
    finally:
        db.close()
    out = {}
    for pair_id, geom in zip(pair_ids, geoms, strict=True):
        a, b = pycolmap.pair_id_to_image_pair(pair_id)
        m = np.asarray(geom.inlier_matches, dtype=np.int64).reshape(-1, 2)
        if len(m) < min_inliers or a not in ids or b not in ids:
            continue
        i, j = ids[a], ids[b]
        if i > j:
            i, j, m = j, i, m[:, ::-1]
        if want is None or (i, j) in want:
            out[(i, j)] = PairGeometry(i, j, m, geom)
    return out


def delete_pairs(database: Path, names: list[str], pairs: Iterable[Pair]) -> None:
    """Remove the two-view geometry (verified matches) of ``pairs`` from ``database``."""
    import pycolmap

    db = pycolmap.Database.open(str(database))
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        for i, j in pairs:
            a, b = ids.get(names[i]), ids.get(names[j])
            if a is not None and b is not None and db.exists_two_view_geometry(a, b):
                db.delete_two_view_geometry(a, b)
    finally:
        db.close()


def _keypoints(rec: Any, image_id: int, cache: dict[int, np.ndarray]) -> np.ndarray:
    if image_id not in cache:
        pts = rec.image(image_id).points2D
        cache[image_id] = np.array([p.xy for p in pts], dtype=np.float64).reshape(-1, 2)
    return cache[image_id]


def _sampson_px(rec: Any, names: list[str], g: PairGeometry, by_name: dict[str, int],
                cache: dict[int, np.ndarray], shuffle: np.random.Generator | None = None,
                ) -> np.ndarray | None:
    """Sampson distance (px) of each match of ``g`` from the model's epipolar geometry;
    None when one of the two frames is not registered."""
    ia, ib = by_name.get(names[g.i]), by_name.get(names[g.j])
    if ia is None or ib is None:
        return None
    im1, im2 = rec.image(ia), rec.image(ib)
    if not (im1.has_pose and im2.has_pose):
        return None
    cam1, cam2 = rec.camera(im1.camera_id), rec.camera(im2.camera_id)
    p1 = _keypoints(rec, ia, cache)[g.matches[:, 0]]
    p2 = _keypoints(rec, ib, cache)[g.matches[:, 1]]
    if shuffle is not None:
        p2 = p2[shuffle.permutation(len(p2))]
    x1 = np.c_[cam1.cam_from_img(p1), np.ones(len(p1))]
    x2 = np.c_[cam2.cam_from_img(p2), np.ones(len(p2))]
    a, b = im1.cam_from_world(), im2.cam_from_world()
    r1, r2 = np.asarray(a.rotation.matrix()), np.asarray(b.rotation.matrix())
    rot = r2 @ r1.T
    t = np.asarray(b.translation) - rot @ np.asarray(a.translation)
    focal = 0.5 * (cam1.mean_focal_length() + cam2.mean_focal_length())
    norm = float(np.linalg.norm(t))
    y1 = x1 @ rot.T
    if norm < 1e-12:  # no baseline: the rotation alone maps the rays
        d = y1[:, :2] / y1[:, 2:3] - x2[:, :2]
        return focal * np.linalg.norm(d, axis=1)
    t = t / norm
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    ess = tx @ rot
    ex1 = x1 @ ess.T
    etx2 = x2 @ ess
    num = np.einsum("ij,ij->i", x2, ex1)
    den = ex1[:, 0] ** 2 + ex1[:, 1] ** 2 + etx2[:, 0] ** 2 + etx2[:, 1] ** 2
    return focal * np.abs(num) / np.sqrt(np.maximum(den, 1e-300))


def agreement(rec: Any, names: list[str], geoms: dict[Pair, PairGeometry], chain: set[Pair],
              threshold_px: float, seed: int = 0) -> Agreement:
    """Share of each pair's matches the model keeps, the chance level and the decision."""
    rng = np.random.default_rng(seed)
    by_name = {rec.image(i).name: i for i in rec.reg_image_ids()}
    share, chance, err = {}, {}, {}
    cache: dict[int, np.ndarray] = {}
    for p in sorted(geoms):
        g = geoms[p]
        e = _sampson_px(rec, names, g, by_name, cache)
        if e is None or not len(e):
            continue
        e0 = _sampson_px(rec, names, g, by_name, cache, rng)
        share[p] = float(np.mean(e <= threshold_px))
        chance[p] = float(np.mean(e0 <= threshold_px)) if e0 is not None else 0.0
        err[p] = float(np.median(e))
    ref = [share[p] for p in share if p in chain]
    reference = float(np.median(ref)) if ref else 1.0
    out = Agreement(share, chance, err, reference)
    out.agrees = {p: share[p] >= 0.5 * (chance[p] + reference) and share[p] > chance[p]
                  for p in share}
    return out


def write_pairs(database: Path, names: list[str], geoms: list[PairGeometry]) -> None:
    """Write the two-view geometries of ``geoms`` back into ``database``."""
    import pycolmap

    db = pycolmap.Database.open(str(database))
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        for g in geoms:
            a, b = sorted((ids[names[g.i]], ids[names[g.j]]))  # the order it was read in
            if g.geometry is not None and not db.exists_two_view_geometry(a, b):
                db.write_two_view_geometry(a, b, g.geometry)
    finally:
        db.close()


def open_mapper(database: Path, min_num_matches: int) -> Any:
    """A COLMAP incremental mapper on the correspondences of ``database`` (pairs with at least
    ``min_num_matches`` verified matches)."""
    import pycolmap

    cache_opts = pycolmap.DatabaseCacheOptions()
    cache_opts.min_num_matches = min_num_matches
    db = pycolmap.Database.open(str(database))
    try:
        cache = pycolmap.DatabaseCache.create(db, cache_opts)
    finally:
        db.close()
    return pycolmap.IncrementalMapper(cache)


def _merge(rec: Any, database: Path, names: list[str], frames: set[int], cfg: SfmConfig,
           tri_options: Any) -> int:
    """Triangulate ``frames`` again with the database's correspondences and merge tracks."""
    by_name = {rec.image(i).name: i for i in rec.reg_image_ids()}
    mapper = open_mapper(database, cfg.min_num_inliers)
    mapper.begin_reconstruction(rec)
    for k in sorted(frames):
        mapper.triangulate_image(tri_options, by_name[names[k]])
    merged = int(mapper.complete_and_merge_tracks(tri_options))
    mapper.end_reconstruction(False)
    return merged


def close_loops(rec: Any, database: Path, names: list[str], chain: set[Pair], loops: set[Pair],
                cfg: SfmConfig, tri_options: Any, adjust: Callable[[Any], Any] | None = None,
                geoms: dict[Pair, PairGeometry] | None = None, max_rounds: int = 3,
                ) -> dict[str, Any]:
    """Test the verified ``loops`` against ``rec`` (mapped from the chain pairs) and merge
    tracks along the ones that agree; after adjusting (``adjust(rec)``), the others are tested
    again against the less drifted model, for at most ``max_rounds`` rounds. Loop pairs that
    never agree are deleted from ``database``. ``geoms``: the verified matches of the chain
    and loop pairs when already read (the database may no longer hold the loops')."""
    if geoms is None:
        geoms = read_geometries(database, names, chain | loops, cfg.min_num_inliers)
    verified = {p for p in loops if p in geoms}
    delete_pairs(database, names, verified)
    accepted: set[Pair] = set()
    merged, rounds, reference = 0, 0, 1.0
    for _ in range(max_rounds):
        agr = agreement(rec, names, geoms, chain, cfg.ransac_max_error_px, cfg.seed)
        reference = agr.reference
        new = {p for p in verified - accepted if agr.agrees.get(p, False)}
        if not new:
            break
        rounds += 1
        accepted |= new
        write_pairs(database, names, [geoms[p] for p in sorted(new)])
        merged += _merge(rec, database, names, {k for p in new for k in p}, cfg, tri_options)
        if adjust is not None:
            adjust(rec)
        log.info("loops: round %d, %d more loop pairs agree with the model (%d of %d)",
                 rounds, len(new), len(accepted), len(verified))
    rejected = verified - accepted
    log.info("loops: %d retrieval pairs verified, %d agree with the sequential model and are "
             "used, %d rejected; %d observations completed or merged",
             len(verified), len(accepted), len(rejected), merged)
    return {"loop_pairs_tried": len(loops), "loop_pairs_verified": len(verified),
            "loop_pairs_accepted": len(accepted), "loop_pairs_rejected": len(rejected),
            "loop_rounds": rounds, "loop_observations_merged": merged,
            "chain_agreement_median": round(reference, 4),
            "rejected_pairs": [[names[i], names[j]] for i, j in sorted(rejected)[:200]],
            "accepted": accepted, "rejected": rejected, "geometries": geoms}


def _seams(pairs: list[Pair], agrees: list[bool], frames: list[int]) -> list[dict[str, int]]:
    """For each boundary between consecutive registered frames: chain pairs crossing it and
    how many agree."""
    out = []
    arr = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    ok = np.array(agrees, dtype=bool)
    for a, b in itertools.pairwise(frames):
        cross = (arr[:, 0] <= a) & (arr[:, 1] >= b)
        out.append({"after": a, "before": b, "pairs": int(cross.sum()),
                    "agreeing": int((cross & ok).sum())})
    return out


def figures(rec: Any, names: list[str], geoms: dict[Pair, PairGeometry], chain: set[Pair],
            loops: set[Pair], cfg: SfmConfig
            ) -> tuple[dict[str, Any], list[dict[str, int]], Agreement]:
    """Consistency figures of ``rec`` (for quality.json) and the broken seams: boundaries
    between consecutive registered frames where the chain pairs crossing it mostly (two or
    more) contradict the model; and the agreement of every pair."""
    agr = agreement(rec, names, geoms, chain, cfg.ransac_max_error_px, cfg.seed)
    chain_p = sorted(p for p in agr.share if p in chain)
    loop_p = sorted(p for p in agr.share if p in loops)
    by_name = {rec.image(i).name for i in rec.reg_image_ids()}
    frames = [k for k, n in enumerate(names) if n in by_name]
    seams = _seams(chain_p, [agr.agrees[p] for p in chain_p], frames)
    broken = [s for s in seams if s["pairs"] - s["agreeing"] >= 2
              and s["agreeing"] < 0.5 * s["pairs"]]
    weak = [s for s in seams if s["pairs"] - s["agreeing"] >= 2 and s not in broken]
    shares = [s["agreeing"] / s["pairs"] for s in seams if s["pairs"]]
    loop_ok = [p for p in loop_p if agr.agrees[p]]
    chain_ok = [p for p in chain_p if agr.agrees[p]]

    def med(ps: list[Pair]) -> float | None:
        return round(float(np.median([agr.error_px[p] for p in ps])), 4) if ps else None

    fig: dict[str, Any] = {
        "threshold_px": cfg.ransac_max_error_px,
        "chain_pairs": len(chain_p),
        "chain_pairs_agreeing": len(chain_ok),
        "chain_agreement_median": round(agr.reference, 4),
        "chain_error_px_median": med(chain_p),
        "loop_pairs": len(loop_p),
        "loop_pairs_agreeing": len(loop_ok),
        "loop_agreeing_share": round(len(loop_ok) / len(loop_p), 4) if loop_p else None,
        "loop_error_px_median": med(loop_ok),
        "weakest_seam_share": round(min(shares), 4) if shares else None,
        "seams_broken": [_seam_names(s, names) for s in broken],
        "seams_weak": [_seam_names(s, names) for s in weak[:20]],
        "seams_weak_count": len(weak),
        "consistent": not broken,
    }
    return fig, broken, agr


def joint_check(rec: Any, names: list[str], geoms: dict[Pair, PairGeometry], chain: set[Pair],
                loops: set[Pair], cfg: SfmConfig) -> dict[str, Any]:
    """Whether a model mapped with the loop pairs can be kept: no broken or weak seam, and most of
    the verified loop pairs agree with it (repeated texture gives many false loop pairs: then
    the loops are held back and mapping starts again from the chain). Figures in the form of
    :func:`close_loops`'s, plus ``consistent`` and, when not, ``reason``."""
    fig, _, agr = figures(rec, names, geoms, chain, loops, cfg)
    verified = {p for p in loops if p in geoms}
    rejected = sorted(p for p in verified if not agr.agrees.get(p, False))
    out: dict[str, Any] = {
        "loop_pairs_tried": len(loops), "loop_pairs_verified": len(verified),
        "loop_pairs_accepted": fig["loop_pairs_agreeing"],
        "loop_pairs_rejected": fig["loop_pairs"] - fig["loop_pairs_agreeing"],
        "chain_agreement_median": fig["chain_agreement_median"], "mapped_with_loops": True,
        "rejected_pairs": [[names[i], names[j]] for i, j in rejected[:200]],
        "consistent": True,
    }
    share = fig["loop_agreeing_share"]
    # a model mapped with pairs that were not tested first must agree with the chain
    # everywhere: a weak seam (two or more chain pairs across one boundary contradicting it)
    # is enough to map again without the loops (seen: a fold by false loops that left 8 of 12
    # chain pairs agreeing at each boundary of the folded stretch)
    seams = fig["seams_broken"] or fig["seams_weak"]
    if seams:
        s = seams[0]
        out["consistent"] = False
        out["reason"] = (f"contradicts the frame pairs between {s['after']} and {s['before']} "
                         f"({s['pairs'] - s['agreeing']} of {s['pairs']}; "
                         f"{len(fig['seams_broken'])} broken, {len(fig['seams_weak'])} weak "
                         f"place(s))")
    elif share is not None and share < 0.5:
        out["consistent"] = False
        out["reason"] = (f"disagrees with {fig['loop_pairs'] - fig['loop_pairs_agreeing']} of "
                         f"its {fig['loop_pairs']} verified loop pairs (repeated texture?)")
    return out


def self_check(rec: Any, names: list[str], geoms: dict[Pair, PairGeometry], chain: set[Pair],
               loops: set[Pair], cfg: SfmConfig) -> dict[str, Any]:
    """Consistency figures of the final model (for quality.json); raises StageError when the
    chain pairs across some boundary mostly contradict the model (a fold or break)."""
    fig, broken, _ = figures(rec, names, geoms, chain, loops, cfg)
    if broken:
        s = broken[0]
        raise StageError(
            f"sfm: the model is inconsistent (folded or broken): between {names[s['after']]} and "
            f"{names[s['before']]} {s['pairs'] - s['agreeing']} of the {s['pairs']} verified "
            f"frame pairs linking the two sides contradict the model's poses ({len(broken)} such "
            f"place(s) in the video); repeated texture or a false loop closure may have placed "
            f"part of the video on the wrong wall"
        )
    if fig["seams_weak"]:
        w = fig["seams_weak"]
        log.warning("sfm self-check: %d place(s) in the video where 2 or more frame pairs "
                    "contradict the model (first between %s and %s)", len(w),
                    w[0]["after"], w[0]["before"])
    if fig["loop_pairs"] and fig["loop_pairs_agreeing"] < 0.5 * fig["loop_pairs"]:
        log.warning("sfm self-check: only %d of %d verified loop pairs agree with the model "
                    "(repeated texture? the others were not used)", fig["loop_pairs_agreeing"],
                    fig["loop_pairs"])
    return fig


def _seam_names(s: dict[str, int], names: list[str]) -> dict[str, Any]:
    return {"after": names[s["after"]], "before": names[s["before"]], "pairs": s["pairs"],
            "agreeing": s["agreeing"]}
