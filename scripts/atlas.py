"""Snakemake adapter: atlas, coverage and textured model of one session."""

from pathlib import Path

from cystomap.atlas import AtlasConfig, build_atlas
from cystomap.logs import log_to
from cystomap.settings import from_mapping
from cystomap.snakemake_io import with_threads

sm = snakemake  # type: ignore[name-defined]  # noqa: F821
with log_to(sm.log[0]):
    build_atlas(
        Path(sm.input.sfm),
        Path(sm.input.preprocessed),
        Path(sm.input.mesh),
        Path(sm.output.atlas),
        from_mapping(AtlasConfig, with_threads(sm.params.atlas, "threads", sm.threads), "atlas"),
        anatomy=sm.params.anatomy,
    )
