"""Pieces of one incremental mapping joined by the frames they share.

COLMAP's incremental mapper starts a new model where it cannot register the next frame (a
blurred stretch, the scope turning on the spot) and lets the new model take up to
``max_model_overlap`` frames of the earlier ones. Frames of such a piece often cannot be
registered one by one to the largest model (too few of their matches have a 3-D point there),
but the frames both models registered fix the similarity between them: the piece's poses are
brought into the largest model by that similarity (fitted on the reprojections of the shared
frames, COLMAP's model merger, or where too few of their points agree - little parallax - on
the poses of at least three shared frames), its frames triangulated and the whole adjusted. A
join is kept only when the model then contradicts the frame pairs nowhere more than before
(``guard``, the seam rule of :mod:`cystomap.sfm.consistency`); otherwise it is undone.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cystomap.sfm.config import SfmConfig

log = logging.getLogger(__name__)


def _registered(rec: Any) -> set[int]:
    return set(rec.reg_image_ids())


def _pose_similarity(piece: Any, rec: Any, shared: set[int]) -> Any:
    """Similarity rec-from-piece from the poses of the frames both registered: the rotation
    from their orientations (the chordal mean; the camera centres of a few neighbouring
    frames are nearly on a line and fix it badly), scale and shift from their centres. None
    when fewer than three frames are shared, the centres have no spread or, after the fit,
    most of them are further from the model's than the model's median step between
    consecutive frames. Two shared frames fix the scale by the one step between them, with
    nothing left over to test it: on held-out glints:11 (1280x720, blurred) two shared frames
    posed from 20-50 points each put a 41-frame piece at 0.22 of its size (true: about 0.85),
    and the joined model went out 3.5 mm off with every self-check passed
    (docs/measurements.md, "Pieces joined on two shared frames")."""
    import numpy as np
    import pycolmap

    ids = sorted(shared)
    if len(ids) < 3:
        return None
    rots = [np.asarray(rec.image(i).cam_from_world().rotation.matrix()).T
            @ np.asarray(piece.image(i).cam_from_world().rotation.matrix()) for i in ids]
    u, _, vt = np.linalg.svd(np.sum(rots, axis=0))
    rot = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    a = np.array([rec.image(i).projection_center() for i in ids])
    b = np.array([piece.image(i).projection_center() for i in ids]) @ rot.T
    da, db = a - a.mean(0), b - b.mean(0)
    spread = float((db ** 2).sum())
    if spread <= 1e-12:
        return None
    scale = float((da * db).sum()) / spread
    if not scale > 0:
        return None
    shift = a.mean(0) - scale * b.mean(0)
    order = sorted(rec.reg_image_ids(), key=lambda i: rec.image(i).name)
    centres = np.array([rec.image(i).projection_center() for i in order])
    step = float(np.median(np.linalg.norm(np.diff(centres, axis=0), axis=1)))
    if np.median(np.linalg.norm(scale * b + shift - a, axis=1)) > step:
        return None
    return pycolmap.Sim3d(scale, pycolmap.Rotation3d(rot), shift)


def _place(database: Path, rec: Any, piece: Any, sim: Any, opts: Any) -> list[int]:
    """Register in ``rec`` the frames of ``piece`` it lacks, at the piece's poses moved by
    ``sim`` (rec from piece), and triangulate them; returns their image ids."""
    import pycolmap

    moved = pycolmap.Reconstruction(piece)
    moved.transform(sim)
    from cystomap.sfm.consistency import open_mapper

    mapper = open_mapper(database, opts.min_num_matches)
    mapper.begin_reconstruction(rec)  # loads the database's frames the model does not hold
    have = _registered(rec)
    new = sorted(i for i in moved.reg_image_ids() if i not in have and rec.exists_image(i))
    for image_id in new:
        frame_id = rec.image(image_id).frame_id
        rec.frame(frame_id).rig_from_world = moved.frame(moved.image(image_id).frame_id
                                                         ).rig_from_world
        rec.register_frame(frame_id)
    tri = opts.get_triangulation()
    for image_id in new:
        mapper.triangulate_image(tri, image_id)
    mapper.complete_and_merge_tracks(tri)
    mapper.end_reconstruction(False)
    return new


def join(database: Path, rec: Any, others: list[Any], names: list[str], key: set[str],
         opts: Any, cfg: SfmConfig, refine: bool, guard: Callable[[Any], int],
         ) -> tuple[Any, list[Any], dict[str, Any]]:
    """Join the ``others`` (pieces of the same mapping, largest first) that share registered
    frames with ``rec`` into it; ``guard(rec)`` counts the places where the model contradicts
    the frame pairs (weak or broken seams): a join that raises it is undone. Returns (model,
    pieces not joined, figures for quality.json)."""
    import pycolmap

    from cystomap.sfm.mapping import adjust, register_rest

    figures: dict[str, Any] = {"pieces": len(others), "joined": 0, "frames_added": 0,
                               "undone": 0, "no_alignment": 0}
    if not others:
        return rec, others, figures
    bad = guard(rec)
    left = []
    for piece in sorted(others, key=lambda r: -r.num_reg_images()):
        shared = _registered(piece) & _registered(rec)
        if not shared or _registered(piece) <= _registered(rec):
            left.append(piece)
            continue
        sim = pycolmap.align_reconstructions_via_reprojections(
            piece, rec, max_reproj_error=cfg.max_reproj_error_px)
        if sim is None:  # too few shared points agree (little parallax): the shared poses
            sim = _pose_similarity(piece, rec, shared)
        if sim is None:
            log.info("pieces: no similarity to the model from the %d frames a piece of %d "
                     "shares with it", len(shared), piece.num_reg_images())
            figures["no_alignment"] += 1
            left.append(piece)
            continue
        backup = pycolmap.Reconstruction(rec)
        before = rec.num_reg_images()
        _place(database, rec, piece, sim, opts)
        adjust(rec, cfg, refine, cfg.ba_global_max_iterations)
        register_rest(database, rec, names, opts, key)
        now = guard(rec)
        if now > bad:
            log.info("pieces: a piece of %d frames (%d shared) joined the model but %d place(s) "
                     "then contradicted the frame pairs (%d before); undone",
                     piece.num_reg_images(), len(shared), now, bad)
            rec = backup
            figures["undone"] += 1
            left.append(piece)
            continue
        log.info("pieces: joined a piece of %d frames by the %d frames it shares with the model: "
                 "%d -> %d frames", piece.num_reg_images(), len(shared), before,
                 rec.num_reg_images())
        figures["joined"] += 1
        figures["frames_added"] += rec.num_reg_images() - before
        bad = now
    return rec, left, figures
