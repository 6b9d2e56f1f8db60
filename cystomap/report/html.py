"""HTML of the study report: one self-contained page rendered from the Jinja2 templates in
``templates/`` (``page.html.j2`` and the sections it includes), autoescaped.

Every string that comes from the study (subject and session names, dates, reasons) is escaped
by the template engine; the templates mark nothing from the study as safe. The page loads
nothing: images are data URIs, the styles and scripts (``report.css``, ``print.css``,
``zoom.js``, ``viewer.js`` next to the templates) are inlined, and the 3-D views are drawn by
plotly.js, inlined once (only when there is a 3-D view), from geometry and colours in a JSON
block (see :mod:`cystomap.report.model3d`). ``print.css`` makes the printed page (and
``report.pdf``, :mod:`cystomap.report.pdf`) the one-page summary followed by a page per change
card.
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass, field
from typing import Any

from jinja2 import Environment, PackageLoader, StrictUndefined
from markupsafe import Markup

from cystomap.anatomy import REGIONS
from cystomap.report.data import ComparisonSummary, SessionSummary
from cystomap.report.followup import Track, track_of
from cystomap.report.media import Embedded
from cystomap.report.plots import size_plot, timeline

VIRIDIS = ("#440154", "#3b528b", "#21918c", "#5ec962", "#fde725")
STATIC = ("report.css", "print.css", "zoom.js", "viewer.js")


def slug(*parts: Any) -> str:
    """An element id from study names (escaped where used; names are [A-Za-z0-9_.-])."""
    return "-".join("".join(c if c.isalnum() or c in "_.-" else "_" for c in str(p)) for p in parts)


def fmt(value: float | int | None, digits: int = 1, unit: str = "") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    text = f"{value:.{digits}f}" if isinstance(value, float) else str(value)
    return f"{text}{unit}"


def fraction(part: int | None, whole: int | None) -> str:
    if part is None or whole is None:
        return "—"
    share = f" ({100 * part / whole:.0f} %)" if whole else ""
    return f"{part} of {whole}{share}"


def clock(hours: Any) -> str:
    """Clock position (hours seen from the neck, 12 = anterior) to the nearest half hour."""
    if not isinstance(hours, int | float) or not math.isfinite(hours):
        return "—"
    half = round(float(hours) * 2) / 2
    h = int(half) % 12 or 12
    return f"{h}:{'30' if half % 1 else '00'}"


def ident(row: dict[str, Any]) -> Any:
    """A change's id as written in changes.csv (read back as a float)."""
    v = row.get("id")
    return int(v) if isinstance(v, float) and v.is_integer() else v


def cell(value: Any, digits: int) -> str:
    """A changes.csv value for a table cell."""
    return fmt(value, digits) if isinstance(value, float | int) or value is None else str(value)


def frame_text(row: dict[str, Any]) -> str:
    """A frame of findback.csv: its index in the video and time, or its image name."""
    frame = row.get("frame")
    label = f"frame {int(frame)}" if isinstance(frame, float) else f"image {row.get('image', '?')}"
    t = row.get("time_s")
    return label + (f" ({fmt(t, 1, ' s')})" if isinstance(t, float) else "")


def json_for_script(data: Any) -> Markup:
    """JSON that is inert inside a <script> element: <, > and & as \\u escapes."""
    text = json.dumps(data, separators=(",", ":"))
    return Markup(text.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026"))


def script_safe(js: str) -> Markup:
    """A script's text must not close its own element."""
    return Markup(js.replace("</script", "<\\/script"))


@dataclass
class SessionPage:
    summary: SessionSummary
    atlas: Embedded
    coverage: Embedded
    coverage_max_views: int | None
    view: str | None  # key of its 3-D view, None when there is none
    atlas_href: str = ""
    coverage_href: str = ""
    regions_href: str = ""  # regions.png (the atlas with the region grid), shown when present


@dataclass
class ChangeCard:
    """One change found back: its row of changes.csv, its crops (atlas_a, atlas_b, frame_a,
    frame_b), the frames that show it (rows of findback.csv by session, best first) and, with
    more than two sessions, the change followed through them."""

    change: dict[str, Any]
    crops: dict[str, Embedded] = field(default_factory=dict)
    frames: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    track: Track | None = None


@dataclass
class ComparisonPage:
    summary: ComparisonSummary
    units: str
    images: dict[str, Embedded] = field(default_factory=dict)  # difference, changes, side_by_side, landmarks
    hrefs: dict[str, str] = field(default_factory=dict)
    view: str | None = None
    max_rows: int = 100
    cards: list[ChangeCard] = field(default_factory=list)


@dataclass(frozen=True)
class Table:
    title: str
    columns: list[str]
    rows: list[list[str]]


@dataclass
class Page:
    subject: str
    sessions: list[SessionPage]
    comparisons: list[ComparisonPage]
    views: dict[str, Any]  # JSON of the 3-D views: {"geometries": ..., "views": ...}
    plotly_js: str  # the plotly.js bundle ("" when there is no 3-D view)
    evaluation: list[Table] = field(default_factory=list)  # phantom scores
    version: str = ""
    tracks: list[Track] = field(default_factory=list)  # changes followed through > 2 sessions
    summary_rows: int = 20  # changes listed on the printed summary (highest scores of all comparisons)


def summary_changes(page: Page) -> tuple[list[tuple[ComparisonPage, dict[str, Any], Track | None]], int]:
    """The changes of the summary: the ``summary_rows`` highest scores over all registered
    comparisons, in comparison order and by score within each; and how many are left out."""
    rows = [(k, i, c, r) for k, c in enumerate(page.comparisons) if c.summary.registered
            for i, r in enumerate(c.summary.changes)]
    top = sorted(rows, key=lambda x: (-(x[3].get("score") or 0.0), x[0], x[1]))[: page.summary_rows]
    top.sort(key=lambda x: (x[0], x[1]))
    listed = [(c, r, track_of(page.tracks, f"{c.summary.a} → {c.summary.b}", r)) for _, _, c, r in top]
    return listed, len(rows) - len(listed)


def unseen_regions(summary: SessionSummary) -> list[tuple[str, float]]:
    """Standard regions of a session whose seen share is below 100 % at the summary's
    precision (whole per cent), with that share."""
    out = []
    for name in REGIONS:
        v = summary.seen(name)
        if v is not None and v < 99.5:
            out.append((name, v))
    return out


def track_units(page: Page, track: Track) -> str:
    """Units of a track's sizes: those of the session where it was first measured."""
    units = {s.summary.name: s.summary.units for s in page.sessions}
    return units.get(track.first.session, "model units")


CHANGE_TABLE = (
    ("id", "id", 0, ""),
    ("diameter_mm", "diameter", 1, "{u}"),
    ("area_mm2", "area", 1, "{u}²"),
    ("relief_mm", "raised", 1, "{u}"),
    ("region", "region", 0, ""),
    ("clock", "clock (from the neck)", 1, ""),
    ("distance_from_neck_mm", "from the neck", 0, "{u}"),
    ("delta_e", "colour change (ΔE)", 1, ""),
    ("observed_share", "seen by both", 2, ""),
    ("score", "score (× threshold)", 2, ""),
)


@functools.cache
def environment() -> Environment:
    env = Environment(loader=PackageLoader("cystomap.report", "templates"), autoescape=True,
                      undefined=StrictUndefined, trim_blocks=True, lstrip_blocks=True, keep_trailing_newline=True)
    env.filters.update(frame_text=frame_text)
    env.globals.update(slug=slug, fmt=fmt, fraction=fraction, clock=clock, ident=ident, cell=cell,
                       frame_text=frame_text, CHANGE_TABLE=CHANGE_TABLE, VIRIDIS=VIRIDIS, REGIONS=REGIONS,
                       timeline=timeline, size_plot=size_plot, summary_changes=summary_changes,
                       unseen_regions=unseen_regions, track_units=track_units)
    return env


def static(name: str) -> str:
    """The text of a style sheet or script next to the templates."""
    loader = environment().loader
    assert loader is not None
    return loader.get_source(environment(), name)[0]


def render(page: Page) -> str:
    assets = {name.replace(".", "_"): script_safe(static(name)) for name in STATIC}
    views = page.views.get("views")
    return environment().get_template("page.html.j2").render(
        page=page, assets=assets,
        plotly_js=script_safe(page.plotly_js) if views else "",
        data=json_for_script(page.views) if views else "")
