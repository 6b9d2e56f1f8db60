"""Snakemake end to end in a temporary directory: a user study from a sessions sheet.

Checks the DAG, real outputs, that a finished study has nothing left to do, that a parameter
change re-runs only its stage and what follows, and how bad input is reported.
"""

from __future__ import annotations

import pandas as pd
import pytest
import synthetic_video as sv

pytestmark = pytest.mark.workflow

CAMERA = {"width": sv.WIDTH, "height": sv.HEIGHT, "fx": 230.0, "fy": 230.0,
          "cx": (sv.WIDTH - 1) / 2, "cy": (sv.HEIGHT - 1) / 2, "k1": -0.05}
DEFECTS = {7: "blur", 12: "black", 20: "dup"}
# A flat pan has no 3-D structure to reconstruct: these tests stop after preprocessing.
TARGETS = ("results/p01/a/preprocessed", "results/p01/b/preprocessed")


def study_config(sheet: str = "sessions.tsv", **sections) -> dict:
    return {"sessions": sheet, "cameras": {"scope": CAMERA}, "phantom": {"enabled": False}, **sections}


def write_study(root, sessions=(("p01", "a", 0), ("p01", "b", 1))):
    rows = []
    for subject, session, seed in sessions:
        video = root / "videos" / f"{subject}_{session}.mp4"
        video.parent.mkdir(exist_ok=True)
        sv.write_video(video, sv.pan_frames(30, speed=5.0, seed=seed, replace=DEFECTS), fps=10)
        rows.append({"subject": subject, "session": session, "video": f"videos/{video.name}",
                     "date": f"2026-0{seed + 1}-01", "camera": "scope"})
    pd.DataFrame(rows).to_csv(root / "sessions.tsv", sep="\t", index=False)


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A two-session study run to the end once; tests below work on copies of its state."""
    from conftest import Workflow

    root = tmp_path_factory.mktemp("study")
    write_study(root)
    wf = Workflow(root, study_config())
    wf.run(*TARGETS)
    return wf


def test_outputs_hold_the_right_frames(finished):
    frames_dir = finished.workdir / "results/p01/a/frames"
    table = pd.read_csv(frames_dir / "frames.csv")
    assert len(table) == 30
    reasons = dict(zip(table["frame"], table["reason"], strict=True))
    assert reasons[7] == "blurred" and reasons[12] == "dark" and reasons[20] == "redundant"
    kept = sorted(p.name for p in frames_dir.glob("f*.png"))
    assert kept == [f"f{i:06d}.png" for i in table.loc[table["kept"], "frame"]]
    pre = finished.workdir / "results/p01/a/preprocessed"
    assert sorted(p.name for p in (pre / "enhanced").glob("*.png")) == kept
    assert sorted(p.name for p in (pre / "color").glob("*.png")) == kept
    for stage in ("frames", "preprocess"):
        assert (finished.workdir / f"logs/p01/a/{stage}.log").stat().st_size > 0
        assert (finished.workdir / f"benchmarks/p01/a/{stage}.tsv").is_file()


def test_finished_study_has_nothing_to_do(finished):
    assert finished.planned_jobs(*TARGETS) == {}


def test_changing_a_stage_parameter_reruns_only_that_stage_and_after(finished):
    finished.write_config(study_config(preprocess={"clahe_clip": 3.0}))
    assert finished.planned_jobs(*TARGETS) == {"preprocess": 2}
    finished.write_config(study_config(frames={"min_motion": 0.05}))
    assert finished.planned_jobs(*TARGETS) == {"frames": 2, "preprocess": 2}
    finished.write_config(study_config())
    assert finished.planned_jobs(*TARGETS) == {}
    assert finished.planned_jobs() == {"sfm": 2, "mesh": 2, "atlas": 2, "compare": 1, "report": 1, "all": 1}


def test_snakemake_lint_is_clean(finished):
    proc = finished.run("--lint")
    assert "Congratulations" in proc.stdout + proc.stderr


def test_dag_lists_every_stage(finished):
    proc = finished.run("-n", "--forceall")
    out = proc.stdout + proc.stderr
    for rule in ("frames", "preprocess", "sfm", "mesh", "atlas", "all"):
        assert f"rule {rule}:" in out


@pytest.mark.parametrize(
    ("config", "message"),
    [
        (study_config(frames={"max_frames": "many"}), "'many' is not of type 'integer'"),
        (study_config(frames={"max_frame": 3}), "Additional properties are not allowed ('max_frame'"),
        (study_config(sheet="missing.tsv"), "missing.tsv: file not found"),
        ({**study_config(), "cameras": {"scope": {"width": 320, "height": 180}}}, "cameras"),
        (study_config(comparisons=[{"subject": "p01", "a": "a", "b": "zz"}]),
         "comparisons[0] (p01: a vs zz): b = 'zz' is not a session of subject 'p01'"),
        (study_config(landmarks=[{"subject": "p01", "session": "q", "name": "scar", "col": 3, "row": 4}]),
         "config landmarks[0] (scar): p01/q is not a session"),
        (study_config(landmarks=[{"subject": "p01", "session": "a", "name": "scar", "col": 3}]),
         "landmarks"),
    ],
)
def test_bad_config_fails_before_any_job(tmp_path, workflow_factory, config, message):
    write_study(tmp_path, sessions=(("p01", "a", 0),))
    wf = workflow_factory(config)
    proc = wf.run("-n", check=False)
    assert proc.returncode != 0
    assert message in proc.stdout + proc.stderr
    assert not (tmp_path / "results").exists()


def test_extra_comparisons_from_the_config_are_planned(tmp_path, workflow_factory):
    write_study(tmp_path, sessions=(("p01", "a", 0), ("p01", "b", 1), ("p01", "c", 2)))
    extra = [{"subject": "p01", "a": "a", "b": "c"}, {"subject": "p01", "a": "a", "b": "b"}]
    proc = workflow_factory(study_config(comparisons=extra)).run("-n", check=False)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out
    planned = {f"{a}_vs_{b}" for a in "abc" for b in "abc" if f"compare/{a}_vs_{b}" in out}
    assert planned == {"a_vs_b", "b_vs_c", "a_vs_c"}  # consecutive pairs + the extra one, once


def test_bad_video_fails_with_its_name_and_leaves_other_sessions_alone(tmp_path, workflow_factory):
    write_study(tmp_path, sessions=(("p01", "a", 0),))
    wf = workflow_factory(study_config())
    wf.run("results/p01/a/frames")
    before = sorted(p.name for p in (tmp_path / "results/p01/a/frames").iterdir())
    rows = pd.read_csv(tmp_path / "sessions.tsv", sep="\t")
    extra = rows.iloc[0].copy()
    extra["session"], extra["video"] = "bad", "videos/bad.mp4"
    (tmp_path / "videos/bad.mp4").write_text("this is not a video\n")
    pd.concat([rows, extra.to_frame().T]).to_csv(tmp_path / "sessions.tsv", sep="\t", index=False)
    proc = wf.run("results/p01/a/frames", "results/p01/bad/frames", check=False)
    assert proc.returncode != 0
    log = (tmp_path / "logs/p01/bad/frames.log").read_text()
    assert "videos/bad.mp4" in log and "InputError" in log
    assert not (tmp_path / "results/p01/bad/frames").exists()
    assert sorted(p.name for p in (tmp_path / "results/p01/a/frames").iterdir()) == before


def test_missing_video_is_named(tmp_path, workflow_factory):
    write_study(tmp_path, sessions=(("p01", "a", 0),))
    (tmp_path / "videos/p01_a.mp4").unlink()
    proc = workflow_factory(study_config()).run("-n", check=False)
    assert proc.returncode != 0
    assert "videos/p01_a.mp4" in proc.stdout + proc.stderr
