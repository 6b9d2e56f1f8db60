"""The study report (cystomap.report) on small synthetic stage outputs: fast, no browser."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from cystomap.anatomy import ANATOMY_COLUMNS, REGIONS
from cystomap.atlas.projection import Projection
from cystomap.compare.changes import CHANGE_COLUMNS
from cystomap.errors import InputError
from cystomap.images import imwrite_rgb, sample_bilinear
from cystomap.outputs import write_json
from cystomap.report import ComparisonInputs, ReportConfig, SessionInputs, build_report
from cystomap.report.model3d import Geometry, load_geometry, vertex_colours

ATLAS_W, ATLAS_H = 256, 128
RADIUS = 40.0
ROT = np.radians(10.0)  # each later session's model frame is the one before turned by this about z
SMALL = ReportConfig(image_width=200, model_vertices=3000)


def _atlas_image(seed: int) -> np.ndarray:
    """RGBA: a smooth colourful pattern with vessels-like lines, a block never seen."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:ATLAS_H, 0:ATLAS_W].astype(np.float64)
    r = 170 + 50 * np.sin(xx / 17 + seed)
    g = 110 + 40 * np.cos(yy / 11)
    b = 100 + 30 * np.sin((xx + yy) / 23)
    rgb = np.dstack([r, g, b]) + rng.normal(0, 6, (ATLAS_H, ATLAS_W, 3))
    rgba = np.dstack([np.clip(rgb, 0, 255), np.full((ATLAS_H, ATLAS_W), 255.0)]).astype(np.uint8)
    rgba[100:, 200:] = 0
    return rgba


def write_session(root: Path, name: str, date: str, seed: int, metric: bool = True) -> SessionInputs:
    """The outputs of one session as the stages write them (frames, sfm, mesh, atlas)."""
    import open3d as o3d

    d = root / f"session{seed}"
    for sub in ("frames", "sfm", "mesh", "atlas"):
        (d / sub).mkdir(parents=True, exist_ok=True)
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=RADIUS, resolution=16)
    o3d.io.write_triangle_mesh(str(d / "mesh/surface.ply"), sphere)
    write_json(d / "mesh/mesh.json", {"watertight": True})
    imwrite_rgb(d / "atlas/atlas.png", _atlas_image(seed))
    views = np.tile(np.linspace(0, 25, ATLAS_W).astype(np.uint8), (ATLAS_H, 1))
    imwrite_rgb(d / "atlas/coverage.png", np.dstack([views * 8, views * 4, 255 - views * 8]))
    proj = Projection("equirectangular", ATLAS_W, ATLAS_H)
    # seen share per region: the dome unseen in session 0, half seen later; the neck 80 % seen
    seen = {r: 100.0 for r in REGIONS} | {"dome": 50.0 * min(seed, 1), "trigone/neck": 80.0}
    regions = {r: {"area_mm2": 1000.0, "seen_area_mm2": 10 * v, "seen_percent": v} for r, v in seen.items()}
    anatomy = {"origin": [0.0, 0.0, 0.0], "neck": [0.0, 0.0, -1.0], "anterior": [1.0, 0.0, 0.0], "source": "test"}
    write_json(d / "atlas/atlas.json", {**proj.to_json(), "coverage_percent": 90.0 + seed,
                                        "coverage": {"views_median": 7.0, "coverage_png": {"max_views": 20}},
                                        "frames": {"registered": 45, "contributing": 44},
                                        "anatomy": anatomy, "regions": regions})
    write_json(d / "frames/frames.json", {"frames_decoded": 60, "frames_kept": 50})
    scale = ({"factor": 2.0, "source": "extent_mm", "metric": True, "model_extent": 60.0} if metric
             else {"factor": 1.0, "source": "none", "metric": False})
    write_json(d / "sfm/quality.json", {"frames_in": 50, "registered": 45 - seed, "mean_reprojection_error_px": 0.61,
                                        "points": 1234, "metric": metric, "scale": scale})
    return SessionInputs.from_root(name, date, d)


def write_comparison(root: Path, a: SessionInputs, b: SessionInputs, registered: bool, n_changes: int = 2,
                     glb: bool = True) -> ComparisonInputs:
    """The outputs of the compare stage for A → B (registered or not)."""
    from cystomap.atlas.model import uv_unwrap, write_glb
    from cystomap.mesh import read_mesh

    d = root / "compare" / f"{a.atlas.parent.name}_vs_{b.atlas.parent.name}"
    d.mkdir(parents=True)
    b_index = int(b.atlas.parent.name.removeprefix("session"))  # the change sites turn with B's frame
    reg = {"registered": registered, "reason": "" if registered else "only 4 inlier matches (need 25)",
           "matches": 60, "inliers": 48 if registered else 4, "inlier_ratio": 0.8 if registered else 0.07}
    if registered:  # B's frame is A's turned by 10° about z (the change sites move with it)
        rot = [[np.cos(ROT), -np.sin(ROT), 0.0], [np.sin(ROT), np.cos(ROT), 0.0], [0.0, 0.0, 1.0]]
        reg["transform_a_to_b"] = {"scale": 1.01, "rotation": rot, "translation": [0.0, 0.0, 0.0]}
        reg["residual_mm"] = {"after_spline": {"median": 0.5}}
    write_json(d / "registration.json", reg)
    write_json(d / "compare.json", {"registered": registered, "changes": n_changes if registered else 0})
    atlas_b = _atlas_image(2)
    imwrite_rgb(d / "side_by_side.png", np.hstack([_atlas_image(1)[..., :3], atlas_b[..., :3]]))
    rows = []
    if registered:
        imwrite_rgb(d / "difference.png", np.full((ATLAS_H, ATLAS_W, 3), 128, np.uint8))
        changes = atlas_b[..., :3].copy()
        changes[20:40, 60:80] = (255, 40, 200)
        imwrite_rgb(d / "changes.png", changes)
        if glb:
            import cv2

            verts, faces = read_mesh(b.mesh)
            ok, png = cv2.imencode(".png", changes[..., ::-1])
            assert ok
            write_glb(d / "changes.glb", uv_unwrap(verts, faces, Projection("equirectangular", ATLAS_W, ATLAS_H)),
                      png.tobytes())
        for i in range(n_changes):
            az = np.radians(-30 + 40 * i) + ROT * b_index
            growth = 1.0 + 0.2 * (b_index - 1)  # the sites grow by a fifth per later session
            rows.append({"id": i + 1, "x": RADIUS * np.cos(az), "y": RADIUS * np.sin(az), "z": 5.0,
                         "azimuth_deg": np.degrees(az), "elevation_deg": 7.0, "area_mm2": (80.0 - i) * growth ** 2,
                         "diameter_mm": round((10.1 - i) * growth, 2), "mean_difference": 30.0,
                         "score": 3.0 - i / 10, "region": ("left lateral wall", "posterior wall")[i % 2],
                         "clock": 2.5 + 3 * i, "distance_from_neck_mm": 40.0 + i,
                         "straddles": ("", "left lateral wall")[i % 2]})
    columns = CHANGE_COLUMNS + ANATOMY_COLUMNS + ("straddles",)
    with open(d / "changes.csv", "w") as fh:
        fh.write(",".join(columns) + "\n")
        for r in rows:
            fh.write(",".join(str(r.get(c, "")) for c in columns) + "\n")
    return ComparisonInputs(a.name, b.name, d)


def make_study(root: Path, names: tuple[str, ...] = ("s1", "s2", "s3"), registered: tuple[bool, ...] = (),
               metric: bool = True) -> tuple[list[SessionInputs], list[ComparisonInputs]]:
    sessions = [write_session(root, n, f"2026-0{i + 1}-1{i}", i, metric) for i, n in enumerate(names)]
    registered = registered or (True,) * (len(names) - 1)
    comparisons = [write_comparison(root, a, b, reg) for a, b, reg in zip(sessions[:-1], sessions[1:], registered,
                                                                             strict=True)]
    return sessions, comparisons


def write_findback(c: ComparisonInputs, seed: int = 0) -> None:
    """compare's find-back for changes 1 and 2: crops (change 2 has no frame of A) and frames."""
    from cystomap.compare.findback import FINDBACK_COLUMNS

    d = c.compare
    (d / "findback").mkdir()
    rng = np.random.default_rng(seed)
    for ident in (1, 2):
        for crop in ("atlas_a", "atlas_b", "frame_a", "frame_b"):
            if ident == 2 and crop == "frame_a":
                continue  # no frame of A saw change 2's site
            imwrite_rgb(d / "findback" / f"change{ident}_{crop}.png",
                        rng.integers(0, 255, (64, 64, 3), dtype=np.uint8))
    rows = [(1, "b", 1, 42, 4.2), (1, "b", 2, 80, 8.0), (1, "a", 1, 17, 1.7), (2, "b", 1, 5, 0.5)]
    with open(d / "findback.csv", "w") as fh:
        fh.write(",".join(FINDBACK_COLUMNS) + "\n")
        for ident, key, rank, frame, t in rows:
            r = {"id": ident, "session": key, "rank": rank, "frame": frame, "time_s": t,
                 "image": f"f{frame:06d}.png", "score": 1.0 / rank}
            fh.write(",".join(str(r.get(c, "")) for c in FINDBACK_COLUMNS) + "\n")


def view_data(text: str) -> dict:
    m = re.search(r"<script type='application/json' id='cm-data'>(.*?)</script>", text, re.S)
    assert m, "the 3-D data block is missing"
    return json.loads(m.group(1))


@pytest.fixture(scope="module")
def three_sessions(tmp_path_factory):
    root = tmp_path_factory.mktemp("study3")
    sessions, comparisons = make_study(root, registered=(True, False))
    out = build_report("p<01>", sessions, comparisons, root / "report.html", SMALL)
    return out, out.read_text()


def test_report_is_self_contained(three_sessions):
    out, text = three_sessions
    assert out.name == "report.html" and not list(out.parent.glob(".report*"))  # atomic, no leftovers
    assert not re.search(r"<(script|img|link|iframe)[^>]*\s(src|href)=['\"]?(https?:)?//", text)
    srcs = re.findall(r"<img [^>]*src='([^']*)'", text)
    assert len(srcs) == 3 * 2 + 2 + 1  # atlas + coverage per session; difference + changes; side by side
    assert all(s.startswith(("data:image/jpeg;base64,", "data:image/png;base64,")) for s in srcs)
    assert text.count("<script>") == 3  # image zoom, plotly.js once, the 3-D viewer
    import plotly

    assert text.count(plotly.offline.get_plotlyjs()[:200]) == 1


def test_three_sessions_have_a_timeline_and_every_section(three_sessions):
    _, text = three_sessions
    assert "id='timeline'" in text and "<svg" in text
    for name in ("s1", "s2", "s3"):
        assert f"id='session-{name}'" in text
    assert "id='compare-s1-s2'" in text and "id='compare-s2-s3'" in text
    timeline = text[text.index("id='timeline'"):text.index("</svg>")]
    assert "2 changes" in timeline and "not registered" in timeline and "32 days" in timeline
    assert "known largest extent of the wall, 120 mm (extent_mm)" in text
    assert "45 of 50 (90 %)" in text  # registered frames of s1
    assert "50 of 60 (83 %)" in text  # frames kept


def test_timeline_shows_comparisons_that_skip_sessions(tmp_path):
    sessions, comparisons = make_study(tmp_path, names=("s1", "s2", "s3", "s4"))
    comparisons.append(write_comparison(tmp_path / "extra", sessions[0], sessions[3], True, n_changes=3))
    imwrite_rgb(comparisons[-1].compare / "landmarks.png", np.zeros((ATLAS_H, ATLAS_W, 3), np.uint8))
    text = build_report("p", sessions, comparisons, tmp_path / "r.html", SMALL).read_text()
    timeline = text[text.index("id='timeline'"):text.index("</svg>")]
    assert timeline.count("<path") == 4 and "3 changes" in timeline and "93 days" in timeline
    assert "id='compare-s1-s4'" in text and "Landmarks marked in s1, found back on s4" in text


def test_failed_registration_says_so_and_shows_both_atlases(three_sessions):
    _, text = three_sessions
    section = text[text.index("id='compare-s2-s3'"):]
    section = section[:section.index("</section>")]
    assert "not registered</span>: only 4 inlier matches (need 25)" in section
    assert "could not be co-registered" in section
    assert "Atlases of s2 (left, earlier) and s3 (right, later)" in section
    assert "Difference map" not in section and "class='cm-3d'" not in section
    assert "<table class='data changes'>" not in section


def test_changes_are_tabled_and_marked_in_3d(three_sessions):
    _, text = three_sessions
    section = text[text.index("id='compare-s1-s2'"):]
    section = section[:section.index("</section>")]
    assert "Difference map" in section and "Changes outlined" in section
    table = section[section.index("<table class='data changes'>"):section.index("</table>")]
    assert table.count("<tr>") == 3  # header + 2 changes
    assert "<th>diameter (mm)</th>" in table and "<td>10.1</td>" in table
    data = view_data(text)
    assert set(data["views"]) == {"s0", "s1", "s2", "c0"}
    changes = data["views"]["c0"]
    assert changes["geometry"] == data["views"]["s1"]["geometry"]  # B's mesh, stored once
    assert [m["label"] for m in changes["markers"]] == ["1", "2"]
    assert len(data["geometries"]) == 3


def test_names_are_escaped(tmp_path):
    sessions, comparisons = make_study(tmp_path, names=("a<b>", "c&d"), registered=(False,))
    text = build_report("<script>alert(1)</script>&", sessions, comparisons, tmp_path / "r.html", SMALL).read_text()
    assert "<script>alert(1)" not in text and "&lt;script&gt;alert(1)&lt;/script&gt;&amp;" in text
    assert "a<b>" not in text and "a&lt;b&gt;" in text and "c&amp;d" in text
    assert "id='timeline'" not in text  # two sessions: no timeline
    data = view_data(text)
    assert data["geometries"]["g0"]["session"] == "a<b>"  # JSON, never parsed as HTML


def test_model_units_without_a_metric_scale(tmp_path):
    sessions, comparisons = make_study(tmp_path, names=("a", "b"), metric=False)
    text = build_report("p", sessions, comparisons, tmp_path / "r.html", SMALL).read_text()
    assert "none: no extent_mm or volume_ml, lengths in arbitrary model units" in text
    assert "<th>diameter (units)</th>" in text
    assert view_data(text)["geometries"]["g0"]["units"] == "model units"


def test_changes_view_falls_back_to_changes_png(tmp_path):
    a, b = (write_session(tmp_path, n, "2026-01-01", i) for i, n in enumerate(("a", "b")))
    c = write_comparison(tmp_path, a, b, registered=True, glb=False)
    data = view_data(build_report("p", [a, b], [c], tmp_path / "r.html", SMALL).read_text())
    assert "c0" in data["views"]


def test_a_flagged_sfm_model_is_named_beside_its_comparison(tmp_path):
    """compare.json's sfm_flags (a session's SfM self-check flagged its model) warn in the
    comparison's section and in the summary; an unflagged study says nothing of it."""
    sessions, comparisons = make_study(tmp_path, names=("a", "b"))
    text = build_report("p", sessions, comparisons, tmp_path / "r.html", SMALL).read_text()
    assert "flagged by its self-check" not in text
    path = comparisons[0].compare / "compare.json"
    summary = json.loads(path.read_text())
    summary["sfm_flags"] = {"a": "rotation drift: 10 loop pairs linking f1..f3 to f9..f12"}
    path.write_text(json.dumps(summary))
    text = build_report("p", sessions, comparisons, tmp_path / "r2.html", SMALL).read_text()
    section = text[text.index("id='compare-a-b'"):]
    assert ("a's 3-D model was flagged by its self-check (rotation drift: 10 loop pairs linking "
            "f1..f3 to f9..f12)") in section
    assert "a → b: a's 3-D model was flagged by its self-check" in text
    # a model short of frames (compare.json sfm_short, from quality.json short_model)
    assert "cannot be found" not in text
    summary["sfm_short"] = {"b": "its model holds only 66 of the 117 frames with features (56 %)"}
    path.write_text(json.dumps(summary))
    text = build_report("p", sessions, comparisons, tmp_path / "r3.html", SMALL).read_text()
    section = text[text.index("id='compare-a-b'"):]
    assert ("b: its model holds only 66 of the 117 frames with features (56 %): changes on wall "
            "only the missing frames filmed cannot be found") in section
    assert "a → b: b: its model holds only 66" in text


def test_single_session_without_3d_data_still_reports(tmp_path):
    s = write_session(tmp_path, "only", "2026-01-01", 0)
    (s.atlas / "atlas.json").unlink()
    (s.sfm / "quality.json").write_text("{not json")
    text = build_report("p", [s], [], tmp_path / "r.html", SMALL).read_text()
    assert "id='session-only'" in text and "cm-data" not in text and "Plotly" not in text
    assert "<td>—</td>" in text  # figures it could not read


def test_overexposed_frames_left_out_of_the_atlas_are_reported(tmp_path):
    s = write_session(tmp_path, "only", "2026-01-01", 0)
    meta = json.loads((s.atlas / "atlas.json").read_text())
    meta["frames"] = {"registered": 45, "overexposed": 3, "contributing": 42}
    write_json(s.atlas / "atlas.json", meta)
    text = build_report("p", [s], [], tmp_path / "r.html", SMALL).read_text()
    assert "42; 3 overexposed frames" in text
    plain = build_report("p", [write_session(tmp_path, "b", "2026-01-02", 1)], [],
                         tmp_path / "b.html", SMALL).read_text()
    assert "overexposed frames" not in plain


def test_bad_inputs_are_named(tmp_path):
    s = write_session(tmp_path, "a", "2026-01-01", 0)
    with pytest.raises(InputError, match="no session"):
        build_report("p", [], [], tmp_path / "r.html")
    with pytest.raises(InputError, match="unknown session"):
        build_report("p", [s], [ComparisonInputs("a", "zz", tmp_path)], tmp_path / "r.html")
    (s.atlas / "coverage.png").unlink()
    with pytest.raises(InputError, match=r"coverage\.png not found"):
        build_report("p", [s], [], tmp_path / "r.html")
    assert not (tmp_path / "r.html").exists()
    with pytest.raises(ValueError, match="jpeg_quality"):
        ReportConfig(jpeg_quality=0)


def test_report_is_deterministic(tmp_path):
    sessions, comparisons = make_study(tmp_path, names=("a", "b"))
    first = build_report("p", sessions, comparisons, tmp_path / "1.html", SMALL).read_bytes()
    assert build_report("p", sessions, comparisons, tmp_path / "2.html", SMALL).read_bytes() == first


def test_vertex_colours_follow_the_atlas_projection(tmp_path):
    import open3d as o3d

    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=10.0, resolution=12)
    path = tmp_path / "s.ply"
    o3d.io.write_triangle_mesh(str(path), sphere)
    geo = load_geometry(path, 3000)
    assert 1000 < len(geo.vertices) <= 3000 and geo.faces.max() < len(geo.vertices)  # subdivided
    assert len(load_geometry(path, 600).vertices) <= 700  # simplified
    img = np.zeros((64, 128, 3), np.uint8)
    img[:, :64] = (255, 0, 0)  # azimuth < 0 (y < 0): red
    img[:, 64:] = (0, 0, 255)  # azimuth > 0 (y > 0): blue
    c = vertex_colours(geo, Projection("equirectangular", 1024, 512), img).astype(int)
    y = geo.vertices[:, 1]
    assert (c[y < -2, 0] > 200).all() and (c[y < -2, 2] < 50).all()
    assert (c[y > 2, 2] > 200).all() and (c[y > 2, 0] < 50).all()
    # columns wrap around (azimuth ±180°), rows clamp
    wrap = sample_bilinear(img, np.array([127.5]), np.array([100.0]), wrap_columns=True)
    assert np.rint(wrap[0]).tolist() == [128, 0, 128]


def test_geometry_json_round_trips():
    import base64

    v = np.array([[0, 0, 0], [100, 0, 0], [0, 50, 20.5]], np.float32)
    g = Geometry(v, np.array([[0, 1, 2]], np.uint32)).to_json()
    q = np.frombuffer(base64.b64decode(g["positions"]), "<u2").reshape(-1, 3)
    back = np.array(g["origin"]) + q * np.array(g["step"])
    assert np.abs(back - v).max() < 0.002 and g["index_bits"] == 16
    assert np.frombuffer(base64.b64decode(g["faces"]), "<u2").tolist() == [0, 1, 2]


def test_each_change_has_a_card_with_its_crops_and_frames(tmp_path):
    """compare's find-back (findback.csv, findback/*.png) becomes one card per change: the four
    crops embedded, the frames of each session with their video index and time."""
    sessions, comparisons = make_study(tmp_path, names=("pre", "post"))
    write_findback(comparisons[0])
    text = build_report("p", sessions, comparisons, tmp_path / "r.html", SMALL).read_text()
    section = text[text.index("id='compare-pre-post'"):]
    section = section[:section.index("</section>")]
    assert section.count("<article class='card'") == 2
    card1 = section[section.index("id='change-pre-post-1'"):section.index("id='change-pre-post-2'")]
    card2 = section[section.index("id='change-pre-post-2'"):]
    assert len(re.findall(r"<img [^>]*src='data:image/", card1)) == 4
    assert len(re.findall(r"<img [^>]*src='data:image/", card2)) == 3
    assert "Frames of post that see it best: frame 42 (4.2 s), frame 80 (8.0 s)" in card1
    assert "Frames of pre that saw the same site: frame 17 (1.7 s)" in card1
    assert "Frames of pre that saw the same site: none" in card2
    assert "Before: pre's atlas at the site" in card1 and "post, frame 42 (4.2 s)" in card1
    assert "diameter 10.1 mm" in card1
    capped = build_report("p", sessions, comparisons, tmp_path / "c.html",
                          ReportConfig(image_width=200, model_vertices=3000, max_change_cards=1))
    assert capped.read_text().count("<article class='card'") == 1


def test_summary_lists_coverage_regions_and_changes(three_sessions):
    """The summary for the record: coverage per session and per standard region (the regions
    not fully seen named), each change with its region, clock, distance from the neck and size."""
    _, text = three_sessions
    summary = text[text.index("id='summary'"):]
    summary = summary[:summary.index("</section>")]
    regions = summary[summary.index("<table class='data regions'>"):]
    regions = regions[:regions.index("</table>")]
    assert regions.count("<tr>") == 1 + 2 + len(REGIONS)  # header, frames registered, whole wall, regions
    assert "<td>whole wall seen</td><td>90.0 %</td><td>91.0 %</td><td>92.0 %</td>" in regions
    assert "<td>dome</td><td class='bad'>0 %</td><td class='part'>50 %</td>" in regions
    assert ("Not fully seen: <strong>s1</strong>: trigone/neck (80 % seen), dome (not seen); "
            "<strong>s2</strong>") in summary
    changes = summary[summary.index("<table class='data summary-changes'>"):]
    changes = changes[:changes.index("</table>")]
    assert changes.count("<tr>") == 3  # header + the 2 changes of s1 → s2 (s2 → s3 not registered)
    assert ("<td>s1 → s2</td><td><a href='#change-s1-s2-1'>1</a></td><td>left lateral wall</td><td>2:30</td>"
            "<td>40 mm</td><td>10.1 mm</td><td>80.0 mm²</td>") in changes
    assert "<td>posterior wall (also left lateral wall)</td><td>5:30</td>" in changes  # on a border
    assert "s2 → s3: not co-registered (only 4 inlier matches (need 25)); no change measured." in summary


def test_summary_caps_its_changes_at_the_highest_scores(tmp_path):
    sessions, comparisons = make_study(tmp_path, names=("a", "b"))
    cfg = ReportConfig(image_width=200, model_vertices=500, summary_rows=1)
    text = build_report("p", sessions, comparisons, tmp_path / "r.html", cfg).read_text()
    changes = text[text.index("<table class='data summary-changes'>"):]
    assert changes[:changes.index("</table>")].count("<tr>") == 2  # header + change 1 (score 3.0)
    assert "1 more change with lower scores is in the comparisons' changes.csv." in text


def test_atlas_with_the_region_grid_is_shown_when_present(tmp_path):
    s = write_session(tmp_path, "only", "2026-01-01", 0)
    imwrite_rgb(s.atlas / "regions.png", np.full((ATLAS_H, ATLAS_W, 3), 200, np.uint8))
    text = build_report("p", [s], [], tmp_path / "r.html", SMALL).read_text()
    section = text[text.index("id='session-only'"):]
    assert "alt='atlas with the region grid of session only'" in section
    assert "Atlas with the standard regions (labelled grid)" in section
    assert "<a href='session0/atlas/regions.png'>Full-size file</a>" in section
    assert "<a href='session0/atlas/atlas.png'>Atlas without the grid</a>" in section


def test_changes_are_followed_through_the_sessions(tmp_path):
    """Four sessions, the third pair not registered: each site of s1 → s2 is found again by
    s2 → s3 (only after s2 → s3's alignment, which turns the frame by 10°), and its size
    followed; s3 → s4 says why it cannot be followed."""
    from cystomap.report import followup
    from cystomap.report.data import load_comparison

    sessions, comparisons = make_study(tmp_path, names=("s1", "s2", "s3", "s4"), registered=(True, True, False))
    for c in comparisons[:2]:
        write_findback(c)
    summaries = [load_comparison(c) for c in comparisons]
    tracks = followup.follow([(s.name, s.date) for s in sessions], summaries)
    assert len(tracks) == 2
    t = tracks[0]
    assert [p.state for p in t.points] == ["before", "measured", "measured", "not registered"]
    assert [p.diameter for p in t.points] == [None, 10.1, 12.12, None]
    assert [p.pair for p in t.points] == ["", "s1 → s2", "s2 → s3", "s3 → s4"]
    for s in summaries:  # without the alignment the sites are 7 mm apart: no link
        s.registration.pop("transform_a_to_b", None)
    assert len(followup.follow([(s.name, s.date) for s in sessions], summaries)) == 4
    assert followup.follow([(s.name, s.date) for s in sessions[:2]], summaries[:1]) == []

    text = build_report("p", sessions, comparisons, tmp_path / "r.html", SMALL).read_text()
    section = text[text.index("id='followup'"):]
    section = section[:section.index("</section>")]
    row = section[section.index("<td>1: left lateral wall</td>"):]
    row = row[:row.index("</tr>")]
    assert "change 1</a>, ⌀ 10.1 mm" in row and "change 1</a>, ⌀ 12.1 mm" in row and "not registered" in row
    assert section.count("<svg") == 2
    card = text[text.index("id='change-s2-s3-1'"):]
    card = card[:card.index("</article>")]
    assert "class='sizeplot'" in card and "Site 1 through the sessions" in card and ">12.1</text>" in card
    assert "<th>site</th>" in text  # the summary names each change's site


def test_3d_views_know_their_centre_for_the_inside_view(three_sessions):
    _, text = three_sessions
    data = view_data(text)
    g = data["geometries"]["g0"]
    assert g["centre"] == [0.0, 0.0, 0.0] and g["neck"] == [0.0, 0.0, -1.0] and g["anterior"] == [1.0, 0.0, 0.0]
    for key in data["views"]:
        assert f"<button type='button' class='cm-inside' data-for='{key}' hidden>View from inside</button>" in text


def test_3d_views_draw_the_region_grid(three_sessions):
    """Each session's geometry carries the regions' borders (on the viewed mesh, about the
    anatomical origin) and names, which the viewer draws as a layer with its own button."""
    _, text = three_sessions
    data = view_data(text)
    for g in data["geometries"].values():
        grid = g["regions"]
        assert len(grid["lines"]) == 6
        pts = np.vstack([np.array(line) for line in grid["lines"]])
        r = np.linalg.norm(pts, axis=1)  # origin (0, 0, 0): on the sphere of the mesh
        assert r.max() < RADIUS * 1.001 and r.min() > RADIUS * 0.97
        assert {lab["text"] for lab in grid["labels"]} == set(REGIONS)
    for key in data["views"]:
        assert f"<button type='button' class='cm-regions' data-for='{key}' hidden>Hide regions</button>" in text


def test_pdf_needs_chromium_and_says_so(tmp_path):
    from cystomap.errors import StageError
    from cystomap.report.pdf import pdf_pages, print_pdf

    page = tmp_path / "r.html"
    page.write_text("<p>x</p>")
    with pytest.raises(StageError, match=r"needs headless Chromium, and 'no-such-chromium' \(config report\.chromium\)"
                                         r" is not found: `make browser` installs"):
        print_pdf(page, tmp_path / "r.pdf", "no-such-chromium")
    assert not (tmp_path / "r.pdf").exists()
    pdf = b"%PDF-1.4\n1 0 obj <</Type /Pages /Count 2>>\n2 0 obj <</Type /Page>>\n3 0 obj <</Type/Page>>\n%%EOF\n"
    assert pdf_pages(pdf) == 2
    with pytest.raises(StageError, match="not a complete PDF"):
        pdf_pages(pdf[:-6])


def test_templates_autoescape_and_are_packaged(repo):
    import tomllib

    from cystomap.report import html

    env = html.environment()
    assert env.autoescape is True
    names = {p.name for p in (repo / "cystomap/report/templates").iterdir()}
    assert set(env.list_templates()) == names and {"page.html.j2", "print.css"} <= names
    data = tomllib.loads((repo / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    assert data["cystomap.report"] == ["templates/*"]


def test_sfm_self_check_in_words():
    from cystomap.report.data import consistency_text

    text, weak = consistency_text({"loop_pairs": 119, "loop_pairs_agreeing": 119,
                                   "weakest_seam_share": 1.0, "seams_weak": [], "consistent": True})
    assert "119 of 119 loop-closure pairs" in text and "100 %" in text and not weak
    text, weak = consistency_text({"loop_pairs": 40, "loop_pairs_agreeing": 9,
                                   "weakest_seam_share": 0.8, "seams_weak": [], "consistent": True})
    assert "9 of 40" in text and weak
    # independent halves: drift flagged in words and as weak (cystomap/sfm/drift.py)
    halves = {"checked": True, "consistent": False, "longest_off_run": 6, "residual_max_steps": 3.2}
    text, weak = consistency_text({"loop_pairs": 58, "loop_pairs_agreeing": 58,
                                   "weakest_seam_share": 1.0, "seams_weak": [],
                                   "consistent": False, "halves": halves})
    assert "6 consecutive frames elsewhere (drift)" in text and "3.2 frame steps" in text and weak
    # loop rotations: drift named with its place and size (cystomap/sfm/rotation.py)
    rot = {"checked": True, "flagged": True, "pairs_tested": 55, "worst_deg": 3.45,
           "worst_frames": [["f000002.png", "f000007.png"], ["f000065.png", "f000068.png"]]}
    text, weak = consistency_text({"loop_pairs": 58, "loop_pairs_agreeing": 58,
                                   "weakest_seam_share": 1.0, "seams_weak": [],
                                   "consistent": False, "rotation": rot})
    assert "f000002.png..f000007.png against f000065.png..f000068.png by 3.5°" in text and weak
    text, weak = consistency_text({"loop_pairs": 58, "loop_pairs_agreeing": 58,
                                   "weakest_seam_share": 1.0, "seams_weak": [], "consistent": True,
                                   "rotation": {**rot, "flagged": False}})
    assert "55 loop pairs with parallax show no rotation drift" in text and not weak


def test_sfm_attempts_in_words():
    from cystomap.report.data import attempts_text

    runs = [{"max_image_size": 640, "registered": 47, "flagged": False, "failed": False},
            {"max_image_size": 1280, "registered": 124, "flagged": False, "failed": False}]
    assert attempts_text({"kept": 1, "runs": runs}) == (
        "mapped twice (47 frames at 640 px, then 124 frames at 1280 px); kept the second")
    runs[1] = {**runs[1], "failed": True}
    runs[0] = {**runs[0], "flagged": True}
    assert attempts_text({"kept": 0, "runs": runs}) == (
        "mapped twice (47 frames, flagged at 640 px, then failed at 1280 px); kept the first")
    assert attempts_text({"kept": 0, "runs": runs[:1]}) is None
