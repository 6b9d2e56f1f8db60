"""What the report shows, read from the stage outputs of one subject.

Every figure comes from a file a stage wrote (``frames.json``, ``sfm/quality.json``,
``mesh.json``, ``atlas.json`` (with its regions), ``registration.json``, ``compare.json``, ``changes.csv``,
``findback.csv``). A
missing or unreadable JSON file leaves its figures empty ("—" in the report) with a warning,
so one damaged summary does not hide the rest; missing images are an error.
"""

from __future__ import annotations

import csv
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cystomap.errors import InputError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SessionInputs:
    """Where one session's outputs are (the workflow's standard layout)."""

    name: str
    date: str  # ISO date, or "" when unknown
    frames: Path  # frames/ (frames.json)
    sfm: Path  # sfm/ (quality.json)
    mesh: Path  # mesh/surface.ply (mesh.json next to it)
    atlas: Path  # atlas/ (atlas.png, coverage.png, atlas.json)

    @classmethod
    def from_root(cls, name: str, date: str, root: Path) -> SessionInputs:
        root = Path(root)
        return cls(name, date, root / "frames", root / "sfm", root / "mesh" / "surface.ply", root / "atlas")


@dataclass(frozen=True)
class ComparisonInputs:
    """One comparison: session names (A earlier, B later) and the compare/ directory."""

    a: str
    b: str
    compare: Path


def read_json(path: Path) -> dict[str, Any]:
    """A JSON object, or {} (with a warning) when the file is missing or unreadable."""
    try:
        data = json.loads(Path(path).read_text())
    except FileNotFoundError:
        log.warning("report: %s not found; its figures are left empty", path)
        return {}
    except (OSError, ValueError) as exc:
        log.warning("report: cannot read %s (%s); its figures are left empty", path, exc)
        return {}
    if not isinstance(data, dict):
        log.warning("report: %s is not a JSON object; its figures are left empty", path)
        return {}
    return data


def _num(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value)


@dataclass
class SessionSummary:
    """The quality figures of one session."""

    name: str
    date: str
    frames_decoded: int | None = None
    frames_kept: int | None = None
    frames_in: int | None = None  # frames given to SfM
    registered: int | None = None
    reprojection_px: float | None = None
    points: int | None = None
    coverage_percent: float | None = None
    views_median: float | None = None
    contributing: int | None = None
    overexposed: int | None = None  # registered frames too clipped to paint the atlas from
    watertight: bool | None = None
    metric: bool = False
    units: str = "model units"
    scale_source: str = "unknown"
    consistency: str | None = None  # SfM self-check in words (sfm/quality.json "consistency")
    consistency_weak: bool = False
    inputs: SessionInputs | None = None
    # atlas.json "regions": per standard region its wall area and seen share (% of its area);
    # empty for atlases written before the regions
    regions: dict[str, dict[str, float]] = field(default_factory=dict)

    def seen(self, region: str) -> float | None:
        """Seen share (%) of a standard region, None when unknown."""
        return _num(self.regions.get(region, {}).get("seen_percent"))

    @property
    def registered_share(self) -> float | None:
        if self.registered is None or not self.frames_in:
            return None
        return self.registered / self.frames_in


def scale_text(scale: dict[str, Any]) -> str:
    """Where the metric scale came from, in words."""
    source = scale.get("source")
    factor = _num(scale.get("factor"))
    if source == "extent_mm":
        extent = _num(scale.get("model_extent"))
        size = f", {extent * factor:.0f} mm" if extent and factor else ""
        return f"known largest extent of the wall{size} (extent_mm)"
    if source == "volume_ml":
        volume = _num(scale.get("model_volume"))
        size = f", {volume * factor ** 3 / 1000:.0f} ml" if volume and factor else ""
        return f"known bladder volume{size} (volume_ml)"
    if source == "none":
        return "none: no extent_mm or volume_ml, lengths in arbitrary model units"
    return "unknown"


def consistency_text(c: dict[str, Any]) -> tuple[str, bool]:
    """The SfM self-check in words, and whether it is weak (loop pairs mostly contradict the
    model, or frame pairs contradict it somewhere)."""
    loops, agree = _int(c.get("loop_pairs")), _int(c.get("loop_pairs_agreeing"))
    seam = _num(c.get("weakest_seam_share"))
    parts = []
    if loops:
        parts.append(f"{agree} of {loops} loop-closure pairs agree with the model")
    if seam is not None:
        parts.append(f"at least {100 * seam:.0f} % of the frame pairs across any point of the "
                     "video agree")
    halves = c.get("halves") if isinstance(c.get("halves"), dict) else {}
    if halves.get("checked"):
        worst = _num(halves.get("residual_max_steps"))
        parts.append("two maps of alternate frames " + (
            "agree with it" if halves.get("consistent", True) else
            f"place {halves.get('longest_off_run')} consecutive frames elsewhere (drift)")
            + (f" (at most {worst:.1f} frame steps apart)" if worst is not None else ""))
    rot = c.get("rotation") if isinstance(c.get("rotation"), dict) else {}
    if rot.get("checked"):
        worst = _num(rot.get("worst_deg"))
        where = rot.get("worst_frames") or [["?", "?"], ["?", "?"]]
        parts.append(
            f"the rotations of {rot.get('pairs_tested')} loop pairs with parallax "
            + (f"say the model has turned frames {where[0][0]}..{where[0][1]} against "
               f"{where[1][0]}..{where[1][1]} by {worst:.1f}° (rotation drift)"
               if rot.get("flagged") and worst is not None else "show no rotation drift"))
    weak = bool(loops and agree is not None and agree < 0.5 * loops) or bool(c.get("seams_weak"))
    return "; ".join(parts) or "not checked", weak or c.get("consistent") is False


def attempts_text(a: dict[str, Any]) -> str | None:
    """The SfM stage's mappings in words when it mapped more than once (sfm/quality.json
    "attempts", cystomap/sfm/retry.py): "mapped twice (47 frames at 640 px, then ...)"."""
    runs = [r for r in a.get("runs", []) if isinstance(r, dict)]
    if len(runs) < 2:
        return None

    def one(r: dict[str, Any]) -> str:
        what = "failed" if r.get("failed") else f"{_int(r.get('registered'))} frames"
        flag = ", flagged" if r.get("flagged") else ""
        return f"{what}{flag} at {_int(r.get('max_image_size'))} px"

    kept = _int(a.get("kept"))
    which = {0: "the first", 1: "the second"}.get(kept or 0, f"run {kept}")
    return (f"mapped {'twice' if len(runs) == 2 else f'{len(runs)} times'} ("
            + ", then ".join(one(r) for r in runs) + f"); kept {which}")


def load_session(inputs: SessionInputs) -> SessionSummary:
    s = SessionSummary(inputs.name, inputs.date, inputs=inputs)
    frames = read_json(Path(inputs.frames) / "frames.json")
    quality = read_json(Path(inputs.sfm) / "quality.json")
    mesh = read_json(Path(inputs.mesh).with_name("mesh.json"))
    atlas = read_json(Path(inputs.atlas) / "atlas.json")
    s.frames_decoded = _int(frames.get("frames_decoded"))
    s.frames_kept = _int(frames.get("frames_kept"))
    s.frames_in = _int(quality.get("frames_in"))
    s.registered = _int(quality.get("registered"))
    s.reprojection_px = _num(quality.get("mean_reprojection_error_px"))
    s.points = _int(quality.get("points"))
    scale = quality.get("scale") if isinstance(quality.get("scale"), dict) else {}
    s.metric = bool(quality.get("metric", scale.get("metric", False)))
    s.units = "mm" if s.metric else "model units"
    s.scale_source = scale_text(scale) if scale else "unknown"
    c = quality.get("consistency") if isinstance(quality.get("consistency"), dict) else {}
    if c:
        s.consistency, s.consistency_weak = consistency_text(c)
    a = quality.get("attempts") if isinstance(quality.get("attempts"), dict) else {}
    tried = attempts_text(a) if a else None
    if tried:
        s.consistency = f"{s.consistency}; {tried}" if s.consistency else tried
    s.coverage_percent = _num(atlas.get("coverage_percent"))
    cov = atlas.get("coverage") if isinstance(atlas.get("coverage"), dict) else {}
    s.views_median = _num(cov.get("views_median"))
    fr = atlas.get("frames") if isinstance(atlas.get("frames"), dict) else {}
    s.contributing = _int(fr.get("contributing"))
    s.overexposed = _int(fr.get("overexposed"))
    if isinstance(mesh.get("watertight"), bool):
        s.watertight = mesh["watertight"]
    regions = atlas.get("regions") if isinstance(atlas.get("regions"), dict) else {}
    s.regions = {str(k): v for k, v in regions.items() if isinstance(v, dict)}
    return s


def _int(value: Any) -> int | None:
    v = _num(value)
    return None if v is None else int(v)


@dataclass
class ComparisonSummary:
    """Registration and changes of one pair of sessions."""

    a: str
    b: str
    directory: Path
    registered: bool = False
    reason: str = ""
    matches: int | None = None
    inliers: int | None = None
    inlier_ratio: float | None = None
    scale: float | None = None
    residual_mm: float | None = None  # median inlier residual after the spline
    compared_share: float | None = None
    changes: list[dict[str, Any]] = field(default_factory=list)
    findback: list[dict[str, Any]] = field(default_factory=list)  # rows of findback.csv
    registration: dict[str, Any] = field(default_factory=dict)  # registration.json
    sfm_flags: dict[str, str] = field(default_factory=dict)  # "a"/"b": the SfM self-check's reason
    sfm_short: dict[str, str] = field(default_factory=dict)  # "a"/"b": a model short of frames

    def _named(self, by_key: dict[str, str]) -> list[tuple[str, str]]:
        names = {"a": self.a, "b": self.b}
        return [(names[k], v) for k, v in sorted(by_key.items()) if k in names]

    def flagged(self) -> list[tuple[str, str]]:
        """(session name, reason) of the sessions whose SfM model its self-check flagged."""
        return self._named(self.sfm_flags)

    def short(self) -> list[tuple[str, str]]:
        """(session name, in words) of the sessions whose SfM model holds too few frames."""
        return self._named(self.sfm_short)

    @property
    def key(self) -> str:
        return f"{self.a}_vs_{self.b}"

    def file(self, name: str) -> Path | None:
        p = self.directory / name
        return p if p.is_file() else None


def load_comparison(inputs: ComparisonInputs) -> ComparisonSummary:
    d = Path(inputs.compare)
    if not d.is_dir():
        raise InputError(f"comparison {inputs.a} vs {inputs.b}: {d} not found")
    c = ComparisonSummary(inputs.a, inputs.b, d)
    reg = read_json(d / "registration.json")
    c.registration = reg
    summary = read_json(d / "compare.json")
    c.registered = bool(reg.get("registered", summary.get("registered", False)))
    c.reason = str(reg.get("reason") or summary.get("reason") or "")
    if not c.registered and not c.reason:
        c.reason = "registration.json is missing or says nothing" if not reg else "no reason given"
    c.matches = _int(reg.get("matches"))
    c.inliers = _int(reg.get("inliers"))
    c.inlier_ratio = _num(reg.get("inlier_ratio"))
    tf = reg.get("transform_a_to_b") if isinstance(reg.get("transform_a_to_b"), dict) else {}
    c.scale = _num(tf.get("scale"))
    c.residual_mm = _find_residual(reg)
    c.compared_share = _find_compared(summary)
    flags = summary.get("sfm_flags")
    if isinstance(flags, dict):
        c.sfm_flags = {str(k): str(v) for k, v in flags.items()}
    short = summary.get("sfm_short")
    if isinstance(short, dict):
        c.sfm_short = {str(k): str(v) for k, v in short.items()}
    c.changes = read_changes(d / "changes.csv")
    if (d / "findback.csv").is_file():  # compare's find-back (absent in older outputs)
        c.findback = read_changes(d / "findback.csv")
    return c


def _find_residual(reg: dict[str, Any]) -> float | None:
    """Median residual (model units) of the inliers after the spline, when recorded."""
    res = reg.get("residual_mm")
    if isinstance(res, dict):
        for stage in ("after_spline", "before_spline"):
            block = res.get(stage)
            if isinstance(block, dict) and _num(block.get("median")) is not None:
                return _num(block.get("median"))
    return None


def _find_compared(summary: dict[str, Any]) -> float | None:
    diff = summary.get("difference")
    if isinstance(diff, dict):
        return _num(diff.get("joint_share_of_b_wall"))
    return None


def read_changes(path: Path) -> list[dict[str, Any]]:
    """Rows of changes.csv with numbers parsed ([] when missing or header only)."""
    if not Path(path).is_file():
        log.warning("report: %s not found; no changes listed", path)
        return []
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    out = []
    for r in rows:
        parsed: dict[str, Any] = {}
        for k, v in r.items():
            try:
                parsed[k] = float(v) if v not in ("", None) else None
            except ValueError:
                parsed[k] = v
        out.append(parsed)
    return out
