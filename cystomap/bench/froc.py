"""FROC benchmark of change detection on randomized phantom pairs.

Each pair is one phantom bladder filmed twice (session 1 → session 2, every stage run on
both): a texture family, per-session photometry (white balance, exposure, gain, vignetting,
``photometric_variation`` 1), lesions of random kinds, sizes (``MIN_DIAMETER_MM`` to
``MAX_DIAMETER_MM``, one per size band at least) and sites (seam, pole, neck or anywhere), and
a deformation of 0 to ``MAX_DEFORMATION``; ``no_change`` pairs have no lesion, so every
region is a false positive. Everything is drawn from the pair's seed.

The operating point of the detector is its ``false_alarm_rate`` (the expected false regions
per pair it is asked for): each pair is compared once at the highest rate, and the regions
whose ``expected_false`` is at most a rate are its detections at that rate, scored against
the phantom's truth; the table gives, per rate, the false positives per pair (lesion pairs,
no-change pairs) and the recall per lesion size band, and the plot recall against false
positives per pair (FROC).

``HELD_OUT_FAMILY`` and ``HELD_OUT_KIND`` take no part in any tuning of the detector (its
development used the default wall and the other kinds); their recall is reported apart.
"""

from __future__ import annotations

import csv
import itertools
import json
import logging
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cystomap.bench.pipeline import run_session
from cystomap.errors import InputError, StageError
from cystomap.phantom import PhantomConfig, default_camera
from cystomap.phantom.config import LESION_KINDS, TEXTURE_FAMILIES
from cystomap.phantom.lesions import lesion_kinds_and_sites

log = logging.getLogger(__name__)

HELD_OUT_FAMILY = "C"
HELD_OUT_KIND = "perivascular"
MIN_DIAMETER_MM = 3.0
MAX_DIAMETER_MM = 30.0
MAX_DEFORMATION = 0.10
# lesion size bands (mm, lower bound inclusive) of the recall columns
SIZE_BANDS = ((3.0, 5.0), (5.0, 10.0), (10.0, 20.0), (20.0, 30.01))
RATES = (0.03, 0.1, 0.3, 1.0)
# a lesion "seen by both" has at least this share of its disc filmed in each session (truth)
SEEN_BY_BOTH = 0.5
# one lesion on the atlas seam, one over the pole, one beside the neck, the rest anywhere
SITES = ("seam", "pole", "neck", "any", "any", "any")


@dataclass(frozen=True)
class Pair:
    """One randomized pair: its name, its phantom and whether it has no change."""

    name: str
    cfg: PhantomConfig
    no_change: bool


def random_pair(seed: int, no_change: bool = False, n_frames: int = 124,
                lossless_video: bool = True) -> Pair:
    """The randomized pair of ``seed`` (see the module docstring)."""
    g = np.random.default_rng([seed, 13])
    family = str(g.choice(TEXTURE_FAMILIES))
    # one lesion per size band, two more of any size (log-uniform)
    diam = [float(g.uniform(lo, min(hi, MAX_DIAMETER_MM))) for lo, hi in SIZE_BANDS]
    diam += [float(np.exp(g.uniform(np.log(MIN_DIAMETER_MM), np.log(MAX_DIAMETER_MM))))
             for _ in range(2)]
    diam = [round(d, 1) for d in diam]
    kinds = tuple(str(k) for k in g.choice(LESION_KINDS, size=len(diam)))
    sites = tuple(str(s) for s in g.permutation(SITES))
    deformation = round(float(g.uniform(0.0, MAX_DEFORMATION)), 3)
    cfg = PhantomConfig(seed=seed, n_frames=n_frames, texture_family=family,
                        photometric_variation=1.0, deformation=deformation,
                        lossless_video=lossless_video,
                        lesion_diameters_mm=() if no_change else tuple(diam),
                        lesion_kinds=() if no_change else kinds,
                        lesion_sites=() if no_change else sites)
    return Pair(f"{'nochange' if no_change else 'pair'}{seed}", cfg, no_change)


def pairs(n_pairs: int, n_no_change: int, first_seed: int = 100, **kw: Any) -> list[Pair]:
    return ([random_pair(first_seed + i, **kw) for i in range(n_pairs)]
            + [random_pair(first_seed + 1000 + i, True, **kw) for i in range(n_no_change)])


def undrawable(pair: Pair) -> str | None:
    """Why the phantom cannot draw ``pair`` (None: it can). Session 2 adds the papillary
    lesions' relief to a deformed wall, which can leave it no longer star-shaped about its
    barycentre (held-out seeds 118 and 119: min cos 0.047 and 0.040); such a pair says nothing
    about the pipeline and is left out of the benchmark, by name, instead of ending the run."""
    from cystomap.phantom.geometry import session_bladder

    try:
        for s in (1, 2):
            session_bladder(pair.cfg, s)
    except InputError as exc:
        return str(exc)
    return None


def build_pair(work: Path, pair: Pair, width: int, height: int) -> tuple[list[Path], float]:
    """Both sessions of ``pair`` through every stage (kept when already built); their roots and
    the seconds spent building."""
    camera = default_camera(width, height)
    roots, t0 = [], time.perf_counter()
    for s in (1, 2):
        root = work / f"{pair.name}_{width}x{height}_s{s}"
        stamp = root / "built.json"
        if not stamp.is_file():
            shutil.rmtree(root, ignore_errors=True)
            run_session(root, pair.cfg, s, camera)
            stamp.write_text(json.dumps({"seconds": time.perf_counter() - t0}))
        roots.append(root)
    return roots, time.perf_counter() - t0


def score_pair(work: Path, pair: Pair, roots: list[Path], rates: tuple[float, ...],
               ) -> list[dict[str, Any]]:
    """Compare the pair at every rate; one row per (rate, true lesion or false positive)."""
    from cystomap.compare import CompareConfig, compare_sessions
    from cystomap.compare.stage import SessionPaths
    from cystomap.evaluate import evaluate_changes

    def paths(root: Path) -> SessionPaths:
        return SessionPaths(root / "sfm", root / "preprocess", root / "mesh/surface.ply",
                            root / "atlas", root / "frames")

    truth = roots[1] / "truth"
    kinds = {}
    with open(truth / "lesions.csv") as fh:
        for r in csv.DictReader(fh):
            kinds[str(r["id"])] = (r.get("kind", ""), r.get("site", ""))
    seen = lesion_seen_shares(roots[0] / "truth", truth)
    rows: list[dict[str, Any]] = []
    # one comparison at the highest rate; the lower operating points keep its regions whose
    # expected_false is at most their rate (the null is fitted alike at every rate of at
    # least PEEL_EXPECTED; below it, and for the saddle splits, this approximates a run at
    # that rate)
    out = work / f"{roots[0].name[:-3]}_compare"
    cfg = CompareConfig(false_alarm_rate=max(rates), findback_frames=0, model=False)
    t0 = time.perf_counter()
    compare_sessions(paths(roots[0]), paths(roots[1]), out, cfg)
    seconds = time.perf_counter() - t0
    reg = json.loads((out / "registration.json").read_text())
    with open(out / "changes.csv") as fh:
        reader = csv.DictReader(fh)
        fields, regions = list(reader.fieldnames or []), list(reader)
    for rate in rates:
        kept = out / f"changes_rate{rate:g}.csv"
        with open(kept, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=fields)
            writer.writeheader()
            writer.writerows(r for r in regions if float(r["expected_false"]) <= rate)
        ev = evaluate_changes(truth, roots[1] / "sfm", kept).get("lesions", {})
        base = {"pair": pair.name, "rate": rate, "family": pair.cfg.texture_family,
                "deformation": pair.cfg.deformation, "no_change": pair.no_change,
                "registered": reg.get("registered"), "compare_s": round(seconds, 1),
                "false_positives": ev.get("false_positives"),
                "regions": ev.get("n_detected")}
        for e in ev.get("lesions", []):
            kind, site = kinds.get(str(e["id"]), ("", ""))
            rows.append({**base, "lesion": e["id"], "kind": kind, "site": site,
                         "diameter_mm": e["diameter_mm"], "detected": e["detected"],
                         "centroid_error_mm": e.get("localisation_error_mm"),
                         "size_error_pct": e.get("size_error_percent"),
                         **seen.get(str(e["id"]), {})})
        if not ev.get("lesions"):
            rows.append({**base, "lesion": "", "kind": "", "site": "", "diameter_mm": None,
                         "detected": None, "centroid_error_mm": None, "size_error_pct": None})
    return rows


def lesion_seen_shares(truth_a: Path, truth_b: Path) -> dict[str, dict[str, float]]:
    """Per lesion id of session B: the share of its disc each session's frames saw
    (``seen_a``, ``seen_b``; :func:`cystomap.evaluate.lesions.seen_share`). A lesion on wall
    session A never filmed is a change no comparison can decide; the summary counts the
    lesions both sessions saw at least half of (``SEEN_BY_BOTH``) apart."""
    from cystomap.evaluate.lesions import seen_share
    from cystomap.evaluate.truth import load_truth

    a, b = load_truth(truth_a), load_truth(truth_b)
    les = b.lesions
    if not len(les):
        return {}
    xyz = les[["x", "y", "z"]].to_numpy(np.float64)
    diam = les["diameter_mm"].to_numpy(np.float64)
    sa, sb = seen_share(a, xyz, diam), seen_share(b, xyz, diam)
    return {str(i): {"seen_a": round(float(x), 3), "seen_b": round(float(y), 3)}
            for i, x, y in zip(les["id"], sa, sb, strict=True)}


def failed_rows(pair: Pair, rates: tuple[float, ...], reason: str) -> list[dict[str, Any]]:
    """Rows of a pair whose session failed (the stage said so): every lesion missed, no region."""
    kinds, sites = lesion_kinds_and_sites(pair.cfg)
    base = {"family": pair.cfg.texture_family, "deformation": pair.cfg.deformation,
            "no_change": pair.no_change, "registered": None, "compare_s": None,
            "false_positives": 0, "regions": 0, "failed": reason[:200]}
    rows: list[dict[str, Any]] = []
    for rate in rates:
        head = {"pair": pair.name, "rate": rate, **base}
        rows += [{**head, "lesion": i + 1, "kind": k, "site": st, "diameter_mm": d,
                  "detected": False, "centroid_error_mm": None, "size_error_pct": None}
                 for i, (d, k, st) in enumerate(zip(pair.cfg.lesion_diameters_mm, kinds, sites,
                                                    strict=True))]
        if pair.no_change:
            rows.append({**head, "lesion": "", "kind": "", "site": "", "diameter_mm": None,
                         "detected": None, "centroid_error_mm": None, "size_error_pct": None})
    return rows


def summarise(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per rate and subset (all, held-out family, held-out kind, the rest; and, where the rows
    say what each session filmed, the lesions both sessions saw at least ``SEEN_BY_BOTH`` of,
    all and of the held-out family): false positives per pair, recall per size band and from
    5 and 10 mm, and the centroid and size errors of the lesions found from 5 mm (the issue's
    targets: 2 mm, 20 %)."""
    import pandas as pd

    df = pd.DataFrame(rows)
    out = []
    for rate, d in df.groupby("rate"):
        per_pair = d.groupby("pair").agg(fp=("false_positives", "first"),
                                         no_change=("no_change", "first"),
                                         family=("family", "first"))
        les = d[d["diameter_mm"].notna()]
        subsets = {
            "all": (les, per_pair[~per_pair.no_change]),
            f"held-out family {HELD_OUT_FAMILY}": (les[les.family == HELD_OUT_FAMILY],
                                                  per_pair[~per_pair.no_change
                                                           & (per_pair.family == HELD_OUT_FAMILY)]),
            f"held-out kind {HELD_OUT_KIND}": (les[les.kind == HELD_OUT_KIND], None),
            "tuned (not held out)": (les[(les.family != HELD_OUT_FAMILY) & (les.kind != HELD_OUT_KIND)],
                                     per_pair[~per_pair.no_change & (per_pair.family != HELD_OUT_FAMILY)]),
        }
        if {"seen_a", "seen_b"} <= set(les.columns):  # lesions a comparison can decide
            both = (les.seen_a >= SEEN_BY_BOTH) & (les.seen_b >= SEEN_BY_BOTH)
            subsets[f"seen by both (>= {SEEN_BY_BOTH:g} of the lesion)"] = (les[both], None)
            subsets[f"seen by both, held-out family {HELD_OUT_FAMILY}"] = (
                les[both & (les.family == HELD_OUT_FAMILY)], None)
        nc = per_pair[per_pair.no_change]
        for name, (sub, pp) in subsets.items():
            row: dict[str, Any] = {"rate": rate, "subset": name,
                                   "lesions": len(sub),
                                   "pairs": None if pp is None else len(pp),
                                   "fp_per_pair": None if pp is None or not len(pp) else
                                   round(float(pp.fp.mean()), 2),
                                   "no_change_pairs": len(nc),
                                   "fp_per_no_change_pair": round(float(nc.fp.mean()), 2) if len(nc)
                                   else None}
            for lo, hi in SIZE_BANDS:
                band = sub[(sub.diameter_mm >= lo) & (sub.diameter_mm < hi)]
                row[f"recall_{lo:g}-{min(hi, MAX_DIAMETER_MM):g}mm"] = (
                    f"{int(band.detected.sum())}/{len(band)}" if len(band) else "")
            for lo in (5.0, 10.0):  # the recall targets
                band = sub[sub.diameter_mm >= lo]
                row[f"recall_from_{lo:g}mm"] = (f"{int(band.detected.sum())}/{len(band)}"
                                                if len(band) else "")
            found = sub[sub.detected == True]  # noqa: E712 (object column with None)
            row["recall"] = round(float(found.shape[0] / len(sub)), 3) if len(sub) else None
            big = found[found.diameter_mm >= 5.0]  # centroid and size targets, from 5 mm
            row["centroid_error_mm_median"] = (round(float(big.centroid_error_mm.median()), 2)
                                               if len(big) else None)
            row["centroid_over_2mm"] = (f"{int((big.centroid_error_mm > 2.0).sum())}/{len(big)}"
                                        if len(big) else "")
            row["size_within_20pct"] = (f"{int((big.size_error_pct.abs() <= 20.0).sum())}/{len(big)}"
                                        if len(big) else "")
            row["centroid_error_mm_max"] = (round(float(found.centroid_error_mm.max()), 2)
                                            if len(found) else None)
            row["size_error_pct_abs_median"] = (round(float(found.size_error_pct.abs().median()), 1)
                                                if len(found) else None)
            out.append(row)
    return out


def plot(summary: list[dict[str, Any]], path: Path) -> None:
    """FROC curves (recall per size band against false positives per pair, log x) as a PNG."""
    import cv2

    w, h, m = 720, 480, 70
    img = np.full((h, w, 3), 255, np.uint8)
    fps = [r["fp_per_pair"] for r in summary if r["subset"] == "all" and r["fp_per_pair"] is not None]
    lo_x, hi_x = np.log10(0.01), np.log10(max([3.0, *fps]))

    def xy(fp: float, rec: float) -> tuple[int, int]:
        x = (np.log10(max(fp, 0.01)) - lo_x) / (hi_x - lo_x)
        return int(m + x * (w - 1.5 * m)), int(h - m - rec * (h - 1.7 * m))

    cv2.rectangle(img, xy(0.01, 0), xy(10 ** hi_x, 1), (0, 0, 0), 1)
    for t in (0.01, 0.1, 0.3, 1.0):
        if np.log10(t) <= hi_x:
            x, y = xy(t, 0)
            cv2.putText(img, f"{t:g}", (x - 12, y + 20), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
    for r in (0.0, 0.5, 1.0):
        x, y = xy(0.01, r)
        cv2.putText(img, f"{r:.1f}", (x - 35, y + 5), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
    cv2.putText(img, "false positives per pair (log)", (w // 2 - 120, h - 20), cv2.FONT_HERSHEY_SIMPLEX,
                0.5, (0, 0, 0), 1)
    cv2.putText(img, "recall", (5, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
    colours = [(200, 0, 0), (0, 140, 0), (0, 0, 220), (160, 0, 160)]
    rows = [r for r in summary if r["subset"] == "all" and r["fp_per_pair"] is not None]
    for k, (lo, hi) in enumerate(SIZE_BANDS):
        key = f"recall_{lo:g}-{min(hi, MAX_DIAMETER_MM):g}mm"
        pts = []
        for r in sorted(rows, key=lambda r: r["rate"]):
            if r[key]:
                a, b = (int(v) for v in r[key].split("/"))
                pts.append(xy(r["fp_per_pair"], a / b))
        for p, q in itertools.pairwise(pts):
            cv2.line(img, p, q, colours[k], 2, cv2.LINE_AA)
        for p in pts:
            cv2.circle(img, p, 4, colours[k], -1, cv2.LINE_AA)
        cv2.putText(img, f"{lo:g}-{min(hi, MAX_DIAMETER_MM):g} mm", (w - 150, 40 + 20 * k),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.5, colours[k], 1, cv2.LINE_AA)
    cv2.imwrite(str(path), img[..., ::-1])


def bench_froc(work: Path, out: Path, n_pairs: int = 30, n_no_change: int = 10, width: int = 1280,
               height: int = 720, n_frames: int = 124, rates: tuple[float, ...] = RATES,
               first_seed: int = 100) -> list[dict[str, Any]]:
    """Build, compare and score the randomized pairs; write ``froc_lesions.csv`` (one row per
    rate and lesion), ``froc.csv`` (the summary), ``froc.md`` and ``froc.png`` under ``out``."""
    from cystomap.bench.common import write_table

    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    left_out: list[str] = []
    for pair in pairs(n_pairs, n_no_change, first_seed, n_frames=n_frames):
        why = undrawable(pair)
        if why is not None:
            log.warning("froc: %s left out: %s", pair.name, why)
            left_out.append(pair.name)
            continue
        try:
            roots, build_s = build_pair(work, pair, width, height)
        except StageError as exc:  # a session the pipeline cannot reconstruct: its lesions missed
            log.warning("froc: %s: a session failed, its lesions count as missed: %s", pair.name, exc)
            truths = [work / f"{pair.name}_{width}x{height}_s{s}" / "truth" for s in (1, 2)]
            seen = (lesion_seen_shares(*truths)
                    if all((t / "seen.png").is_file() for t in truths) else {})
            rows += [{**r, **seen.get(str(r["lesion"]), {})}
                     for r in failed_rows(pair, rates, str(exc))]
            _write_csv(out / "froc_lesions.csv", rows)
            continue
        log.info("froc: %s built (%.0f s): %s", pair.name, build_s, pair.cfg)
        rows += [{**r, "build_s": round(build_s)} for r in score_pair(work, pair, roots, rates)]
        _write_csv(out / "froc_lesions.csv", rows)  # after every pair: a partial run is kept
    summary = summarise(rows)
    _write_csv(out / "froc.csv", summary)
    write_table(summary, out, "froc", f"FROC: {n_pairs} randomized pairs + {n_no_change} no-change pairs "
                f"at {width}x{height}, {n_frames} frames (held out: texture family {HELD_OUT_FAMILY}, "
                f"lesion kind {HELD_OUT_KIND})"
                + (f"; left out, the phantom cannot draw them: {', '.join(left_out)}" if left_out else ""))
    plot(summary, out / "froc.png")
    return summary


def _write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)


__all__ = ["HELD_OUT_FAMILY", "HELD_OUT_KIND", "SEEN_BY_BOTH", "Pair", "bench_froc",
           "lesion_seen_shares", "pairs", "random_pair"]
