"""The default study (the built-in phantom) through Snakemake, at test size."""

from __future__ import annotations

import json

import pandas as pd
import pytest

pytestmark = pytest.mark.workflow

SMALL_CAMERA = {"width": 320, "height": 180, "fx": 234.966, "fy": 234.966, "cx": 159.5, "cy": 89.5,
                "k1": -0.12, "k2": 0.02}


def phantom_config(**phantom) -> dict:
    return {"cameras": {"phantom_small": SMALL_CAMERA},
            "phantom": {"enabled": True, "camera": "phantom_small", "n_frames": 16, **phantom}}


def test_default_config_plans_the_whole_study(tmp_path, workflow_factory):
    wf = workflow_factory({})
    jobs = wf.planned_jobs()
    assert jobs == {"phantom_session": 2, "frames": 2, "preprocess": 2, "evaluate": 1, "all": 1}


def test_phantom_study_runs_end_to_end(tmp_path, workflow_factory):
    wf = workflow_factory(phantom_config())
    wf.run()
    for session in ("s1", "s2"):
        truth = json.loads((tmp_path / f"results/phantom/phantom/{session}/truth/truth.json").read_text())
        assert truth["n_frames"] == 16
        table = pd.read_csv(tmp_path / f"results/phantom/{session}/frames/frames.csv")
        assert len(table) == 16, "every rendered frame is decoded"
        assert not table.loc[table["kept"], "reason"].ne("kept").any()
        kept = sorted(p.name for p in (tmp_path / f"results/phantom/{session}/frames").glob("f*.png"))
        assert kept == [f"f{i:06d}.png" for i in table.loc[table["kept"], "frame"]]
        assert (tmp_path / f"results/phantom/{session}/preprocessed/camera.json").is_file()
    evaluation = json.loads((tmp_path / "results/phantom/evaluation.json").read_text())
    assert set(evaluation["sessions"]) == {"s1", "s2"}
    assert wf.planned_jobs() == {}
    wf.write_config(phantom_config(seed=8))
    assert wf.planned_jobs() == {"phantom_session": 2, "frames": 2, "preprocess": 2, "evaluate": 1, "all": 1}
