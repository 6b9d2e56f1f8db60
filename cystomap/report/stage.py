"""Rule ``report``: one self-contained HTML page per subject (``results/{subject}/report.html``).

Per session: the quality figures (frames used and registered, reprojection error, coverage,
source of the scale), the atlas, the coverage map and an interactive 3-D view of the textured
model. Per comparison of consecutive sessions: co-registration, the difference map, the changes
outlined on the atlas and highlighted on the 3-D model, the changes table and a card per change
(before / after crops of both atlases and of the best frame of each session, and the frames
that show it, from compare's find-back); when the sessions
could not be co-registered, the reason and both atlases side by side. A summary for the
patient record (coverage per session and per standard region, each change with its region, clock
and distance from the neck; printed with ``print.css`` as one page, followed by a page per card:
``report.pdf``, :mod:`cystomap.report.pdf`). A timeline when the subject has more than two
sessions, and each change followed through them (:mod:`cystomap.report.followup`); the phantom's
scores when an evaluation is given. Each 3-D view can be flown from the inside.

The page opens offline: images are embedded (downsampled to ``image_width``), the 3-D views
are drawn by plotly.js, inlined once from the ``plotly`` package.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cystomap.anatomy import Anatomy
from cystomap.atlas.model import read_glb
from cystomap.atlas.projection import Projection, SurfaceRays
from cystomap.atlas.regions import region_grid
from cystomap.errors import InputError
from cystomap.outputs import atomic_file
from cystomap.report import followup, html, media, model3d
from cystomap.report.config import ReportConfig
from cystomap.report.data import (
    ComparisonInputs,
    ComparisonSummary,
    SessionInputs,
    SessionSummary,
    load_comparison,
    load_session,
    read_json,
)

log = logging.getLogger(__name__)

UNSEEN_GREY = (96, 96, 96)  # unseen wall in the 3-D views (as texture.png of the atlas stage)


def build_report(
    subject: str,
    sessions: Sequence[SessionInputs],
    comparisons: Sequence[ComparisonInputs],
    out_html: Path,
    cfg: ReportConfig | None = None,
    evaluation: Path | None = None,
) -> Path:
    """Write the study report of ``subject`` to ``out_html`` (atomically) and return its path.

    ``sessions`` in date order; ``comparisons`` name sessions of ``sessions``; ``evaluation``
    is the phantom's ``evaluation.json`` (optional).
    """
    cfg = cfg or ReportConfig()
    out_html = Path(out_html)
    t0 = time.perf_counter()
    if not sessions:
        raise InputError(f"report {subject}: no session")
    names = [s.name for s in sessions]
    if len(set(names)) != len(names):
        raise InputError(f"report {subject}: duplicate session names {names}")
    summaries = {s.name: load_session(s) for s in sessions}
    views: dict[str, Any] = {"geometries": {}, "views": {}}
    geometries: dict[str, model3d.Geometry] = {}
    session_pages = []
    for i, s in enumerate(sessions):
        session_pages.append(_session_page(i, s, summaries[s.name], out_html.parent, cfg, views, geometries))
    comparison_pages = []
    for k, c in enumerate(comparisons):
        missing = [n for n in (c.a, c.b) if n not in summaries]
        if missing:
            raise InputError(f"report {subject}: comparison {c.a} vs {c.b} names unknown session(s) {missing}")
        comparison_pages.append(_comparison_page(k, c, summaries, out_html.parent, cfg, views, geometries))
    tracks = followup.follow([(s.name, s.date) for s in sessions], [c.summary for c in comparison_pages])
    for c in comparison_pages:
        for card in c.cards:
            card.track = followup.track_of(tracks, f"{c.summary.a} → {c.summary.b}", card.change)
    plotly_js = ""
    if views["views"]:
        import plotly.offline

        plotly_js = plotly.offline.get_plotlyjs()
    page = html.Page(subject, session_pages, comparison_pages, views, plotly_js,
                     evaluation_tables(read_json(evaluation)) if evaluation else [], _version(), tracks,
                     cfg.summary_rows)
    text = html.render(page)
    with atomic_file(out_html) as tmp:
        tmp.write_text(text, encoding="utf-8")
    log.info("report: %s, %d session(s), %d comparison(s), %d 3-D view(s), %.1f MB in %.1f s", out_html,
             len(sessions), len(comparisons), len(views["views"]), len(text.encode()) / 1e6,
             time.perf_counter() - t0)
    return out_html


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("cystomap")
    except Exception:  # not installed (plain checkout)
        return ""


def _href(path: Path, base: Path) -> str:
    """``path`` relative to the report's directory (a link to the full-size file)."""
    try:
        return Path(os.path.relpath(Path(path).resolve(), Path(base).resolve())).as_posix()
    except ValueError:  # another drive
        return ""


def _session_page(i: int, s: SessionInputs, summary: SessionSummary, base: Path, cfg: ReportConfig,
                  views: dict[str, Any], geometries: dict[str, model3d.Geometry]) -> html.SessionPage:
    atlas_dir = Path(s.atlas)
    atlas_png, coverage_png = atlas_dir / "atlas.png", atlas_dir / "coverage.png"
    regions_png = atlas_dir / "regions.png"  # the atlas with the region grid (atlases since the anatomy)
    for p in (atlas_png, coverage_png):
        if not p.is_file():
            raise InputError(f"report: session {s.name}: {p} not found")
    atlas_rgba = media.read_rgba(atlas_png)
    if regions_png.is_file():
        atlas_img = media.embed_file(regions_png, cfg.image_width, cfg.jpeg_quality)
    else:
        atlas_img = media.embed_array(media.over(atlas_rgba), cfg.image_width, cfg.jpeg_quality, atlas_png)
    coverage_img = media.embed_file(coverage_png, cfg.image_width, cfg.jpeg_quality)
    meta = read_json(atlas_dir / "atlas.json")
    cov = meta.get("coverage") if isinstance(meta.get("coverage"), dict) else {}
    legend = cov.get("coverage_png") if isinstance(cov.get("coverage_png"), dict) else {}
    max_views = legend.get("max_views") if isinstance(legend.get("max_views"), int) else None
    view_key = None
    proj = _projection(meta, atlas_dir)
    if proj is not None and Path(s.mesh).is_file():
        geometry = model3d.load_geometry(Path(s.mesh), cfg.model_vertices)
        gkey = f"g{i}"
        geometries[gkey] = geometry
        views["geometries"][gkey] = {**geometry.to_json(), "units": summary.units, "session": s.name,
                                     **_inside_camera(meta, proj), **_region_grid(meta, geometry)}
        textured = media.over(atlas_rgba, UNSEEN_GREY)
        view_key = f"s{i}"
        views["views"][view_key] = model3d.View(gkey, model3d.vertex_colours(geometry, proj, textured)).to_json()
    else:
        log.warning("report: session %s: no 3-D view (mesh or atlas.json missing)", s.name)
    return html.SessionPage(summary, atlas_img, coverage_img, max_views, view_key,
                            _href(atlas_png, base), _href(coverage_png, base),
                            _href(regions_png, base) if regions_png.is_file() else "")


def _inside_camera(meta: dict[str, Any], proj: Projection) -> dict[str, list[float]]:
    """Where the 3-D view's camera goes from the inside: the model's centre (the anatomical
    origin, else the atlas barycentre) and, when atlas.json has the anatomical frame, the neck
    and anterior directions (it looks away from the neck, anterior up)."""
    anatomy = meta.get("anatomy") if isinstance(meta.get("anatomy"), dict) else {}
    found = {k: _vector(anatomy.get(k)) for k in ("origin", "neck", "anterior")}
    out = {k: v for k, v in found.items() if v is not None and k != "origin"}
    out["centre"] = found["origin"] or [float(v) for v in proj.barycentre]
    return out


def _region_grid(meta: dict[str, Any], geometry: model3d.Geometry) -> dict[str, Any]:
    """``{"regions": ...}``: the standard regions' borders and names on the viewed mesh
    (:func:`cystomap.atlas.regions.region_grid`) when atlas.json has the anatomical frame."""
    anatomy = meta.get("anatomy")
    if not isinstance(anatomy, dict) or not len(geometry.faces):
        return {}
    try:
        frame = Anatomy.from_json(anatomy)
    except (KeyError, TypeError, ValueError, InputError) as exc:
        log.warning("report: atlas.json's anatomy is not usable (%s); no region grid", exc)
        return {}
    rays = SurfaceRays(geometry.vertices.astype(np.float64), geometry.faces.astype(np.int64),
                       origin=frame.origin)
    return {"regions": region_grid(frame, rays)}


def _vector(value: Any) -> list[float] | None:
    ok = isinstance(value, list) and len(value) == 3 and all(isinstance(x, int | float) for x in value)
    return [float(x) for x in value] if ok else None


def _projection(meta: dict[str, Any], where: Path) -> Projection | None:
    try:
        return Projection.from_json(meta)
    except (KeyError, TypeError, ValueError) as exc:
        log.warning("report: %s/atlas.json has no usable projection (%s)", where, exc)
        return None


def _comparison_page(k: int, c: ComparisonInputs, summaries: dict[str, SessionSummary], base: Path,
                     cfg: ReportConfig, views: dict[str, Any],
                     geometries: dict[str, model3d.Geometry]) -> html.ComparisonPage:
    summary = load_comparison(c)
    b = summaries[c.b]
    page = html.ComparisonPage(summary, b.units, max_rows=cfg.max_table_rows)
    for name in ("difference", "changes", "side_by_side", "landmarks"):
        p = summary.file(f"{name}.png")
        if p is not None:
            page.images[name] = media.embed_file(p, cfg.image_width, cfg.jpeg_quality)
            page.hrefs[name] = _href(p, base)
    if summary.registered and b.inputs is not None:
        page.view = _changes_view(k, summary, b, views, geometries)
    page.cards = _change_cards(summary, cfg)
    return page


CROPS = ("atlas_a", "atlas_b", "frame_a", "frame_b")


def _change_cards(c: ComparisonSummary, cfg: ReportConfig) -> list[html.ChangeCard]:
    """A card per change (highest scores first, at most max_change_cards) that compare
    found back (findback.csv and the crops in findback/)."""
    if not c.findback or not c.registered:
        return []
    cards = []
    for r in c.changes[: cfg.max_change_cards]:
        ident = r.get("id")
        rows = [x for x in c.findback if x.get("id") == ident]
        card = html.ChangeCard(r)
        for key in ("a", "b"):
            mine = [x for x in rows if x.get("session") == key]
            card.frames[key] = sorted(mine, key=lambda x: x.get("rank") or 0)
        name = int(ident) if isinstance(ident, float) else ident
        for crop in CROPS:
            p = c.file(f"findback/change{name}_{crop}.png")
            if p is not None:
                card.crops[crop] = media.embed_file(p, cfg.image_width, cfg.jpeg_quality)
        if card.crops or rows:
            cards.append(card)
    return cards


def _changes_view(k: int, c: ComparisonSummary, b: SessionSummary, views: dict[str, Any],
                  geometries: dict[str, model3d.Geometry]) -> str | None:
    """B's model coloured from the texture of changes.glb (regions tinted and outlined), or
    from changes.png, with a marker at each change."""
    assert b.inputs is not None
    geometry_key = next((g for g, meta in views["geometries"].items() if meta.get("session") == b.name), None)
    if geometry_key is None:
        return None
    meta = read_json(Path(b.inputs.atlas) / "atlas.json")
    proj = _projection(meta, Path(b.inputs.atlas))
    if proj is None:
        return None
    texture = _changes_texture(c)
    if texture is None:
        log.warning("report: %s: no changes.glb or changes.png; no 3-D view of the changes", c.directory)
        return None
    geometry = geometries[geometry_key]
    colours = model3d.vertex_colours(geometry, proj, texture)
    centre = proj.barycentre
    markers = []
    unit = "mm" if b.units == "mm" else "units"
    for r in c.changes:
        xyz = [r.get(a) for a in ("x", "y", "z")]
        if not all(isinstance(v, float) for v in xyz):
            continue
        p = model3d.lifted(np.array(xyz, float), centre)[0]
        ident = int(r["id"]) if isinstance(r.get("id"), float) else r.get("id")
        hover = (f"change {ident}: diameter {html.fmt(r.get('diameter_mm'), 1)} {unit}, "
                 f"score {html.fmt(r.get('score'), 2)}")
        markers.append(model3d.Marker((float(p[0]), float(p[1]), float(p[2])), str(ident), hover))
    key = f"c{k}"
    views["views"][key] = model3d.View(geometry_key, colours, markers).to_json()
    return key


def _changes_texture(c: ComparisonSummary) -> np.ndarray | None:
    import cv2

    glb = c.file("changes.glb")
    if glb is not None:
        try:
            doc, binary = read_glb(glb)
            view = doc["bufferViews"][doc["images"][0]["bufferView"]]
            start = int(view.get("byteOffset", 0))
            png = np.frombuffer(binary[start:start + int(view["byteLength"])], np.uint8)
            bgr = cv2.imdecode(png, cv2.IMREAD_COLOR)
            if bgr is not None:
                return np.ascontiguousarray(bgr[..., ::-1])
        except (ValueError, KeyError, IndexError) as exc:
            log.warning("report: cannot read the texture of %s (%s)", glb, exc)
    png_path = c.file("changes.png")
    return media.read_rgb(png_path) if png_path is not None else None


SESSION_SCORES = (
    ("frames registered", ("registration", "registered_share"), 100, 1, " %"),
    ("trajectory RMSE after Sim(3)", ("trajectory", "rmse_mm"), 1, 2, " mm"),
    ("scale error", ("trajectory", "scale_error"), 100, 1, " %"),
    ("surface mean error", ("surface", "accuracy_mean_mm"), 1, 2, " mm"),
    ("seen wall within the completeness threshold", ("surface", "completeness"), 100, 1, " %"),
    ("atlas coverage", ("atlas", "coverage_percent"), 1, 1, " %"),
    ("truly seen share of the wall", ("atlas", "coverage_percent_true"), 1, 1, " %"),
)
COMPARISON_SCORES = (
    ("lesions found", ("lesions", "n_matched"), 1, 0, ""),
    ("true lesions", ("lesions", "n_true"), 1, 0, ""),
    ("false positives", ("lesions", "false_positives"), 1, 0, ""),
    ("mean localisation error", ("lesions", "localisation_error_mm_mean"), 1, 1, " mm"),
    ("mean size error", ("lesions", "size_error_percent_mean"), 1, 1, " %"),
)


def evaluation_tables(ev: dict[str, Any]) -> list[html.Table]:
    """Headline scores of a phantom subject's evaluation.json: one table for the sessions,
    one for the comparisons (a row per score, a column per session or pair)."""

    def get(block: Any, keys: tuple[str, ...]) -> float | None:
        for key in keys:
            block = block.get(key) if isinstance(block, dict) else None
        return float(block) if isinstance(block, int | float) and not isinstance(block, bool) else None

    tables = []
    for title, group, scores in (("Sessions", ev.get("sessions"), SESSION_SCORES),
                                 ("Comparisons", ev.get("comparisons"), COMPARISON_SCORES)):
        if not isinstance(group, dict) or not group:
            continue
        names = [str(n) for n in group]
        rows = []
        for label, keys, scale, digits, unit in scores:
            values = [get(group[n], keys) for n in group]
            if all(v is None for v in values):
                continue
            rows.append([label, *(html.fmt(None if v is None else v * scale, digits, unit) for v in values)])
        if rows:
            tables.append(html.Table(title, ["score", *names], rows))
    return tables
