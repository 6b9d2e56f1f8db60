"""Snakemake adapter: atlas, coverage and textured model of one session."""

from pathlib import Path

from cystomap.atlas import AtlasConfig, build_atlas
from cystomap.logs import log_to
from cystomap.snakemake_io import job_config

sm = snakemake  # type: ignore[name-defined]  # noqa: F821
with log_to(sm.log[0]):
    build_atlas(
        Path(sm.input.sfm),
        Path(sm.input.preprocessed),
        Path(sm.input.mesh),
        Path(sm.output.atlas),
        job_config(AtlasConfig, sm.params.atlas, "atlas", sm.threads),
        anatomy=sm.params.anatomy,
    )
