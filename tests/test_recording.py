"""Recording-like phantom sessions (issue 16): their timing, and a short one through the
workflow, video to atlas (pause frames dropped, every kept frame registered)."""

from __future__ import annotations

import itertools
import json
import threading
from pathlib import Path

import numpy as np
import pytest

from cystomap.errors import InputError
from cystomap.parallel import prefetch
from cystomap.phantom import PhantomConfig
from cystomap.phantom.recording import PAUSE_S, recording_timing


def test_recording_timing_is_seeded_and_has_pauses_returns_and_bends() -> None:
    fps, n = 30.0, 1800
    share, labels = recording_timing(n, fps, np.random.default_rng(3))
    again, labels2 = recording_timing(n, fps, np.random.default_rng(3))
    assert np.array_equal(share, again) and labels == labels2
    assert share[0] == 0.0 and share.max() == 1.0 and share[-1] > 0.97
    lab = np.array(labels)
    step = np.diff(share)
    assert {"scan", "pause", "bend", "back"} <= set(labels)
    # pauses: still for at least PAUSE_S[0] seconds each
    runs = np.split(np.flatnonzero(lab == "pause"), np.flatnonzero(np.diff(
        np.flatnonzero(lab == "pause")) > 1) + 1)
    assert all(len(r) >= PAUSE_S[0] * fps - 1 for r in runs)
    assert all(np.all(step[r[1:] - 1] == 0) for r in runs)
    # returns go back over the path, bends go forward faster than the scan
    assert np.median(step[lab[1:] == "back"]) < 0
    assert np.median(step[lab[1:] == "bend"]) > 2 * np.median(step[lab[1:] == "scan"])


def test_recording_config() -> None:
    assert PhantomConfig(trajectory="recording", duration_s=60, fps=30).frame_count == 1800
    assert PhantomConfig(trajectory="recording", n_frames=50).frame_count == 50
    assert PhantomConfig(duration_s=60, fps=30).frame_count == 124  # a sweep: n_frames
    with pytest.raises(InputError, match="trajectory"):
        PhantomConfig(trajectory="zigzag")


def test_benchmark_overrides_nest_and_merge(tmp_path: Path) -> None:
    """The recording benchmark's --set/--variants items become nested workflow config keys
    merged over its own config; a malformed item is refused by name."""
    from cystomap.bench.recording import parse_overrides, workflow_config

    got = parse_overrides(["preprocess.scale=0.5", "atlas.width=1024", "sfm.retry=off",
                           "atlas.model=false"])
    assert got == {"preprocess": {"scale": 0.5}, "sfm": {"retry": "off"},
                   "atlas": {"width": 1024, "model": False}}
    cam = dict(width=640, height=360, fx=470.0, fy=470.0, cx=319.5, cy=179.5, k1=-0.1, k2=0.0,
               p1=0.0, p2=0.0, k3=0.0)
    (tmp_path / "camera.json").write_text(json.dumps({**cam, "name": "phantom"}))
    config = workflow_config(tmp_path, parse_overrides(["phantom.seed=8", "cameras.phantom.fx=500"]))
    assert config == {"phantom": {"enabled": False, "seed": 8}, "sessions": "sessions.tsv",
                      "cameras": {"phantom": {**cam, "fx": 500}}}
    with pytest.raises(ValueError, match=r"preprocess\.scale"):
        parse_overrides(["preprocess.scale"])


def test_prefetch_keeps_order_raises_and_stops() -> None:
    assert list(prefetch(iter(range(100)), 4)) == list(range(100))

    def broken():
        yield 1
        raise ValueError("bad frame")

    with pytest.raises(ValueError, match="bad frame"):
        list(prefetch(broken(), 2))
    produced = []

    def endless():
        i = 0
        while True:
            produced.append(i)
            yield i
            i += 1

    before = threading.active_count()
    for i in prefetch(endless(), 3):
        if i == 5:
            break
    assert threading.active_count() == before and len(produced) <= 5 + 3 + 2


# the short recording of the slow test: 40 s at 8 fps (320 frames) at 640x360, lossless (mp4v
# wipes out the fine texture at this size); at 320x180 SfM registers only 103 of 233 frames
SHORT = {"seed": 7, "trajectory": "recording", "duration_s": 40.0, "fps": 8.0,
         "lossless_video": True, "motion_blur_px": 8.0, "atlas_height": 128}
SHORT_SIZE = (640, 360)
# measured on SHORT (2026-12-02): 234 of 320 frames kept (1 of the 37 paused), all 234
# registered in one model, trajectory RMSE 0.087 mm (through Snakemake, 2026-12-05: 234, all
# registered, 0.079 mm)
RMSE_MM = 0.18
COVERAGE_PP = 1.3  # atlas coverage error, measured -0.65 pp (2026-12-05; issue 16's target 2)
# two kept frames are near-identical when their true poses differ by less than this (the
# hand tremor of a pause is 0.05 deg rms; the kept spacing about 3 deg)
SAME_DEG, SAME_MM = 0.5, 0.2


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = (np.trace(a.T @ b) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


@pytest.mark.slow
@pytest.mark.workflow
def test_short_recording_drops_pauses_and_registers(tmp_path: Path) -> None:
    """Through the workflow (Snakemake, video to atlas, as `make bench`'s recording suite runs
    it): the pauses' frames are dropped, every kept frame registers in one model, and the atlas
    covers the wall the video saw."""
    from cystomap.bench.recording import SUBJECT, run_workflow, score
    from cystomap.frames import read_frames_csv
    from cystomap.phantom import default_camera, generate_session

    truth_dir = generate_session(tmp_path / "truth", 1, PhantomConfig(**SHORT),
                                 default_camera(*SHORT_SIZE))
    run_workflow(tmp_path / "run", truth_dir, cores=2)
    results = tmp_path / "run" / "results" / SUBJECT / "s1"
    rows = read_frames_csv(results / "frames" / "frames.csv")
    truth = json.loads((truth_dir / "truth.json").read_text())
    motion = np.array(truth["frames"]["motion"])
    assert len(rows) == len(motion) == 320
    kept = np.array([r["kept"] for r in rows])
    # the frames of each pause go, but one or two at its edges
    pause = np.flatnonzero(motion == "pause")
    runs = np.split(pause, np.flatnonzero(np.diff(pause) > 1) + 1)
    assert len(runs) >= 2
    for r in runs:
        assert np.count_nonzero(kept[r]) <= 2, r
    # no two kept frames in a row are near-identical by their true poses
    rot, cen = _true_poses(truth_dir)
    ids = np.flatnonzero(kept)
    same = [(a, b) for a, b in itertools.pairwise(ids)
            if _angle_deg(rot[a], rot[b]) < SAME_DEG and np.linalg.norm(cen[a] - cen[b]) < SAME_MM]
    assert not same, same
    got = score(tmp_path / "run", truth_dir)
    assert got["frames_kept"] == len(ids)
    assert got["models"] == 1
    assert got["registered"] >= 0.95 * len(ids), (got["registered"], len(ids))
    assert got["rmse_mm"] <= RMSE_MM, got["rmse_mm"]
    assert abs(got["coverage_error_pp"]) <= COVERAGE_PP, got["coverage_error_pp"]


def _true_poses(truth_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """Camera-to-world rotations and centres per video frame from poses.csv."""
    from scipy.spatial.transform import Rotation

    data = np.loadtxt(truth_dir / "poses.csv", delimiter=",", skiprows=1)
    q = data[:, [2, 3, 4, 1]]  # x y z w
    return Rotation.from_quat(q).as_matrix(), data[:, 5:8]
