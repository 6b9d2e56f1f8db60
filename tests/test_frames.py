"""Tests of the ``frames`` stage on small seeded synthetic videos."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import synthetic_video as sv

from cystomap.camera import Camera
from cystomap.errors import InputError
from cystomap.frames import CSV_COLUMNS, FramesConfig, extract_frames, read_frames_csv
from cystomap.phantom import PhantomConfig, default_camera, generate_session
from cystomap.settings import from_mapping

N = 60
FPS = 25.0
SPEED = 4.0  # px per frame
DEFECTS = {10: "black", 20: "blur", 30: "dup", 40: "white"}
EXPECTED_DROPS = {10: "dark", 20: "blurred", 30: "redundant", 40: "overexposed"}
DIAGONAL = math.hypot(sv.WIDTH, sv.HEIGHT)
EXACT = FramesConfig(min_motion=0.005, lookahead=0)  # keep every frame that moved (>= 1.8 px)


@pytest.fixture(scope="module")
def pan_video(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("video") / "pan.mp4"
    return sv.write_video(path, sv.pan_frames(N, SPEED, replace=DEFECTS), FPS)


def _run(video: Path, out: Path, cfg: FramesConfig) -> list[dict]:
    assert extract_frames(video, out, cfg) == out
    return read_frames_csv(out / "frames.csv")


def test_drops_exactly_the_defective_frames(pan_video: Path, tmp_path: Path) -> None:
    out = tmp_path / "frames"
    rows = _run(pan_video, out, EXACT)
    header = (out / "frames.csv").read_text().splitlines()[0]
    assert header == ",".join(CSV_COLUMNS)
    assert [r["frame"] for r in rows] == list(range(N))
    assert [r["time_s"] for r in rows] == pytest.approx([i / FPS for i in range(N)], abs=1e-3)
    dropped = {r["frame"]: r["reason"] for r in rows if not r["kept"]}
    assert dropped == EXPECTED_DROPS
    assert all(r["reason"] == "kept" for r in rows if r["kept"])
    kept = [r["frame"] for r in rows if r["kept"]]
    assert sorted(p.name for p in out.glob("*.png")) == [f"f{i:06d}.png" for i in kept]

    # exposure figures
    black, white = rows[10], rows[40]
    assert black["dark"] > 0.99 and white["saturated"] > 0.99
    assert max(r["dark"] for r in rows if r["kept"]) < 0.05
    assert max(r["saturated"] for r in rows if r["kept"]) < 0.01
    # the blurred frame is far below its neighbours' sharpness
    assert rows[20]["sharpness"] < 0.4 * np.median([r["sharpness"] for r in rows[15:26]])

    # motion against the last kept frame: the pan speed, twice it after a dropped frame
    for r in rows[1:]:
        if r["frame"] in (10, 40):
            continue
        gap = 2 if r["frame"] - 1 in EXPECTED_DROPS else 1
        if r["frame"] == 30:
            gap = 0  # exact copy of the kept frame 29
        assert r["motion_px"] == pytest.approx(gap * SPEED, abs=0.3), r

    # file names carry the index of the frame in the video: compare pixels with a fresh decode
    decoded = sv.decode_all(pan_video)
    for i in (0, 31, 59):
        assert np.array_equal(cv2.imread(str(out / f"f{i:06d}.png")), decoded[i])

    summary = json.loads((out / "frames.json").read_text())
    assert summary["frames_decoded"] == N and summary["frames_kept"] == N - 4
    assert summary["reasons"]["blurred"] == 1 and summary["fov_share"] == 1.0


def test_default_settings_space_frames(pan_video: Path, tmp_path: Path) -> None:
    cfg = FramesConfig()
    rows = _run(pan_video, tmp_path / "frames", cfg)
    for i, reason in EXPECTED_DROPS.items():
        if reason != "redundant":
            assert rows[i]["reason"] == reason
    kept = [r for r in rows if r["kept"]]
    threshold = cfg.min_motion * DIAGONAL  # 11 px: every third frame at 4 px / frame
    # (the video's last frame is kept once it moved half the spacing: test_last_frame_...)
    assert kept[-1]["frame"] == N - 1 and kept[-1]["motion_px"] >= 0.5 * threshold
    kept = kept[:-1]
    assert all(r["motion_px"] >= threshold for r in kept[1:])
    assert all(rows[i]["reason"] == "redundant" for i in range(N)
               if not rows[i]["kept"] and i not in (10, 20, 40))
    assert 14 <= len(kept) <= 20
    gaps = np.diff([r["frame"] for r in kept])
    assert gaps.min() >= 2 and gaps.max() <= 6  # 3 frames + lookahead 2, +1 after a drop
    # a sharper frame further on never stretches the gap beyond twice min_motion
    assert all(r["motion_px"] <= 2 * threshold for r in kept[1:])


def test_spacing_and_min_gap(pan_video: Path, tmp_path: Path) -> None:
    cfg = FramesConfig(min_motion=0.05, lookahead=0)  # 18.4 px: every 5th frame
    kept = [r for r in _run(pan_video, tmp_path / "a", cfg) if r["kept"]][:-1]  # but the last
    frames = [r["frame"] for r in kept]
    assert all(r["motion_px"] >= 0.05 * DIAGONAL for r in kept[1:])
    assert set(np.diff(frames)) <= {5, 6}  # 6 where a frame of the 5th step was dropped
    assert len(kept) == 12

    cfg = FramesConfig(min_motion=0.0, min_gap=10)
    frames = [r["frame"] for r in _run(pan_video, tmp_path / "b", cfg) if r["kept"]]
    assert frames[0] == 0 and np.diff(frames).min() >= 10
    assert 5 <= len(frames) <= 6


def test_last_frame_is_kept_when_it_moved_on(pan_video: Path, tmp_path: Path) -> None:
    """The video's last frame shows the end of the sweep, which no later frame shows: kept
    when it moved at least half the spacing since the last kept frame (4 px steps, every 5th
    frame kept at 18.4 px: frame 59, 12 px after frame 56); a pause at the end adds that one
    view once, not one frame per paused frame."""
    cfg = FramesConfig(min_motion=0.05, lookahead=0)
    rows = _run(pan_video, tmp_path / "a", cfg)
    kept = [r for r in rows if r["kept"]]
    assert kept[-1]["frame"] == N - 1 and kept[-2]["frame"] == 56  # 5th steps, one shifted
    assert 0.5 * 0.05 * DIAGONAL <= kept[-1]["motion_px"] < 0.05 * DIAGONAL
    frames = sv.pan_frames(N, SPEED)
    paused = sv.write_video(tmp_path / "paused.mp4", frames + [frames[-1]] * 12, FPS)
    rows = _run(paused, tmp_path / "b", cfg)
    kept = [r["frame"] for r in rows if r["kept"]]
    # the pause adds one frame, its last (frame 59's view), however long it is
    assert kept[-1] == N + 11 and kept[-2] == N - 5  # no defects here: every 5th frame
    assert all(r["reason"] == "redundant" for r in rows[N - 4:N + 11])


def test_max_frames_spreads_over_the_video(pan_video: Path, tmp_path: Path) -> None:
    out = tmp_path / "frames"
    rows = _run(pan_video, out, FramesConfig(min_motion=0.005, lookahead=0, max_frames=8))
    kept = [r["frame"] for r in rows if r["kept"]]
    assert 6 <= len(kept) <= 8
    assert kept[0] <= 2 and kept[-1] >= N - 10  # covers the whole video
    assert len(list(out.glob("f*.png"))) == len(kept)
    reasons = {r["frame"]: r["reason"] for r in rows}
    assert {reasons[i] for i in (10, 20, 40)} == {"dark", "blurred", "overexposed"}
    assert sum(r == "over_limit" for r in reasons.values()) >= N - 4 - 8 - 1


def test_time_range(pan_video: Path, tmp_path: Path) -> None:
    cfg = FramesConfig(min_motion=0.005, lookahead=0, start_s=0.4, end_s=1.2)  # frames 10..29
    rows = _run(pan_video, tmp_path / "frames", cfg)
    kept = [r["frame"] for r in rows if r["kept"]]
    assert kept == [i for i in range(11, 30) if i != 20]
    assert all(rows[i]["reason"] == "outside_range" for i in [*range(10), *range(30, N)])


@pytest.mark.parametrize(("gain", "offset"), [(0.5, 10.0), (0.5, 60.0)], ids=["dim", "flat"])
def test_thresholds_follow_the_video(tmp_path: Path, gain: float, offset: float) -> None:
    """Dim or washed-out, low-contrast videos are judged the same way."""
    frames = [np.clip(gain * f.astype(np.float32) + offset, 0, 255).astype(np.uint8)
              for f in sv.pan_frames(N, SPEED, replace={20: "blur", 30: "dup"}, seed=3)]
    video = sv.write_video(tmp_path / "dim.mp4", frames, FPS)
    rows = _run(video, tmp_path / "frames", EXACT)
    assert {r["frame"]: r["reason"] for r in rows if not r["kept"]} == {
        20: "blurred", 30: "redundant"}


def test_circular_field_of_view(tmp_path: Path) -> None:
    circle = (170.0, 85.0, 100.0)  # cut by the top and bottom of the frame
    frames = sv.pan_frames(40, SPEED, circle=circle, replace={5: "black", 15: "blur"}, seed=1)
    video = sv.write_video(tmp_path / "circle.mp4", frames, FPS)
    out = tmp_path / "frames"
    rows = _run(video, out, FramesConfig(min_motion=0.0))
    assert {r["frame"]: r["reason"] for r in rows if not r["kept"]} == {5: "dark", 15: "blurred"}
    # the black border (45% of the frame) is not counted as dark, nor does the static rim
    # hide the motion
    assert max(r["dark"] for r in rows if r["kept"]) < 0.05
    assert np.median([r["motion_px"] for r in rows[1:5]]) == pytest.approx(SPEED, abs=0.3)
    true_share = float(np.count_nonzero(sv.circle_border(
        np.full((sv.HEIGHT, sv.WIDTH), 255, np.uint8), *circle))) / (sv.WIDTH * sv.HEIGHT)
    share = json.loads((out / "frames.json").read_text())["fov_share"]
    assert share == pytest.approx(true_share, abs=0.03)


def test_scope_like_video(tmp_path: Path) -> None:
    """Rotation with tremor, zoom, drift, glints, noise, vignetting, a round FOV, static text
    in the corner and inside the FOV, two defocused frames and a three-frame light dip."""
    frames = sv.scope_frames(N, blurred=(20, 21), dimmed=(40, 41, 42))
    video = sv.write_video(tmp_path / "scope.mp4", frames, FPS)
    out = tmp_path / "frames"
    cfg = FramesConfig()
    rows = _run(video, out, cfg)
    assert {r["frame"]: r["reason"] for r in rows if r["reason"] not in ("kept", "redundant")} \
        == {20: "blurred", 21: "blurred", 40: "dark", 41: "dark", 42: "dark"}
    summary = json.loads((out / "frames.json").read_text())
    assert summary["segments"] == 1  # tracked throughout, even across the light dip
    assert summary["static_share"] > 0  # the static text inside the FOV is ignored
    true_share = float(np.count_nonzero(sv.circle_border(
        np.full((sv.HEIGHT, sv.WIDTH), 255, np.uint8), sv.WIDTH / 2, sv.HEIGHT / 2,
        0.45 * sv.WIDTH))) / (sv.WIDTH * sv.HEIGHT)
    assert summary["fov_share"] == pytest.approx(true_share, abs=0.03)
    kept = [r for r in rows if r["kept"]]
    # the spacing scales with the round FOV's bounding box, not the frame's diagonal
    fov_diagonal = math.hypot(0.9 * sv.WIDTH, min(0.9 * sv.WIDTH, sv.HEIGHT))
    assert summary["thresholds"]["fov_diagonal_px"] == pytest.approx(fov_diagonal, rel=0.05)
    threshold = summary["thresholds"]["min_motion_px"]
    assert threshold == pytest.approx(cfg.min_motion * summary["thresholds"]["fov_diagonal_px"],
                                      abs=0.01)
    assert all(threshold <= r["motion_px"] < 2.5 * threshold for r in kept[1:]
               if r["frame"] != 44)  # the first frame after the dip may have moved further
    assert 8 <= len(kept) <= 16


def test_content_changes_and_jumps_are_not_drops(tmp_path: Path) -> None:
    """Sharpness that falls because the scene has less detail (vessel-rich mucosa giving way to
    a smooth patch, all in focus) is not blur, and a jump too large to track starts a new
    segment instead of losing frames; truly blurred frames go, in rich and in smooth parts."""
    frames = sv.pan_frames(80, SPEED, seed=4, detail=(1.0, 0.05), jumps={40: 90.0},
                           replace={15: "blur", 65: "blur"})
    video = sv.write_video(tmp_path / "vary.mp4", frames, FPS)
    out = tmp_path / "frames"
    cfg = FramesConfig()
    rows = _run(video, out, cfg)
    assert rows[75]["sharpness"] < 0.3 * rows[5]["sharpness"]  # raw sharpness falls 3x+
    assert {r["frame"]: r["reason"] for r in rows if r["reason"] not in ("kept", "redundant")} \
        == {15: "blurred", 65: "blurred"}
    assert rows[40]["kept"] and rows[40]["motion_px"] is None  # first frame after the jump
    assert json.loads((out / "frames.json").read_text())["segments"] == 2
    threshold = cfg.min_motion * DIAGONAL
    kept = [r for r in rows if r["kept"]]
    assert all(r["motion_px"] <= 2 * threshold for r in kept[1:] if r["motion_px"] is not None)
    assert all(r["motion_px"] < 2 * threshold for r in rows if r["reason"] == "redundant")


@pytest.fixture(scope="module")
def phantom_videos(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A clean and a spoiled (defocused and black frames, motion blur) phantom session: sparse
    video (10 fps, the camera turning ~11 deg a frame), small and fast to render."""
    root = tmp_path_factory.mktemp("phantom")
    fast = {"seed": 5, "n_frames": 80, "mesh_edge_mm": 4.0, "cube_face_px": 512,
            "atlas_height": 64, "threads": 1}
    camera = default_camera(256, 144)
    return {
        "clean": generate_session(root / "clean", 1, PhantomConfig(**fast), camera),
        "spoiled": generate_session(root / "spoiled", 1, PhantomConfig(
            **fast, bad_frame_fraction=0.1, motion_blur_px=3.0), camera),
    }


def test_phantom_keeps_every_good_frame(phantom_videos: dict[str, Path], tmp_path: Path) -> None:
    """Nothing of a clean session is called blurred or untracked (its raw sharpness varies
    several-fold with the content and distance; consecutive frames often cannot be tracked),
    and the gaps between kept frames stay within twice min_motion where the video allows."""
    cfg = FramesConfig()
    out = tmp_path / "frames"
    rows = _run(phantom_videos["clean"] / "video.mp4", out, cfg)
    assert {r["reason"] for r in rows} <= {"kept", "redundant"}
    assert sum(r["kept"] for r in rows) >= 0.9 * len(rows)  # the camera moves fast
    sharp = np.array([r["sharpness"] for r in rows])
    assert sharp.max() > 4 * sharp.min()
    threshold = cfg.min_motion * math.hypot(256, 144)
    assert all(r["motion_px"] < 2 * threshold for r in rows if r["reason"] == "redundant")
    last = 0
    for r in rows[1:]:
        if r["kept"]:  # a longer gap only for a single step or a tracking break
            assert r["motion_px"] is None or r["motion_px"] <= 2 * threshold \
                or r["frame"] == last + 1, r
            last = r["frame"]


def test_phantom_drops_exactly_the_bad_frames(phantom_videos: dict[str, Path],
                                              tmp_path: Path) -> None:
    video = phantom_videos["spoiled"]
    truth = json.loads((video / "truth.json").read_text())
    expected = {b["frame"]: "dark" if b["kind"] == "black" else "blurred"
                for b in truth["bad_frames"]}
    assert len(expected) == 8 and set(expected.values()) == {"dark", "blurred"}
    rows = _run(video / "video.mp4", tmp_path / "frames", FramesConfig())
    assert {r["frame"]: r["reason"] for r in rows
            if r["reason"] not in ("kept", "redundant")} == expected


def test_static_camera_keeps_one_frame(tmp_path: Path) -> None:
    frame = sv.texture(sv.HEIGHT, sv.WIDTH, seed=5)
    video = sv.write_video(tmp_path / "static.mp4", [frame] * 30, FPS)
    rows = _run(video, tmp_path / "frames", FramesConfig())
    assert sum(r["kept"] for r in rows) == 1
    assert all(r["reason"] == "redundant" for r in rows if not r["kept"])


# ------------------------------------------------------------------ bad input


def _assert_clean_failure(video: Path, out: Path, match: str, **kwargs: object) -> None:
    with pytest.raises(InputError, match=match) as err:
        extract_frames(video, out, FramesConfig(), **kwargs)  # type: ignore[arg-type]
    assert video.name in str(err.value)
    assert not out.exists()
    assert not [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.")]


def test_missing_video(tmp_path: Path) -> None:
    _assert_clean_failure(tmp_path / "nope.mp4", tmp_path / "frames", "not found")


def test_text_file_is_not_a_video(tmp_path: Path) -> None:
    fake = tmp_path / "notes.mp4"
    fake.write_text("this is not a video\n" * 50)
    _assert_clean_failure(fake, tmp_path / "frames", "video|decodable")


def test_all_black_video_has_no_usable_frame(tmp_path: Path) -> None:
    video = sv.write_video(tmp_path / "black.mp4",
                           [np.zeros((sv.HEIGHT, sv.WIDTH, 3), np.uint8)] * 20, FPS)
    _assert_clean_failure(video, tmp_path / "frames", "no usable frame")


def test_frame_size_must_match_camera(pan_video: Path, tmp_path: Path) -> None:
    camera = Camera.from_fov(640, 360, 75.0, name="scope")
    _assert_clean_failure(pan_video, tmp_path / "frames", "320x180.*640x360", camera=camera)
    ok = Camera.from_fov(sv.WIDTH, sv.HEIGHT, 75.0)
    extract_frames(pan_video, tmp_path / "ok", EXACT, camera=ok)


def test_failure_keeps_earlier_output(tmp_path: Path) -> None:
    out = tmp_path / "frames"
    out.mkdir()
    (out / "frames.csv").write_text("earlier result\n")
    with pytest.raises(InputError):
        extract_frames(tmp_path / "missing.mp4", out)
    assert (out / "frames.csv").read_text() == "earlier result\n"


def test_config_from_mapping() -> None:
    cfg = from_mapping(FramesConfig, {"max_frames": 100, "min_motion": 0.05}, "frames")
    assert cfg.max_frames == 100 and cfg.min_motion == 0.05
    with pytest.raises(InputError, match="fov"):
        from_mapping(FramesConfig, {"fov": "octagon"}, "frames")
    with pytest.raises(InputError, match=r"frames\.max_frames"):
        from_mapping(FramesConfig, {"max_frames": "lots"}, "frames")


class _CountingCapture:
    """A cv2.VideoCapture that counts the frames it decodes."""

    def __init__(self, cap: cv2.VideoCapture, counts: dict[str, int]) -> None:
        self.cap, self.counts = cap, counts

    def read(self) -> tuple[bool, np.ndarray | None]:
        self.counts["decoded"] += 1
        return self.cap.read()

    def grab(self) -> bool:
        self.counts["decoded"] += 1
        return self.cap.grab()

    def get(self, prop: int) -> float:
        return self.cap.get(prop)

    def release(self) -> None:
        self.cap.release()


@pytest.mark.parametrize("write_while_decoding", [True, False])
def test_video_is_decoded_once(pan_video: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                               write_while_decoding: bool) -> None:
    """Writing every frame while decoding (and deleting the dropped ones) or decoding the kept
    ones again: the same PNGs and frames.csv; the first decodes every frame exactly once."""
    import cystomap.frame_decoding as frames

    counts = {"opened": 0, "decoded": 0}
    real_open = frames.open_video

    def counting_open(path: Path):  # type: ignore[no-untyped-def]
        cap, info = real_open(path)
        counts["opened"] += 1
        return _CountingCapture(cap, counts), info

    monkeypatch.setattr(frames, "open_video", counting_open)
    monkeypatch.setattr(frames, "_write_while_decoding", lambda *_: write_while_decoding)
    out = tmp_path / "frames"
    rows = _run(pan_video, out, EXACT)
    kept = [r["frame"] for r in rows if r["kept"]]
    assert len(rows) == N and 0.5 * N < len(kept) < N
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [f"f{i:06d}.png" for i in kept] + ["frames.csv", "frames.json"])  # no stray greys
    timing = json.loads((out / "frames.json").read_text())["timing"]
    if write_while_decoding:
        # one pass: N frames and the read that finds the end
        assert counts == {"opened": 1, "decoded": N + 1}
        assert timing["written_while_decoding"] == N and timing["decoded_again"] == 0
    else:
        # the first frames are written anyway (to measure); the kept ones after them again
        again = [i for i in kept if i > frames._COST_FRAMES]
        assert counts == {"opened": 2, "decoded": N + 1 + again[-1] + 1}
        assert timing["decoded_again"] == len(again)
    reference = tmp_path / "reference"
    monkeypatch.setattr(frames, "_write_while_decoding", lambda *_: not write_while_decoding)
    _run(pan_video, reference, EXACT)
    assert (out / "frames.csv").read_bytes() == (reference / "frames.csv").read_bytes()
    for i in kept:
        name = f"f{i:06d}.png"
        assert (out / name).read_bytes() == (reference / name).read_bytes()


def test_tracker_prepared_ahead_tracks_the_same(pan_video: Path) -> None:
    """The scoring worker prepares each frame's normalised grey and corners ahead of the
    tracking (Tracker.prepare); the chained motion is exactly that of preparing in add()."""
    from cystomap.frame_scoring import _finish_probe, _measure, _new_probe, to_analysis
    from cystomap.frame_tracking import _Tracker

    cfg = FramesConfig()
    cap = cv2.VideoCapture(str(pan_video))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame)
    cap.release()
    probe = _new_probe(pan_video, frames[0], FPS, cfg, None)
    greys = [to_analysis(f, (probe.aw, probe.ah)) for f in frames]
    probe = _finish_probe(pan_video, probe, greys, cfg)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    inline, ahead = _Tracker(probe, cfg), _Tracker(probe, cfg)
    shifts = []
    for grey in greys:
        m = _measure(grey, cfg, probe, kernel)
        seg_a, t_a = inline.add(grey, m.glints, m.usable, m.look)
        prepared = ahead.prepare(grey, m.glints, m.usable and m.look is not None)
        seg_b, t_b = ahead.add(grey, m.glints, m.usable, m.look, prepared)
        assert seg_a == seg_b
        assert np.array_equal(t_a, t_b, equal_nan=True)
        if seg_a == 0:
            shifts.append(t_a[0, 2])
    # it tracked the pan: the first segment spans most frames, moving SPEED px a frame
    # (at analysis size) in one direction
    assert len(shifts) > 0.8 * N  # 58 of 60 measured
    steps = np.abs(np.diff(shifts)) * probe.width / probe.aw
    assert np.median(steps) == pytest.approx(SPEED, rel=0.25)
