"""Snakemake adapter: structure from motion of one session."""

from pathlib import Path

from cystomap.logs import log_to
from cystomap.settings import from_mapping
from cystomap.sfm import SfmConfig, run_sfm
from cystomap.snakemake_io import with_threads

sm = snakemake  # type: ignore[name-defined]  # noqa: F821
with log_to(sm.log[0]):
    run_sfm(
        Path(sm.input.preprocessed),
        Path(sm.output.sfm),
        from_mapping(SfmConfig, with_threads(sm.params.sfm, "num_threads", sm.threads), "sfm"),
        extent_mm=sm.params.extent_mm,
        volume_ml=sm.params.volume_ml,
    )
