"""Changes followed through more than two sessions of a subject.

compare measures changes between two sessions; a subject with sessions s1, s2, s3 … has the
consecutive comparisons s1→s2, s2→s3, … A change of s1→s2 sits on s2's wall (s2's model frame,
``changes.csv`` x, y, z); the next comparison's similarity (``registration.json``
``transform_a_to_b``: ``p_B = scale · R p_A + t``) carries it into s3's frame, where it is
the same site as a change of s2→s3 when the two centroids are closer than the larger of the
two radii plus that registration's median residual (one centroid inside the other's disc,
up to the alignment error). Linked changes form a :class:`Track`: per session, the size of
the change measured in the comparison that ends there, or why there is none.

What the comparisons cannot give: a change's size in a session where nothing changed (compare
measures the changed region, not the lesion), and whether a site without a change was seen by
both sessions (that needs the pair's compared area per site); comparisons that skip sessions
(the config's ``comparisons:``) are not followed.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cystomap.report.data import ComparisonSummary

log = logging.getLogger(__name__)

#: Session states in a track (the change's row in ``Point.change`` when measured).
MEASURED, BEFORE, NO_CHANGE, NOT_REGISTERED = "measured", "before", "no change", "not registered"


@dataclass
class Point:
    """A track at one session."""

    session: str
    date: str
    state: str  # MEASURED, BEFORE (not yet found), NO_CHANGE (compared, no change there), NOT_REGISTERED
    change: dict[str, Any] | None = None  # the change's row of changes.csv (MEASURED)
    pair: str = ""  # the comparison ("a → b") that ends at this session

    @property
    def diameter(self) -> float | None:
        v = (self.change or {}).get("diameter_mm")
        return float(v) if isinstance(v, int | float) else None


@dataclass
class Track:
    """One site followed through the sessions (in date order)."""

    number: int
    points: list[Point] = field(default_factory=list)

    @property
    def measured(self) -> list[Point]:
        return [p for p in self.points if p.state == MEASURED]

    @property
    def first(self) -> Point:
        return self.measured[0]


def _xyz(row: dict[str, Any]) -> np.ndarray | None:
    v = [row.get(k) for k in ("x", "y", "z")]
    return np.array(v, float) if all(isinstance(x, float) for x in v) else None


def _transform(c: ComparisonSummary) -> tuple[float, np.ndarray, np.ndarray] | None:
    tf = c.registration.get("transform_a_to_b")
    try:
        return float(tf["scale"]), np.asarray(tf["rotation"], float).reshape(3, 3), \
            np.asarray(tf["translation"], float).reshape(3)
    except (KeyError, TypeError, ValueError):
        return None


def _radius(row: dict[str, Any]) -> float:
    d = row.get("diameter_mm")
    return float(d) / 2 if isinstance(d, float) else 0.0


def consecutive(sessions: Sequence[tuple[str, str]], comparisons: Sequence[ComparisonSummary]
                ) -> list[ComparisonSummary | None]:
    """For sessions [(name, date)] in date order, the comparison of each consecutive pair
    (None when the pair was not compared)."""
    by_pair = {(c.a, c.b): c for c in comparisons}
    return [by_pair.get((a[0], b[0])) for a, b in itertools.pairwise(sessions)]


def follow(sessions: Sequence[tuple[str, str]], comparisons: Sequence[ComparisonSummary]) -> list[Track]:
    """Tracks of every change of the consecutive comparisons (none for two sessions or fewer)."""
    if len(sessions) <= 2:
        return []
    pairs = consecutive(sessions, comparisons)
    chains: list[list[tuple[int, dict[str, Any]]]] = []  # per track: (pair index, change row)
    open_: dict[int, int] = {}  # change index in the previous pair -> chain
    for k, c in enumerate(pairs):
        rows = c.changes if c is not None and c.registered else []
        here: dict[int, int] = {}
        prev = pairs[k - 1] if k else None
        tf = _transform(c) if c is not None and c.registered else None
        residual = c.residual_mm if c is not None and c.residual_mm is not None else 0.0
        taken: set[int] = set()
        if prev is not None and tf is not None and open_:
            scale, rot, t = tf
            pts = [(j, _xyz(r)) for j, r in enumerate(rows)]
            for i, chain_id in open_.items():
                row = prev.changes[i]
                p = _xyz(row)
                if p is None:
                    continue
                q = scale * rot @ p + t
                best = min(((float(np.linalg.norm(q - x)), j) for j, x in pts if x is not None and j not in taken),
                           default=None)
                if best is None:
                    continue
                dist, j = best
                if dist <= max(scale * _radius(row), _radius(rows[j])) + residual:
                    chains[chain_id].append((k, rows[j]))
                    here[j] = chain_id
                    taken.add(j)
        for j, r in enumerate(rows):
            if j not in here:
                here[j] = len(chains)
                chains.append([(k, r)])
        open_ = here
    tracks = []
    for n, chain in enumerate(sorted(chains, key=lambda ch: (ch[0][0], -(ch[0][1].get("score") or 0))), start=1):
        found = dict(chain)
        start = chain[0][0]
        points = [Point(sessions[0][0], sessions[0][1], BEFORE)]
        for k, c in enumerate(pairs):
            name, date = sessions[k + 1]
            label = f"{sessions[k][0]} → {name}"
            if k in found:
                points.append(Point(name, date, MEASURED, found[k], label))
            elif k < start:
                points.append(Point(name, date, BEFORE, None, label))
            elif c is None or not c.registered:
                points.append(Point(name, date, NOT_REGISTERED, None, label))
            else:
                points.append(Point(name, date, NO_CHANGE, None, label))
        tracks.append(Track(n, points))
    log.info("report: %d change(s) of %d consecutive comparison(s) in %d track(s)",
             sum(len(ch) for ch in chains), sum(c is not None for c in pairs), len(tracks))
    return tracks


def track_of(tracks: Sequence[Track], pair: str, row: dict[str, Any]) -> Track | None:
    """The track holding the change ``row`` of comparison ``pair`` ("a → b")."""
    for t in tracks:
        if any(p.pair == pair and p.change is row for p in t.measured):
            return t
    return None
