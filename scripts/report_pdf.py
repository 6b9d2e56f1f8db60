"""Snakemake adapter: report.pdf of one subject, the study report printed by headless Chromium."""

from pathlib import Path

from cystomap.logs import log_to
from cystomap.report.pdf import print_pdf

sm = snakemake  # type: ignore[name-defined]  # noqa: F821
with log_to(sm.log[0]):
    print_pdf(Path(sm.input.html), Path(sm.output.pdf), sm.params.chromium)
