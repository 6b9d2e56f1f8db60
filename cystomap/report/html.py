"""HTML of the study report: one self-contained page (styles, images, data, script inline).

Every string that comes from the study (subject and session names, dates, reasons) goes
through :func:`esc`. The page loads nothing: images are data URIs, the 3-D views are drawn by
plotly.js, which is inlined once (only when there is a 3-D view), from geometry and colours in
a JSON block (see :mod:`cystomap.report.model3d`).
"""

from __future__ import annotations

import datetime as dt
import html
import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from cystomap.report.data import ComparisonSummary, SessionSummary
from cystomap.report.media import Embedded

VIRIDIS = ("#440154", "#3b528b", "#21918c", "#5ec962", "#fde725")


def esc(value: Any) -> str:
    return html.escape(str(value), quote=True)


def slug(*parts: str) -> str:
    """An element id from study names (escaped where used; names are [A-Za-z0-9_.-])."""
    return "-".join("".join(c if c.isalnum() or c in "_.-" else "_" for c in p) for p in parts)


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


@dataclass
class SessionPage:
    summary: SessionSummary
    atlas: Embedded
    coverage: Embedded
    coverage_max_views: int | None
    view: str | None  # key of its 3-D view, None when there is none
    atlas_href: str = ""
    coverage_href: str = ""


@dataclass
class ChangeCard:
    """One change found back: its row of changes.csv, its crops (atlas_a, atlas_b, frame_a,
    frame_b) and the frames that show it (rows of findback.csv by session, best first)."""

    change: dict[str, Any]
    crops: dict[str, Embedded] = field(default_factory=dict)
    frames: dict[str, list[dict[str, Any]]] = field(default_factory=dict)


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


# --------------------------------------------------------------------------- page


def render(page: Page) -> str:
    n_s, n_c = len(page.sessions), len(page.comparisons)
    nav = [("overview", "Overview")]
    if n_s > 2:
        nav.append(("timeline", "Timeline"))
    nav += [(slug("session", s.summary.name), f"Session {s.summary.name}") for s in page.sessions]
    nav += [(slug("compare", c.summary.a, c.summary.b), f"{c.summary.a} → {c.summary.b}")
            for c in page.comparisons]
    if page.evaluation:
        nav.append(("evaluation", "Evaluation"))
    body = [
        f"<header><h1>Study report: {esc(page.subject)}</h1>",
        f"<p class='lead'>{n_s} session{'s' if n_s != 1 else ''}, {n_c} comparison"
        f"{'s' if n_c != 1 else ''} between them.</p>",
        "<nav>" + " ".join(f"<a href='#{esc(i)}'>{esc(t)}</a>" for i, t in nav) + "</nav></header>",
        "<main>",
        overview(page),
    ]
    if n_s > 2:
        body.append(timeline_section(page.sessions, page.comparisons))
    body += [session_section(s) for s in page.sessions]
    body += [comparison_section(c) for c in page.comparisons]
    if page.evaluation:
        body.append(evaluation_section(page.evaluation))
    body.append("</main>")
    body.append(f"<footer>Written by cystomap {esc(page.version)} from the stage outputs next to this file. "
                "It loads nothing from the network: images, data and the plotly.js viewer are inside it."
                "</footer>")
    scripts = f"<script>{ZOOM_JS}</script>\n"
    if page.views.get("views"):
        data = json_for_script(page.views)
        scripts += (f"<script>{_script_safe(page.plotly_js)}</script>\n"
                   f"<script type='application/json' id='cm-data'>{data}</script>\n"
                   f"<script>{VIEWER_JS}</script>")
    return ("<!DOCTYPE html>\n<html lang='en'>\n<head>\n<meta charset='utf-8'>\n"
            "<meta name='viewport' content='width=device-width, initial-scale=1'>\n"
            f"<title>cystomap report: {esc(page.subject)}</title>\n<style>{CSS}</style>\n</head>\n"
            "<body>\n" + "\n".join(body) + "\n" + scripts + "\n</body>\n</html>\n")


def json_for_script(data: Any) -> str:
    """JSON that is inert inside a <script> element: <, > and & as \\u escapes."""
    text = json.dumps(data, separators=(",", ":"))
    return text.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


def _script_safe(js: str) -> str:
    """A script's text must not close its own element."""
    return js.replace("</script", "<\\/script")


def overview(page: Page) -> str:
    rows = []
    for s in page.sessions:
        m = s.summary
        rows.append(
            "<tr>"
            f"<td><a href='#{esc(slug('session', m.name))}'>{esc(m.name)}</a></td><td>{esc(m.date or '—')}</td>"
            f"<td>{fraction(m.frames_kept, m.frames_decoded)}</td>"
            f"<td>{fraction(m.registered, m.frames_in)}</td>"
            f"<td>{fmt(m.reprojection_px, 2, ' px')}</td>"
            f"<td>{fmt(m.coverage_percent, 1, ' %')}</td>"
            f"<td>{esc(m.scale_source)}</td></tr>")
    out = ["<section id='overview'><h2>Overview</h2>",
           "<table class='data'><thead><tr><th>session</th><th>date</th><th>frames used (of decoded)</th>"
           "<th>frames registered (of used)</th><th>reprojection error</th><th>coverage of the wall</th>"
           "<th>source of the scale</th></tr></thead><tbody>", *rows, "</tbody></table>"]
    if page.comparisons:
        crow = []
        for c in page.comparisons:
            m = c.summary
            status = "registered" if m.registered else f"<span class='bad'>not registered</span>: {esc(m.reason)}"
            changes = str(len(m.changes)) if m.registered else "—"
            crow.append(
                f"<tr><td><a href='#{esc(slug('compare', m.a, m.b))}'>{esc(m.a)} → {esc(m.b)}</a></td>"
                f"<td>{status}</td><td>{fraction(m.inliers, m.matches)}</td><td>{changes}</td></tr>")
        out += ["<table class='data'><thead><tr><th>comparison</th><th>co-registration</th>"
                "<th>inlier matches (of matches)</th><th>changes found</th></tr></thead><tbody>",
                *crow, "</tbody></table>"]
    out.append("</section>")
    return "\n".join(out)


def figure(img: Embedded, alt: str, caption: str, href: str = "") -> str:
    link = f" <a href='{esc(href)}'>Full-size file</a>." if href else ""
    return (f"<figure><img src='{img.uri}' width='{img.width}' height='{img.height}' alt='{esc(alt)}' "
            f"title='click to enlarge'><figcaption>{caption}{link}</figcaption></figure>")


def coverage_legend(max_views: int | None) -> str:
    stops = ", ".join(VIRIDIS)
    top = f"{max_views}+" if max_views else "many"
    return (f"<div class='legend'><span class='swatch' style='background:#000'></span> unseen "
            f"<span class='ramp' style='background:linear-gradient(to right, {stops})'></span> "
            f"1 … {esc(top)} frames</div>")


def session_section(s: SessionPage) -> str:
    m = s.summary
    facts = [
        ("date", esc(m.date or "—")),
        ("frames used", fraction(m.frames_kept, m.frames_decoded) + " decoded frames kept (sharp, exposed, "
         "not redundant)"),
        ("frames registered", fraction(m.registered, m.frames_in) + " frames posed by structure from motion"),
        ("reprojection error", fmt(m.reprojection_px, 2, " px") + " mean over all observations"),
        ("3-D points", fmt(m.points)),
        ("model self-check", (f"<span class='bad'>{esc(m.consistency)}</span>" if m.consistency_weak
                              else esc(m.consistency or "—"))),
        ("coverage", fmt(m.coverage_percent, 1, " %") + " of the wall area seen by at least one frame"
         + (f"; median {fmt(m.views_median, 0)} frames per seen point" if m.views_median is not None else "")),
        ("frames in the atlas", fmt(m.contributing)),
        ("source of the scale", esc(m.scale_source)),
        ("lengths in", esc(m.units)),
    ]
    if m.watertight is not None:
        facts.append(("surface", "closed (watertight)" if m.watertight else "<span class='bad'>not closed</span>"))
    dl = "<dl class='facts'>" + "".join(f"<dt>{k}</dt><dd>{v}</dd>" for k, v in facts) + "</dl>"
    view = ""
    if s.view:
        view = view_block(s.view, f"Textured 3-D model of session {m.name}",
                          "Textured model: drag to rotate, scroll to zoom. Seen from outside, so the inner wall "
                          f"appears mirrored; grey = not seen. Axes in {esc(m.units)}.")
    atlas = figure(s.atlas, f"atlas of session {m.name}",
                   "Atlas: the whole wall unrolled about its centre, neck at the bottom, dome at the top, "
                   "seen from inside as when facing the patient (patient's right on the left; "
                   "column = clock position seen from the neck, 12 = anterior at the edges); "
                   "black = not seen.", s.atlas_href)
    coverage = figure(s.coverage, f"coverage map of session {m.name}",
                      "Coverage: how many frames see each point of the wall. " + coverage_legend(s.coverage_max_views),
                      s.coverage_href)
    return "\n".join([
        f"<section id='{esc(slug('session', m.name))}'><h2>Session {esc(m.name)}</h2>",
        top(dl, view), f"<div class='pair'>{atlas}{coverage}</div>", "</section>"])


def top(facts: str, view: str) -> str:
    """The figures of a section next to its 3-D view (stacked on narrow screens)."""
    return f"<div class='top'><div>{facts}</div>{view}</div>" if view else facts


def view_block(key: str, label: str, caption: str) -> str:
    return (f"<figure class='view'><div class='cm-3d' data-view='{esc(key)}' role='img' aria-label='{esc(label)}'>"
            "<p class='placeholder'>3-D view: loads when scrolled into view.</p></div>"
            f"<figcaption>{caption}</figcaption></figure>")


CHANGE_TABLE = (
    ("id", "id", 0, ""),
    ("diameter_mm", "diameter", 1, "{u}"),
    ("area_mm2", "area", 1, "{u}²"),
    ("region", "region", 0, ""),
    ("clock", "clock (from the neck)", 1, ""),
    ("distance_from_neck_mm", "from the neck", 0, "{u}"),
    ("delta_e", "colour change (ΔE)", 1, ""),
    ("observed_share", "seen by both", 2, ""),
    ("score", "score (× threshold)", 2, ""),
)


def changes_table(c: ComparisonPage) -> str:
    rows = c.summary.changes
    if not rows:
        return "<p class='none'>No change found.</p>"
    unit = "mm" if c.units == "mm" else "units"
    shown = rows[: c.max_rows]
    head = "".join(f"<th>{esc(label)}{esc(' (' + suffix.format(u=unit).strip() + ')') if suffix else ''}</th>"
                   for _, label, _, suffix in CHANGE_TABLE)
    body = []
    for r in shown:
        cells = []
        for key, _, digits, _ in CHANGE_TABLE:
            v = r.get(key)
            if isinstance(v, float) and key == "id":
                v = int(v)
            cells.append(f"<td>{esc(fmt(v, digits) if isinstance(v, float | int) or v is None else v)}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    more = (f"<p>{len(rows) - len(shown)} more regions with lower scores are in changes.csv.</p>"
            if len(rows) > len(shown) else "")
    return (f"<table class='data changes'><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"
            f"{more}")


def _frame_text(row: dict[str, Any]) -> str:
    frame = row.get("frame")
    label = f"frame {int(frame)}" if isinstance(frame, float) else f"image {row.get('image', '?')}"
    t = row.get("time_s")
    return label + (f" ({fmt(t, 1, ' s')})" if isinstance(t, float) else "")


def change_card(card: ChangeCard, a: str, b: str, units: str) -> str:
    """A change's card: before / after crops of the atlases and of the best frames, and the
    frames (video index, time) of each session that show it."""
    r = card.change
    ident = int(r["id"]) if isinstance(r.get("id"), float) else r.get("id")
    unit = "mm" if units == "mm" else "units"
    facts = (f"diameter {fmt(r.get('diameter_mm'), 1, ' ' + unit)}, colour change ΔE "
             f"{fmt(r.get('delta_e'), 1)}, score {fmt(r.get('score'), 2)}")
    best = {k: (rows[0] if rows else None) for k, rows in card.frames.items()}
    captions = {
        "atlas_a": f"Before: {esc(a)}'s atlas at the site",
        "atlas_b": f"After: {esc(b)}'s atlas",
        "frame_a": f"{esc(a)}, " + (esc(_frame_text(best["a"])) if best.get("a") else "best frame"),
        "frame_b": f"{esc(b)}, " + (esc(_frame_text(best["b"])) if best.get("b") else "best frame"),
    }
    figs = "".join(figure(card.crops[k], f"change {ident}: {k.replace('_', ' ')}", captions[k])
                   for k in ("atlas_a", "atlas_b", "frame_a", "frame_b") if k in card.crops)
    lines = []
    for key, name, what in (("b", b, "see it best"), ("a", a, "saw the same site")):
        rows = card.frames.get(key, [])
        listed = ", ".join(esc(_frame_text(x)) for x in rows) if rows else "none"
        lines.append(f"<li>Frames of {esc(name)} that {what}: {listed}</li>")
    return (f"<article class='card' id='{esc(slug('change', a, b, str(ident)))}'>"
            f"<h4>Change {esc(ident)}</h4><p>{esc(facts)}</p><div class='crops'>{figs}</div>"
            f"<ul class='frames'>{''.join(lines)}</ul></article>")


def comparison_section(c: ComparisonPage) -> str:
    m = c.summary
    facts = [("co-registration", "registered" if m.registered
              else f"<span class='bad'>not registered</span>: {esc(m.reason)}"),
             ("inlier matches", fraction(m.inliers, m.matches) + " matched 3-D points of the two sessions")]
    if m.scale is not None:
        facts.append(("scale A → B", fmt(m.scale, 3)))
    if m.residual_mm is not None:
        facts.append(("residual after alignment", fmt(m.residual_mm, 2, f" {c.units}") + " median over the inliers"))
    if m.compared_share is not None:
        facts.append(("wall compared", fmt(100 * m.compared_share, 1, " %") + f" of {esc(m.b)}'s wall seen by both"))
    if m.registered:
        facts.append(("changes found", str(len(m.changes))))
    dl = "<dl class='facts'>" + "".join(f"<dt>{k}</dt><dd>{v}</dd>" for k, v in facts) + "</dl>"
    if not m.registered:
        dl += ("<p class='warn'>The two sessions could not be co-registered, so no change is measured. "
               "Both atlases are shown side by side for comparison by eye.</p>")
    view = ""
    if c.view:
        view = view_block(c.view, f"Changes on the 3-D model of {m.b}",
                          f"Changes highlighted on {esc(m.b)}'s model: tinted magenta, numbered markers (hover one "
                          f"for its size). Axes in {esc(c.units)}.")
    parts = [f"<section id='{esc(slug('compare', m.a, m.b))}'><h2>Comparison {esc(m.a)} → {esc(m.b)}</h2>",
             top(dl, view)]
    img = c.images
    if "side_by_side" in img and not m.registered:
        parts.append(figure(img["side_by_side"], f"atlases of {m.a} and {m.b} side by side",
                            f"Atlases of {esc(m.a)} (left, earlier) and {esc(m.b)} (right, later).",
                            c.hrefs.get("side_by_side", "")))
    maps = []
    if "difference" in img:
        maps.append(figure(img["difference"], f"difference map {m.a} to {m.b}",
                           f"Difference map on {esc(m.b)}'s atlas grid: 50 % grey = no change, colour = "
                           f"{esc(m.b)} − {esc(m.a)} per channel after illumination matching, black = not "
                           "compared (not seen by both sessions).", c.hrefs.get("difference", "")))
    if "changes" in img:
        maps.append(figure(img["changes"], f"changes on the atlas of {m.b}",
                           f"Changes outlined in magenta and numbered on {esc(m.b)}'s atlas.",
                           c.hrefs.get("changes", "")))
    if "landmarks" in img:
        maps.append(figure(img["landmarks"], f"landmarks on the atlas of {m.b}",
                           f"Landmarks marked in {esc(m.a)}, found back on {esc(m.b)}'s atlas (yellow crosses; "
                           "landmarks.csv lists them).", c.hrefs.get("landmarks", "")))
    if maps:
        parts.append(f"<div class='pair'>{''.join(maps)}</div>")
    if m.registered:
        parts += ["<h3>Changes</h3>", changes_table(c)]
    if c.cards:
        more = len(m.changes) - len(c.cards)
        parts += ["<h3>Each change found back in the videos</h3>",
                  f"<p>Per change: the site in {esc(m.a)}'s atlas (before) and {esc(m.b)}'s (after), "
                  f"and the frame of each session that shows it best (the region outlined in magenta); "
                  "frames are numbered by their index in the video (findback.csv lists them).</p>",
                  "<div class='cards'>" + "".join(change_card(k, m.a, m.b, c.units) for k in c.cards)
                  + "</div>"]
        if more > 0:
            parts.append(f"<p>{more} more changes with lower scores are in findback.csv.</p>")
    parts.append("</section>")
    return "\n".join(parts)


def evaluation_section(tables: Sequence[Table]) -> str:
    parts = ["<section id='evaluation'><h2>Evaluation against the phantom's ground truth</h2>"]
    for t in tables:
        head = "".join(f"<th>{esc(c)}</th>" for c in t.columns)
        body = "".join("<tr>" + "".join(f"<td>{esc(v)}</td>" for v in row) + "</tr>" for row in t.rows)
        parts.append(f"<h3>{esc(t.title)}</h3><table class='data scores'><thead><tr>{head}</tr></thead>"
                     f"<tbody>{body}</tbody></table>")
    parts.append("<p>All scores in evaluation.md next to this report.</p></section>")
    return "\n".join(parts)


# --------------------------------------------------------------------------- timeline


def _days(a: str, b: str) -> int | None:
    try:
        return (dt.date.fromisoformat(b) - dt.date.fromisoformat(a)).days
    except ValueError:
        return None


def timeline_svg(sessions: Sequence[SessionSummary], comparisons: Iterable[ComparisonSummary]) -> str:
    """Sessions in date order on a line, each with its coverage and registered frames; above
    it, an arc per comparison with the time elapsed and the changes found (comparisons that
    skip sessions arc higher)."""
    comparisons = list(comparisons)
    index = {s.name: i for i, s in enumerate(sessions)}
    pairs = [c for c in comparisons if c.a in index and c.b in index]
    spans = [abs(index[c.b] - index[c.a]) for c in pairs]
    rise = 50  # arc height per session spanned; its labels sit under its apex
    step, left = 190, 95
    top = 20 + rise * max(spans, default=1)
    width = left * 2 + step * max(len(sessions) - 1, 0)
    height = top + 100
    x = {s.name: left + i * step for i, s in enumerate(sessions)}
    parts = [f"<svg xmlns='http://www.w3.org/2000/svg' class='timeline' width='{width}' height='{height}' "
             f"viewBox='0 0 {width} {height}' role='img' aria-label='timeline of the sessions'>",
             f"<line x1='{left}' y1='{top}' x2='{width - left}' y2='{top}' stroke='#888' stroke-width='2'/>"]
    dates = {s.name: s.date for s in sessions}
    for c, span in zip(pairs, spans, strict=True):
        x0, x1 = sorted((x[c.a], x[c.b]))
        mid = (x0 + x1) / 2
        apex = top - 8 - rise * span  # a quadratic curve reaches half way to its control point
        colour = "#2a7" if c.registered else "#c33"
        parts.append(f"<path d='M{x0 + 10},{top - 8} Q{mid},{2 * apex - top + 8} {x1 - 10},{top - 8}' fill='none' "
                     f"stroke='{colour}' stroke-width='2'/>")
        label = (f"{len(c.changes)} change{'s' if len(c.changes) != 1 else ''}" if c.registered
                 else "not registered")
        days = _days(dates.get(c.a, ""), dates.get(c.b, ""))
        parts.append(f"<text x='{mid}' y='{apex + 17}' text-anchor='middle' class='tl-pair' fill='{colour}'>"
                     f"{esc(label)}</text>")
        if days is not None:
            parts.append(f"<text x='{mid}' y='{apex + 31}' text-anchor='middle' class='tl-small'>{days} days</text>")
    for s in sessions:
        cx = x[s.name]
        parts.append(f"<a href='#{esc(slug('session', s.name))}'><circle cx='{cx}' cy='{top}' r='9' "
                     "fill='#1f5fa8'/></a>")
        lines = [(s.name, "tl-name"), (s.date or "date unknown", "tl-small"),
                 (f"coverage {fmt(s.coverage_percent, 0, ' %')}", "tl-small"),
                 (f"registered {fraction(s.registered, s.frames_in)}", "tl-small")]
        for k, (text, cls) in enumerate(lines):
            parts.append(f"<text x='{cx}' y='{top + 30 + 18 * k}' text-anchor='middle' class='{cls}'>"
                         f"{esc(text)}</text>")
    parts.append("</svg>")
    return "".join(parts)


def timeline_section(sessions: Sequence[SessionPage], comparisons: Sequence[ComparisonPage]) -> str:
    svg = timeline_svg([s.summary for s in sessions], [c.summary for c in comparisons])
    return (f"<section id='timeline'><h2>Timeline</h2><div class='scroll'>{svg}</div>"
            "<p>Sessions in date order with their coverage and registered frames; above the line, each "
            "comparison with the time between its sessions and the changes found.</p></section>")


# --------------------------------------------------------------------------- styles and script

CSS = """
:root { color-scheme: light; }
body { font: 15px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 0; color: #1b1b1b;
  background: #fafafa; }
header { background: #1f3b5a; color: #fff; padding: 18px 28px 10px; }
header h1 { margin: 0 0 4px; font-size: 26px; }
header .lead { margin: 0 0 10px; opacity: .9; }
nav a { color: #cfe3ff; margin-right: 14px; text-decoration: none; white-space: nowrap; }
nav a:hover { text-decoration: underline; }
main { max-width: 1120px; margin: 0 auto; padding: 8px 28px 28px; }
section { background: #fff; border: 1px solid #e2e2e2; border-radius: 6px; padding: 6px 22px 18px;
  margin: 18px 0; }
h2 { font-size: 21px; border-bottom: 1px solid #eee; padding-bottom: 6px; }
table.data { border-collapse: collapse; margin: 10px 0 14px; font-size: 14px; }
table.data th, table.data td { border-bottom: 1px solid #e6e6e6; padding: 5px 10px; text-align: left;
  vertical-align: top; }
table.data thead th { background: #f2f5f8; }
table.changes td, table.scores td + td { text-align: right; font-variant-numeric: tabular-nums; }
dl.facts { display: grid; grid-template-columns: max-content 1fr; gap: 4px 16px; margin: 10px 0 16px; }
dl.facts dt { font-weight: 600; color: #444; }
dl.facts dd { margin: 0; }
figure { margin: 14px 0; }
figure img { max-width: 100%; height: auto; display: block; border: 1px solid #ddd; background: #000; }
figcaption { font-size: 13.5px; color: #444; margin-top: 5px; }
.legend { margin-top: 4px; }
.swatch { display: inline-block; width: 14px; height: 12px; vertical-align: middle; border: 1px solid #999; }
.ramp { display: inline-block; width: 160px; height: 12px; vertical-align: middle; margin-left: 12px; }
.view { margin: 10px 0; }
.view .cm-3d { width: 100%; height: 460px; border: 1px solid #ddd; background: #fff; }
.top { display: grid; grid-template-columns: minmax(280px, 2fr) 3fr; gap: 22px; align-items: start; }
.pair { display: grid; grid-template-columns: 1fr 1fr; gap: 18px; }
@media (max-width: 900px) { .top, .pair { grid-template-columns: 1fr; } }
figure img { cursor: zoom-in; }
.zoom { position: fixed; inset: 0; background: rgba(0, 0, 0, .85); display: flex; align-items: center;
  justify-content: center; z-index: 10; cursor: zoom-out; }
.zoom img { max-width: 96vw; max-height: 94vh; cursor: zoom-out; }
.placeholder { color: #777; padding: 20px; }
.bad { color: #b3261e; font-weight: 600; }
.warn { background: #fff4e5; border-left: 4px solid #e08a00; padding: 8px 12px; }
.none { color: #555; }
.cards { display: grid; grid-template-columns: 1fr; gap: 14px; }
.card { border: 1px solid #e2e2e2; border-radius: 6px; padding: 4px 14px 8px; }
.card h4 { margin: 8px 0 2px; font-size: 16px; }
.card p { margin: 2px 0; }
.crops { display: grid; grid-template-columns: repeat(4, 1fr); gap: 10px; }
.crops figure { margin: 6px 0; }
ul.frames { margin: 4px 0; padding-left: 20px; font-size: 14px; }
@media (max-width: 900px) { .crops { grid-template-columns: 1fr 1fr; } }
.scroll { overflow-x: auto; }
svg.timeline text { font: 13px system-ui, sans-serif; fill: #333; paint-order: stroke; stroke: #fff;
  stroke-width: 4px; stroke-linejoin: round; }
svg.timeline .tl-name { font-weight: 700; font-size: 14px; }
svg.timeline .tl-small { font-size: 12px; fill: #555; }
svg.timeline .tl-pair { font-weight: 600; }
footer { color: #666; font-size: 12.5px; text-align: center; padding: 10px 20px 30px; }
"""

ZOOM_JS = """
document.addEventListener("click", function (e) {
  var open = document.querySelector(".zoom");
  if (open) { open.remove(); return; }
  if (e.target.tagName === "IMG" && e.target.closest("figure")) {
    var box = document.createElement("div"), img = document.createElement("img");
    box.className = "zoom"; img.src = e.target.src; img.alt = e.target.alt;
    box.appendChild(img); document.body.appendChild(box);
  }
});
"""

VIEWER_JS = """
(function () {
  "use strict";
  var MAX_LIVE = 6;
  var data = JSON.parse(document.getElementById("cm-data").textContent);
  var cache = {};
  var live = [];
  function bytes(b64) {
    var s = atob(b64), u = new Uint8Array(s.length);
    for (var i = 0; i < s.length; i++) u[i] = s.charCodeAt(i);
    return u;
  }
  function geometry(key) {
    if (cache[key]) return cache[key];
    var g = data.geometries[key];
    var v = new Uint16Array(bytes(g.positions).buffer), fb = bytes(g.faces).buffer;
    var f = g.index_bits === 16 ? new Uint16Array(fb) : new Uint32Array(fb);
    var out = {x: new Float32Array(g.n), y: new Float32Array(g.n), z: new Float32Array(g.n),
               i: new Uint32Array(g.m), j: new Uint32Array(g.m), k: new Uint32Array(g.m), units: g.units};
    var o = g.origin, s = g.step;
    for (var a = 0; a < g.n; a++) {
      out.x[a] = o[0] + s[0] * v[3 * a]; out.y[a] = o[1] + s[1] * v[3 * a + 1]; out.z[a] = o[2] + s[2] * v[3 * a + 2];
    }
    for (var b = 0; b < g.m; b++) { out.i[b] = f[3 * b]; out.j[b] = f[3 * b + 1]; out.k[b] = f[3 * b + 2]; }
    cache[key] = out;
    return out;
  }
  function axis(title) {
    return {title: {text: title}, showbackground: false, gridcolor: "#e4e4e4", zeroline: false};
  }
  function draw(el) {
    var view = data.views[el.getAttribute("data-view")];
    var g = geometry(view.geometry), c = bytes(view.colours), n = g.x.length;
    var colours = new Array(n);
    for (var a = 0; a < n; a++) colours[a] = "rgb(" + c[3 * a] + "," + c[3 * a + 1] + "," + c[3 * a + 2] + ")";
    var traces = [{type: "mesh3d", x: g.x, y: g.y, z: g.z, i: g.i, j: g.j, k: g.k, vertexcolor: colours,
      hoverinfo: "skip", flatshading: false,
      lighting: {ambient: 0.85, diffuse: 0.35, specular: 0.03, roughness: 0.9, fresnel: 0.05}}];
    if (view.markers.length) {
      traces.push({type: "scatter3d", mode: "markers+text",
        x: view.markers.map(function (m) { return m.x; }), y: view.markers.map(function (m) { return m.y; }),
        z: view.markers.map(function (m) { return m.z; }), text: view.markers.map(function (m) { return m.label; }),
        hovertext: view.markers.map(function (m) { return m.hover; }), hoverinfo: "text", textposition: "top center",
        marker: {size: 6, color: "#ff28c8", line: {color: "#ffffff", width: 2}},
        textfont: {color: "#111111", size: 15}});
    }
    var u = g.units;
    var layout = {margin: {l: 0, r: 0, t: 0, b: 0}, showlegend: false, paper_bgcolor: "#ffffff",
      scene: {aspectmode: "data", xaxis: axis("x (" + u + ")"), yaxis: axis("y (" + u + ")"),
              zaxis: axis("z (" + u + ")"), camera: {eye: {x: 1.2, y: 1.2, z: 0.75}}}};
    el.setAttribute("data-state", "drawing");
    el.innerHTML = "";
    return Plotly.newPlot(el, traces, layout, {displaylogo: false, responsive: true}).then(function () {
      return new Promise(function (done) { requestAnimationFrame(function () { requestAnimationFrame(done); }); });
    }).then(function () {
      el.setAttribute("data-state", "drawn");
      live.push(el);
      while (live.length > MAX_LIVE) {
        var old = null;
        for (var q = 0; q < live.length; q++) { if (!live[q].cmVisible) { old = live[q]; break; } }
        if (!old) break;
        live.splice(live.indexOf(old), 1);
        Plotly.purge(old);
        old.setAttribute("data-state", "idle");
        old.innerHTML = "<p class='placeholder'>3-D view: loads when scrolled into view.</p>";
      }
    });
  }
  function show(el) {
    var state = el.getAttribute("data-state");
    if (state === "drawing" || state === "drawn") return;
    draw(el).catch(function (err) {
      el.setAttribute("data-state", "failed");
      el.textContent = "The 3-D view could not be drawn: " + err;
      console.error("cystomap 3-D view:", err);
    });
  }
  var els = Array.prototype.slice.call(document.querySelectorAll(".cm-3d"));
  if (typeof Plotly === "undefined") {
    els.forEach(function (el) { el.setAttribute("data-state", "failed"); el.textContent = "3-D viewer missing."; });
    throw new Error("cystomap report: plotly.js is missing");
  }
  if (!("IntersectionObserver" in window)) { els.forEach(show); return; }
  var io = new IntersectionObserver(function (entries) {
    entries.forEach(function (e) {
      e.target.cmVisible = e.isIntersecting;
      if (e.isIntersecting) show(e.target);
    });
  }, {rootMargin: "300px 0px"});
  els.forEach(function (el) { el.setAttribute("data-state", "idle"); io.observe(el); });
})();
"""
