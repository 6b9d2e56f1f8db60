"""Snakemake adapter: compare two sessions of one subject."""

from pathlib import Path

from cystomap.compare import CompareConfig, compare_sessions
from cystomap.compare.stage import SessionPaths
from cystomap.logs import log_to
from cystomap.settings import from_mapping
from cystomap.snakemake_io import with_threads

sm = snakemake  # type: ignore[name-defined]  # noqa: F821
with log_to(sm.log[0]):
    a, b = ([Path(sm.input[f"{s}_{k}"]) for k in ("sfm", "preprocessed", "mesh", "atlas", "frames")] for s in "ab")
    compare_sessions(
        SessionPaths(*a),
        SessionPaths(*b),
        Path(sm.output.compare),
        from_mapping(CompareConfig, with_threads(sm.params.compare, "threads", sm.threads), "compare"),
        landmarks=sm.params.landmarks,
    )
