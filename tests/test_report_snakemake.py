"""Snakemake's own report (`snakemake --report report.zip`) of the finished phantom study."""

from __future__ import annotations

import collections
import zipfile
from pathlib import PurePosixPath

import pytest

pytestmark = pytest.mark.workflow

CAPTIONS = (
    "Atlas of session <strong>s1</strong> of subject <strong>phantom</strong>",
    "Atlas of session <strong>s2</strong> of subject <strong>phantom</strong>",
    "Coverage map of session <strong>s1</strong>",
    "Difference map of subject <strong>phantom</strong>, session s1 \\u2192 s2",
    "Changes found between sessions s1 and s2 of subject <strong>phantom</strong>",
    "Changes table, sessions s1 \\u2192 s2 of subject <strong>phantom</strong>",
    "Landmarks marked in session s1 of subject <strong>phantom</strong>",
    "Find-back, sessions s1 \\u2192 s2 of subject <strong>phantom</strong>",
    "Study report of subject <strong>phantom</strong>",
    "cystomap turns monocular cystoscopy videos",  # the workflow description
)


def test_snakemake_report_holds_atlases_change_maps_and_tables(phantom_study, tmp_path):
    out = tmp_path / "snakemake_report.zip"
    phantom_study.run("--report", str(out))
    with zipfile.ZipFile(out) as z:
        names = [PurePosixPath(n) for n in z.namelist()]
        index = next(n for n in names if n.name == "report.html" and len(n.parts) == 2)
        main = z.read(str(index)).decode()
    files = collections.Counter(n.name for n in names if "raw" in n.parts)
    assert files["atlas.png"] == 2 and files["coverage.png"] == 2
    assert files["difference.png"] == 1 and files["changes.png"] == 1 and files["changes.csv"] == 1
    assert files["landmarks.png"] == 1 and files["landmarks.csv"] == 1
    assert files["findback.csv"] == 1
    crops = [n for n in files if n.startswith("change") and n.endswith(("_a.png", "_b.png"))]
    assert crops and all(files[n] == 1 for n in crops)  # findback/change{id}_{atlas,frame}_{a,b}.png
    assert files["evaluation.md"] == 1
    assert files["report.html"] == 1  # the study report itself
    assert files["texture.png"] == 0  # only the files named by the patterns
    for caption in CAPTIONS:
        assert caption in main, caption


def test_report_pdf_is_a_default_target_only_when_asked(workflow_factory):
    """report.pdf needs Chromium, so `snakemake` (and `make run`) plans it only with report.pdf: true."""
    from conftest import phantom_config

    wf = workflow_factory(phantom_config())
    jobs = wf.planned_jobs()
    assert jobs["report"] == 1 and "report_pdf" not in jobs
    wf.write_config({**phantom_config(), "report": {"pdf": True}})
    assert wf.planned_jobs()["report_pdf"] == 1  # the explicit target: test_report_browser.py
