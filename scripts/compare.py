"""Snakemake adapter: compare two sessions of one subject."""

from pathlib import Path

from cystomap.compare import CompareConfig, compare_sessions
from cystomap.compare.stage import SessionPaths
from cystomap.logs import log_to
from cystomap.snakemake_io import job_config

sm = snakemake  # type: ignore[name-defined]  # noqa: F821
with log_to(sm.log[0]):
    a, b = ([Path(sm.input[f"{s}_{k}"]) for k in ("sfm", "preprocessed", "mesh", "atlas", "frames")] for s in "ab")
    compare_sessions(
        SessionPaths(*a),
        SessionPaths(*b),
        Path(sm.output.compare),
        job_config(CompareConfig, sm.params.compare, "compare", sm.threads),
        landmarks=sm.params.landmarks,
    )
