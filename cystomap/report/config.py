"""Settings of the study report (rule ``report``)."""

from __future__ import annotations

from dataclasses import dataclass

from cystomap.settings import setting, validate


@dataclass(frozen=True)
class ReportConfig:
    """Settings of the ``report`` rule."""

    # Images (atlases, coverage, difference and change maps) are embedded at most this wide
    # (pixels; never upscaled): the 2048-pixel atlas at half size keeps the report small.
    image_width: int = setting(1024, "[64, 8192]")
    # JPEG quality of the embedded images (an image is embedded as PNG instead when that is
    # smaller, e.g. the flat colours of the coverage map).
    jpeg_quality: int = setting(85, "[1, 100]")
    # Vertices of each 3-D view (at most): the surface mesh is subdivided (4x the vertices
    # per step, more colour detail) while it stays within this, or simplified to it; colours
    # are sampled from the atlas at each vertex. Below 65536, face indices take 16 bits.
    model_vertices: int = setting(65000, "[500, 1000000]")
    # The changes table lists at most this many regions (the highest scores; the rest are
    # counted).
    max_table_rows: int = setting(100, ">= 1")
    # Per comparison, at most this many changes (the highest scores) get a card with the
    # crops and frames compare found them back in (findback.csv, findback/).
    max_change_cards: int = setting(20, ">= 0")
    # The summary (the first page of the printed report and of report.pdf) lists at most this
    # many changes: the highest scores of all comparisons (the rest are counted); about 30 rows
    # fit on its A4 page next to five sessions.
    summary_rows: int = setting(20, ">= 1")
    # report.pdf (rule report_pdf: the summary page, then a page per change card) for every
    # subject among the workflow's default targets. It needs headless Chromium (`make browser`
    # installs Debian's); without it the rule fails naming what is missing. Off: a fresh machine's
    # `make run` needs no browser; `snakemake results/{subject}/report.pdf` makes one on request.
    pdf: bool = False
    # The Chromium executable for report.pdf (a name on PATH or a path).
    chromium: str = "chromium"

    def __post_init__(self) -> None:
        validate(self, "report", {"chromium is not empty": bool(self.chromium.strip())})
