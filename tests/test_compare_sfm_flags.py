"""compare names a session whose SfM self-check flagged its model (sfm/quality.json)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest

from cystomap.compare.stage import SessionPaths, sfm_flags, sfm_short
from cystomap.errors import InputError


def _session(root: Path, consistency: dict | None) -> SessionPaths:
    (root / "sfm").mkdir(parents=True)
    if consistency is not None:
        (root / "sfm" / "quality.json").write_text(json.dumps({"consistency": consistency}))
    return SessionPaths(root / "sfm", root / "pre", root / "mesh.ply", root / "atlas")


def test_flagged_session_is_named_with_the_checks_reason(tmp_path, caplog) -> None:
    a = _session(tmp_path / "a", {"consistent": False, "reason": "drift: 3 consecutive frames"})
    b = _session(tmp_path / "b", {"consistent": True})
    with caplog.at_level(logging.WARNING, logger="cystomap.compare.stage"):
        assert sfm_flags(a, b) == {"a": "drift: 3 consecutive frames"}
    assert "session A's SfM model was flagged by its self-check" in caplog.text


def test_unflagged_or_unchecked_sessions_say_nothing(tmp_path) -> None:
    a = _session(tmp_path / "a", None)  # no quality.json: an older or foreign model
    b = _session(tmp_path / "b", {"chain_pairs": 10})  # no verdict recorded
    assert sfm_flags(a, b) == {}


def test_unreadable_quality_json_is_named(tmp_path) -> None:
    a = _session(tmp_path / "a", {"consistent": True})
    (tmp_path / "a" / "sfm" / "quality.json").write_text("{not json")
    with pytest.raises(InputError, match=r"quality\.json"):
        sfm_flags(a, a)


def test_session_whose_model_is_short_of_frames_is_named(tmp_path, caplog) -> None:
    """quality.json's short_model (the SfM stage handed on a model holding fewer than
    retry_registered_share of its frames) is named with its figures; a model without it is not."""
    a = _session(tmp_path / "a", {"consistent": True})
    b = _session(tmp_path / "b", {"consistent": True})
    q = json.loads((tmp_path / "b" / "sfm" / "quality.json").read_text())
    q["short_model"] = {"registered": 66, "frames_with_features": 117, "share": 0.5641,
                        "retry_registered_share": 0.95}
    (tmp_path / "b" / "sfm" / "quality.json").write_text(json.dumps(q))
    with caplog.at_level(logging.WARNING, logger="cystomap.compare.stage"):
        assert sfm_short(a, b) == {
            "b": "its model holds only 66 of the 117 frames with features (56 %)"}
    assert "session B: its model holds only 66" in caplog.text
    assert sfm_short(a, a) == {}
