"""compare names a session whose SfM self-check flagged its model (sfm/quality.json)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest

from cystomap.compare.stage import SessionPaths, sfm_flags
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
