"""Snakemake adapter: the study report of one subject."""

from collections.abc import Iterable
from pathlib import Path

from cystomap.logs import log_to
from cystomap.report import ComparisonInputs, ReportConfig, SessionInputs, build_report
from cystomap.settings import from_mapping


def paths(value: str | Iterable[str] | None) -> list[Path]:
    """A named input as a list of paths (Snakemake may give a str for a single file)."""
    if value is None:
        return []
    return [Path(value)] if isinstance(value, str) else [Path(v) for v in value]


sm = snakemake  # type: ignore[name-defined]  # noqa: F821
with log_to(sm.log[0]):
    inputs = dict(sm.input.items())
    columns = [paths(inputs.get(k)) for k in ("frames", "sfm", "mesh", "atlas")]
    sessions = [SessionInputs(s["name"], s["date"], *files)
                for s, *files in zip(sm.params.sessions, *columns, strict=True)]
    comparisons = [ComparisonInputs(a, b, d)
                   for (a, b), d in zip(sm.params.pairs, paths(inputs.get("compare")), strict=True)]
    evaluation = paths(inputs.get("evaluation"))
    build_report(
        sm.wildcards.subject,
        sessions,
        comparisons,
        Path(sm.output.html),
        from_mapping(ReportConfig, sm.params.report, "report"),
        evaluation[0] if evaluation else None,
    )
