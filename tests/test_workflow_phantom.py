"""The default study (the built-in phantom) through Snakemake, at test size (640x360)."""

from __future__ import annotations

import json

import pandas as pd
import pytest
import yaml
from conftest import phantom_config

pytestmark = pytest.mark.workflow

ALL_JOBS = {"phantom_session": 2, "frames": 2, "preprocess": 2, "sfm": 2, "mesh": 2, "atlas": 2, "compare": 1,
            "evaluate": 1, "report": 1, "all": 1}


def test_default_config_plans_the_whole_study(repo, workflow_factory):
    wf = workflow_factory(yaml.safe_load((repo / "config.yaml").read_text()))
    assert wf.planned_jobs() == ALL_JOBS


def test_phantom_study_runs_end_to_end(phantom_study):
    wf, tmp_path = phantom_study, phantom_study.workdir
    for session in ("s1", "s2"):
        truth = json.loads((tmp_path / f"results/phantom/phantom/{session}/truth/truth.json").read_text())
        assert truth["n_frames"] == 124
        table = pd.read_csv(tmp_path / f"results/phantom/{session}/frames/frames.csv")
        assert len(table) == 124, "every rendered frame is decoded"
        assert table["kept"].sum() >= 100, "a clean phantom scan keeps nearly every frame"
        kept = sorted(p.name for p in (tmp_path / f"results/phantom/{session}/frames").glob("f*.png"))
        assert kept == [f"f{i:06d}.png" for i in table.loc[table["kept"], "frame"]]
        mesh = json.loads((tmp_path / f"results/phantom/{session}/mesh/mesh.json").read_text())
        assert mesh["watertight"]
    evaluation = json.loads((tmp_path / "results/phantom/evaluation.json").read_text())
    for session in ("s1", "s2"):
        scores = evaluation["sessions"][session]
        # every frame the frames stage kept is registered (it keeps ~90 % of a clean scan)
        assert scores["registration"]["registered_share"] >= 0.85
        assert scores["reprojection"]["mean_error_px"] < 0.8
        assert scores["trajectory"]["rmse_mm"] < 1.0  # measured 0.24-0.28 mm
        assert abs(scores["trajectory"]["scale_error"]) < 0.05
        assert scores["surface"]["accuracy_mean_mm"] < 0.6
        assert scores["surface"]["completeness"] > 0.95
        assert abs(scores["atlas"]["coverage_error_pp"]) < 3
        assert scores["atlas"]["ssim"] > 0.7
    assert set(evaluation["comparisons"]) == {"s1_vs_s2"}
    lesions = evaluation["comparisons"]["s1_vs_s2"]["lesions"]
    assert lesions["n_matched"] >= 5 and lesions["false_positives"] <= 1  # measured 6/6, 0
    compare = tmp_path / "results/phantom/compare/s1_vs_s2"
    assert json.loads((compare / "registration.json").read_text())["registered"]
    assert list(pd.read_csv(compare / "changes.csv").columns[:4]) == ["id", "x", "y", "z"]
    marks = pd.read_csv(compare / "landmarks.csv")
    assert list(marks["name"]) == ["centre"] and list(marks["status"]) == ["ok"]
    assert (tmp_path / "results/phantom/report.html").stat().st_size > 0
    # every change found back: B's best frame (a frame of the video) and its crops, a card each
    changes, found = pd.read_csv(compare / "changes.csv"), pd.read_csv(compare / "findback.csv")
    best_b = found[(found["session"] == "b") & (found["rank"] == 1)]
    assert sorted(best_b["id"]) == sorted(changes["id"])
    assert all((compare / c).is_file() for c in best_b["crop"])
    assert (best_b["time_s"] - best_b["frame"] / 10.0).abs().max() < 1e-3  # rendered at 10 fps
    report = (tmp_path / "results/phantom/report.html").read_text()
    assert report.count("<article class='card'") == min(len(changes), 20)
    assert wf.planned_jobs() == {}
    try:
        wf.write_config(phantom_config(seed=8))
        assert wf.planned_jobs() == ALL_JOBS
    finally:
        wf.write_config(phantom_config())
