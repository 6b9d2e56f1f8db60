"""Score whole sessions and comparisons, and write ``evaluation.json`` / ``.tsv`` / ``.md``."""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cystomap.evaluate.anatomy import score_anatomy
from cystomap.evaluate.config import EvalConfig
from cystomap.evaluate.lesions import score_changes
from cystomap.evaluate.surface import read_atlas_json, score_atlas, score_surface
from cystomap.evaluate.trajectory import (
    Model,
    Sim3,
    find_models,
    load_model,
    score_model,
    score_registration,
    score_trajectory,
)
from cystomap.evaluate.truth import Truth, load_truth
from cystomap.outputs import atomic_file, write_json

log = logging.getLogger(__name__)

PathLike = str | os.PathLike[str]
#: Rows of the markdown summary (flattened keys); the TSV holds every scalar.
SUMMARY_KEYS = (
    "registration.registered_share", "registration.registered_share_good",
    "registration.n_models", "reprojection.mean_error_px",
    "trajectory.rmse_mm", "trajectory.rmse_percent_extent", "trajectory.scale_ratio",
    "trajectory.scale_error", "trajectory.rotation_error_deg_median",
    "surface.accuracy_mean_mm", "surface.accuracy_median_mm", "surface.completeness",
    "atlas.coverage_percent", "atlas.coverage_percent_true", "atlas.coverage_error_pp",
    "atlas.mask_iou", "atlas.albedo_correlation", "atlas.ssim", "atlas.ssim_stretched",
    "atlas.detail_correlation", "atlas.sharpness_ratio",
    "alignment.rmse_mm", "lesions.recall", "lesions.false_positives",
    "lesions.localisation_error_mm_mean", "lesions.size_error_percent_mean",
    "anatomy.neck_error_deg", "anatomy.roll_error_deg", "anatomy.regions_accuracy",
    "lesions.region_accuracy",
)


@dataclass(frozen=True)
class SessionInputs:
    """One session to score: its truth directory and whichever pipeline outputs exist."""

    name: str
    truth_dir: PathLike
    sfm: PathLike | Sequence[PathLike] | None = None
    mesh: PathLike | None = None
    atlas: PathLike | None = None


@dataclass(frozen=True)
class ComparisonInputs:
    """One comparison A → B: session B's truth and SfM model, and the detected changes."""

    name: str
    truth_dir_b: PathLike
    sfm_b: PathLike | Sequence[PathLike] | None
    changes: PathLike | None


def sessions_from_lists(
    names: Sequence[str],
    truth_dirs: Sequence[PathLike],
    sfm: Sequence[PathLike | None] | None = None,
    meshes: Sequence[PathLike | None] | None = None,
    atlases: Sequence[PathLike | None] | None = None,
) -> list[SessionInputs]:
    """Zip parallel lists (e.g. Snakemake inputs) into SessionInputs; None/"" = not produced."""
    n = len(names)
    cols = [_column(c, n, what) for c, what in ((truth_dirs, "truth_dirs"), (sfm, "sfm"),
                                                 (meshes, "meshes"), (atlases, "atlases"))]
    return [SessionInputs(names[i], *(c[i] for c in cols)) for i in range(n)]  # type: ignore[arg-type]


def comparisons_from_lists(
    names: Sequence[str],
    truth_dirs_b: Sequence[PathLike],
    sfm_b: Sequence[PathLike | None],
    changes: Sequence[PathLike | None],
) -> list[ComparisonInputs]:
    n = len(names)
    cols = [_column(c, n, what) for c, what in ((truth_dirs_b, "truth_dirs_b"), (sfm_b, "sfm_b"),
                                                 (changes, "changes"))]
    return [ComparisonInputs(names[i], *(c[i] for c in cols)) for i in range(n)]  # type: ignore[arg-type]


def _column(values: Sequence[Any] | None, n: int, what: str) -> list[Any]:
    if values is None:
        return [None] * n
    if len(values) != n:
        raise ValueError(f"{what}: expected {n} entries (one per name), got {len(values)}")
    return [v if v not in ("", None) else None for v in values]


def _paths(value: PathLike | Iterable[PathLike] | None) -> list[Path]:
    if value is None or value == "":
        return []
    if isinstance(value, str | os.PathLike):
        return [Path(value)]
    return [Path(v) for v in value if v not in ("", None)]


def _load_models(sfm: PathLike | Sequence[PathLike] | None, cfg: EvalConfig,
                 left_out: list[str]) -> list[Model]:
    models = []
    for p in _paths(sfm):
        found = find_models(p)
        if not found:
            left_out.append(f"sfm: no COLMAP model at {p}")
            log.warning("no COLMAP model at %s; its scores are left out", p)
        models.extend(load_model(m, cfg) for m in found)
    return models


def _reference(models: list[Model], cfg: EvalConfig) -> Model:
    """The model the mesh, atlas and changes are taken to be in (``cfg.reference_model``)."""
    if cfg.reference_model == "largest":
        return max(models, key=lambda m: len(m.frames))  # first of the largest
    return models[0]


def _align(truth: Truth, models: list[Model], cfg: EvalConfig,
           left_out: list[str]) -> tuple[dict[str, Any] | None, Sim3 | None]:
    if not models:
        return None, None
    res = score_trajectory(truth, _reference(models, cfg), cfg)
    if res is None:
        left_out.append("trajectory: too few registered frames with a true pose")
        return None, None
    return res


def evaluate_session(
    truth_dir: PathLike,
    sfm_dir: PathLike | Sequence[PathLike] | None = None,
    mesh_ply: PathLike | None = None,
    atlas_dir: PathLike | None = None,
    cfg: EvalConfig | None = None,
) -> dict[str, Any]:
    """Score one session's outputs against its truth; any missing output leaves its scores out.

    ``sfm_dir``: one or more COLMAP model directories (or parents of numbered models). One is
    the reference (``cfg.reference_model``: the first, as the mesh stage picks it, or the
    largest): its Sim(3) to the truth brings the mesh and the atlas (in its frame) into the
    truth frame. Registration counts frames registered in any of the models. Sections of the result:
    registration, models, reprojection, trajectory, surface, atlas, and left_out (reasons).
    """
    cfg = cfg or EvalConfig()
    truth = load_truth(truth_dir)
    left_out: list[str] = []
    result: dict[str, Any] = {
        "truth_dir": str(truth_dir),
        "inputs": {"sfm": [str(p) for p in _paths(sfm_dir)], "mesh": _str(mesh_ply),
                   "atlas": _str(atlas_dir)},
    }
    models = _load_models(sfm_dir, cfg, left_out)
    sim3 = None
    if models:
        result["registration"] = score_registration(truth, models)
        result["models"] = [score_model(truth, m) for m in models]
        ref = _reference(models, cfg)
        result["reprojection"] = {
            "mean_error_px": ref.reprojection_error_px,
            "reported_mean_error_px": ref.quality.get("mean_reprojection_error_px"),
        }
        traj, sim3 = _align(truth, models, cfg, left_out)
        if traj is not None:
            result["trajectory"] = traj
    elif not _paths(sfm_dir):
        left_out.append("sfm: not given")

    mesh = Path(mesh_ply) if mesh_ply else None
    if mesh is None or not mesh.is_file():
        left_out.append(f"surface: no mesh{f' at {mesh}' if mesh else ''}")
    elif sim3 is None:
        left_out.append("surface: no Sim(3) alignment (needs an SfM model)")
    else:
        result["surface"] = score_surface(truth, mesh, sim3, cfg)

    atlas = Path(atlas_dir) if atlas_dir else None
    if atlas is not None and atlas.is_file():  # the path of atlas.json itself
        atlas = atlas.parent
    if atlas is None or not (atlas / "atlas.json").is_file():
        left_out.append(f"atlas: no atlas.json{f' in {atlas}' if atlas else ''}")
    else:
        result["atlas"] = score_atlas(truth, atlas, sim3, cfg)
        if sim3 is not None:
            anatomy = score_anatomy(truth, read_atlas_json(atlas), sim3)
            if anatomy is not None:
                result["anatomy"] = anatomy
    result["left_out"] = left_out
    for why in left_out:
        log.info("%s: left out: %s", truth_dir, why)
    return result


def evaluate_changes(
    truth_dir_b: PathLike,
    sfm_dir_b: PathLike | Sequence[PathLike] | None,
    changes_csv: PathLike | None,
    cfg: EvalConfig | None = None,
) -> dict[str, Any]:
    """Score a comparison's ``changes.csv`` (in session B's model frame) against B's lesions."""
    cfg = cfg or EvalConfig()
    truth = load_truth(truth_dir_b)
    left_out: list[str] = []
    result: dict[str, Any] = {"truth_dir_b": str(truth_dir_b), "changes": _str(changes_csv)}
    changes = Path(changes_csv) if changes_csv else None
    if changes is None or not changes.is_file():
        left_out.append(f"lesions: no changes.csv{f' at {changes}' if changes else ''}")
    else:
        models = _load_models(sfm_dir_b, cfg, left_out)
        traj, sim3 = _align(truth, models, cfg, left_out)
        if sim3 is None or traj is None:
            left_out.append("lesions: no Sim(3) alignment of session B (needs its SfM model)")
        else:
            result["alignment"] = {k: traj[k] for k in ("n_matched", "rmse_mm", "scale_ratio")}
            result["lesions"] = score_changes(truth, changes, sim3, cfg)
    result["left_out"] = left_out
    return result


def evaluate_subject(
    out_dir: PathLike,
    sessions: Sequence[SessionInputs],
    comparisons: Sequence[ComparisonInputs] = (),
    cfg: EvalConfig | None = None,
) -> dict[str, Any]:
    """Score every session and comparison; write evaluation.json, evaluation.tsv, evaluation.md."""
    from cystomap import __version__

    cfg = cfg or EvalConfig()
    names = [s.name for s in sessions] + [c.name for c in comparisons]
    if len(set(names)) != len(names):
        raise ValueError(f"session and comparison names must be unique, got {names}")
    report = {
        "cystomap_version": __version__,
        "config": dataclasses.asdict(cfg),
        "sessions": {s.name: evaluate_session(s.truth_dir, s.sfm, s.mesh, s.atlas, cfg)
                     for s in sessions},
        "comparisons": {c.name: evaluate_changes(c.truth_dir_b, c.sfm_b, c.changes, cfg)
                        for c in comparisons},
    }
    out = Path(out_dir)
    write_json(out / "evaluation.json", report)
    write_tsv(out / "evaluation.tsv", report)
    write_markdown(out / "evaluation.md", report)
    return report


def flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Dotted keys of every scalar (lists of dicts by index; numeric lists are skipped)."""
    flat: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            flat.update(flatten(v, key + "."))
        elif isinstance(v, list):
            for i, item in enumerate(v):
                if isinstance(item, dict):
                    flat.update(flatten(item, f"{key}.{i}."))
        else:
            flat[key] = v
    return flat


def _fmt(v: Any, digits: int = 6) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, float):
        if not math.isfinite(v):
            return "nan"
        return f"{0.0 if abs(v) < 1e-9 else v:.{digits}g}"  # float noise of exact results
    return str(v)


def write_tsv(path: PathLike, report: dict[str, Any]) -> Path:
    """Long table: kind, name, metric, value (one row per scalar score)."""
    lines = ["kind\tname\tmetric\tvalue"]
    for kind in ("sessions", "comparisons"):
        for name, res in report[kind].items():
            for k, v in flatten(res).items():
                lines.append(f"{kind[:-1]}\t{name}\t{k}\t{_fmt(v)}")
    with atomic_file(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return Path(path)


def write_markdown(path: PathLike, report: dict[str, Any]) -> Path:
    """Summary tables (metric × session, metric × comparison) and what was left out."""
    parts = ["# cystomap evaluation", ""]
    for kind, title in (("sessions", "Sessions"), ("comparisons", "Comparisons")):
        results = report[kind]
        if not results:
            continue
        flats = {n: flatten(r) for n, r in results.items()}
        keys = [k for k in SUMMARY_KEYS if any(k in f for f in flats.values())]
        parts += [f"## {title}", "", "| metric | " + " | ".join(flats) + " |",
                  "|---|" + "---:|" * len(flats)]
        parts += [f"| {k} | " + " | ".join(_fmt(f.get(k), 4) for f in flats.values()) + " |"
                  for k in keys]
        parts.append("")
        for n, r in results.items():
            parts += [f"- {n}: left out: {why}" for why in r.get("left_out", [])]
        parts.append("")
    with atomic_file(path) as tmp:
        tmp.write_text("\n".join(parts))
    return Path(path)


def _str(p: PathLike | None) -> str | None:
    return None if p in (None, "") else str(p)
