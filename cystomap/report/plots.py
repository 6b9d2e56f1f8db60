"""Geometry of the report's two small SVG plots; the templates (``timeline.svg.j2``,
``size_plot.svg.j2``) draw them. SVG rather than plotly: they print (``report.pdf``) and
need no script.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from typing import Any

from cystomap.report.data import ComparisonSummary, SessionSummary
from cystomap.report.followup import MEASURED, Track


def _days(a: str, b: str) -> int | None:
    try:
        return (dt.date.fromisoformat(b) - dt.date.fromisoformat(a)).days
    except ValueError:
        return None


def timeline(sessions: Sequence[SessionSummary], comparisons: Sequence[ComparisonSummary]) -> dict[str, Any]:
    """Sessions in date order on a line, each with its coverage and registered frames; above
    it, an arc per comparison with the time elapsed and the changes found (comparisons that
    skip sessions arc higher)."""
    index = {s.name: i for i, s in enumerate(sessions)}
    pairs = [c for c in comparisons if c.a in index and c.b in index]
    spans = [abs(index[c.b] - index[c.a]) for c in pairs]
    rise = 50  # arc height per session spanned; its labels sit under its apex
    step, left = 190, 95
    top = 20 + rise * max(spans, default=1)
    width = left * 2 + step * max(len(sessions) - 1, 0)
    x = {s.name: left + i * step for i, s in enumerate(sessions)}
    dates = {s.name: s.date for s in sessions}
    arcs = []
    for c, span in zip(pairs, spans, strict=True):
        x0, x1 = sorted((x[c.a], x[c.b]))
        apex = top - 8 - rise * span  # a quadratic curve reaches half way to its control point
        n = len(c.changes)
        arcs.append({"x0": x0 + 10, "x1": x1 - 10, "mid": (x0 + x1) / 2, "y": top - 8, "control": 2 * apex - top + 8,
                     "apex": apex, "colour": "#2a7" if c.registered else "#c33",
                     "label": f"{n} change{'s' if n != 1 else ''}" if c.registered else "not registered",
                     "days": _days(dates.get(c.a, ""), dates.get(c.b, ""))})
    nodes = [{"x": x[s.name], "name": s.name, "date": s.date or "date unknown",
              "coverage": s.coverage_percent, "registered": s.registered, "frames_in": s.frames_in}
             for s in sessions]
    return {"width": width, "height": top + 100, "left": left, "top": top, "arcs": arcs, "nodes": nodes}


def size_plot(track: Track, units: str, width: int = 300, height: int = 120) -> dict[str, Any]:
    """A change's diameter at each session of its track: a dot where it was measured, an open
    ring on the axis where the site was compared without a change, nothing before it was found
    or where the pair was not registered."""
    pts = track.points
    values = [p.diameter for p in pts if p.state == MEASURED and p.diameter is not None]
    top = max(values, default=1.0) * 1.15 or 1.0
    left, right, y0, y1 = 42, 12, 14, 30  # margins: plot area from y0 to height - y1
    step = (width - left - right) / max(len(pts) - 1, 1)
    base = height - y1
    scale = (base - y0) / top
    out = []
    for i, p in enumerate(pts):
        d = p.diameter if p.state == MEASURED else None
        out.append({"x": left + i * step, "y": base - d * scale if d is not None else base, "state": p.state,
                    "label": p.session, "value": d})
    line = [(q["x"], q["y"]) for q in out if q["value"] is not None]
    return {"width": width, "height": height, "left": left, "right": width - right, "top": y0, "base": base,
            "max": top, "points": out, "line": " ".join(f"{a:.1f},{b:.1f}" for a, b in line),
            "unit": "mm" if units == "mm" else "units"}
