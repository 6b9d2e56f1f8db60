"""Independent halves: a check of the model that no pairwise test can make.

The seam and loop tests of :mod:`cystomap.sfm.consistency` ask whether each verified image pair
agrees with the relative pose the model gives its two frames. A model can pass all of them and
still be wrong by several frame steps: a stretch held by few, weak pairs (blur, glints) can bend
or drift smoothly, every pair's epipolar geometry bending with it, and relative poses say
nothing about scale along the video. Two maps made from disjoint frames do not share that
error: the registered (key)frames are split alternately into two halves, each half is mapped
again on its own (the same verified pairs among its frames, incremental mapping, no
densification), and every piece of each half is brought onto the model by a similarity fitted
on the camera centres of its frames. Where the model and a half disagree by more than the
model's own step between consecutive frames (the median distance between consecutive camera
centres, so no threshold in model units), the frame is *off*: the two maps do not even agree on
which neighbour a frame is nearest to. A correct model agrees with both halves to a small share
of a step; the check fails when :data:`MIN_OFF_RUN` consecutive frames of the model are off
(so in both halves: they alternate), where one half alone can be wrong by its own fault. A
frame neither half placed ends a run: otherwise one half's error on both sides of the other
half's gap makes a run of its own (seen on a clean 640x360 phantom session at 0.15 mm: the
even half 2-3 steps off at frames 92-96, where the odd half had lost 93 and 95, and the odd
half 4-6 steps off from 97 on, the even half agreeing there).
Frames that neither half could place (a stretch held only by pairs too weak for a map of half
the frames) are counted as unconfirmed: reported, not failed.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from cystomap.geometry.sim3 import umeyama
from cystomap.sfm.config import SfmConfig

log = logging.getLogger(__name__)

# consecutive frames (of the compared ones, in video order) off that fail the check: one half
# can place a frame badly by its own fault; three in a row are off in both halves
MIN_OFF_RUN = 3


def _centres(rec: Any) -> dict[str, np.ndarray]:
    return {rec.image(i).name: np.asarray(rec.image(i).projection_center(), float)
            for i in rec.reg_image_ids()}


def _map_half(database: Path, image_dir: Path, out: Path, cfg: SfmConfig, refine: bool,
              frames: list[str]) -> list[dict[str, np.ndarray]]:
    """Camera centres of every piece (at least ``min_model_frames``) of ``frames`` mapped on
    their own."""
    import pycolmap

    from cystomap.sfm.mapping import pipeline_options

    pycolmap.set_random_seed(cfg.seed)
    opts = pipeline_options(cfg, refine, image_dir)
    opts.image_names = frames
    out.mkdir(parents=True, exist_ok=True)
    recs = pycolmap.incremental_mapping(database, image_dir, out, options=opts)
    return [_centres(r) for r in recs.values() if r.num_reg_images() >= cfg.min_model_frames]


def compare(model: dict[str, np.ndarray], order: list[str],
            halves: list[list[dict[str, np.ndarray]]]) -> dict[str, Any]:
    """Disagreement of each half's pieces with the model's camera centres, in model steps
    (``order``: the registered frames in video order)."""
    pos = np.array([model[n] for n in order])
    step = float(np.median(np.linalg.norm(np.diff(pos, axis=0), axis=1))) if len(pos) > 1 else 0.0
    off: list[set[str]] = []
    residual: dict[str, float] = {}
    compared = []
    for pieces in halves:
        # a frame two pieces of one half hold is placed by the one that agrees better: pieces
        # of one half that disagree with each other are that half's own fault
        best: dict[str, float] = {}
        for piece in pieces:
            common = [n for n in order if n in piece]
            if len(common) < 3 or step <= 0:
                continue
            src = np.array([piece[n] for n in common])
            dst = np.array([model[n] for n in common])
            sim = umeyama(src, dst)
            if sim is None:
                continue
            err = np.linalg.norm(sim.apply(src) - dst, axis=1) / step
            for n, e in zip(common, err, strict=True):
                best[n] = min(best.get(n, np.inf), float(e))
        residual.update(best)
        off.append({n for n, e in best.items() if e > 1.0})
        compared.append(len(best))
    # consecutive frames of the model off, alternately in one half and the other: both maps,
    # made from disjoint frames, put that stretch elsewhere than the model does
    run = longest = 0
    start = first = None
    offs = set().union(*off) if off else set()
    for n in order:
        if n in offs:
            run += 1
            if run == 1:
                start = n
            if run > longest:
                longest, first = run, start
        else:  # agrees, or neither half placed it: a run needs evidence at every frame
            run = 0
    # consecutive frames of the model that neither half placed: not confirmed (not wrong)
    gap = unplaced = 0
    for n in order:
        gap = 0 if n in residual else gap + 1
        unplaced = max(unplaced, gap)
    vals = np.array(list(residual.values())) if residual else np.zeros(0)
    worst = max(residual, key=residual.__getitem__) if residual else None
    return {
        "frames_compared": compared,
        "step": step,
        "residual_median_steps": round(float(np.median(vals)), 4) if len(vals) else None,
        "residual_max_steps": round(float(vals.max()), 4) if len(vals) else None,
        "worst_frame": worst,
        "frames_off": [len(b) for b in off],
        "longest_off_run": longest,
        "off_run_from": first,
        "frames_unconfirmed": len(order) - len(residual),
        "longest_unconfirmed_run": unplaced,
        "consistent": longest < MIN_OFF_RUN,
    }


def halves_check(database: Path, image_dir: Path, work: Path, rec: Any, names: list[str],
                 key: list[int], cfg: SfmConfig, refine: bool) -> dict[str, Any]:
    """Map the registered keyframes of ``rec`` in two alternating halves and compare (see the
    module's doc); figures for quality.json's ``consistency.halves``."""
    model = _centres(rec)
    keys = {names[i] for i in key}
    order = [n for n in names if n in model]
    mapped = [n for n in order if n in keys]
    if len(mapped) < 4 * cfg.min_model_frames:
        mapped = order
    split = [mapped[0::2], mapped[1::2]]
    if min(len(h) for h in split) < 2 * cfg.min_model_frames:
        return {"checked": False, "reason": f"too few frames ({len(order)})", "consistent": True}
    halves = [_map_half(database, image_dir, work / f"half_{k}", cfg, refine, h)
              for k, h in enumerate(split)]
    out = {"checked": True, "frames": [len(h) for h in split],
           "pieces": [len(h) for h in halves],
           **compare(model, [n for n in order if n in set(mapped)], halves)}
    out["step"] = round(out["step"], 6)
    log.info("halves: %s and %s frames mapped on their own in %s and %s piece(s); disagreement "
             "with the model: median %s, max %s steps (%s); frames off %s, longest run %d",
             *out["frames"], *out["pieces"], out["residual_median_steps"],
             out["residual_max_steps"], out["worst_frame"], out["frames_off"],
             out["longest_off_run"])
    return out
