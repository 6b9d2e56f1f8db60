"""The anatomical frame, the standard regions and clock positions (cystomap.anatomy).

Units on an ellipsoid; then small phantom sessions (the compare tests' stand-in SfM models
from the true poses, session B in a rotated, shifted, scaled frame of its own, real mesh and
atlas stages) whose frame, regions and the changes' regions are scored against the truth.
"""

from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from test_compare import B_FRAME, CUBE, N_FRAMES, build_session

from cystomap.anatomy import (
    Anatomy,
    AnatomyHint,
    atlas_axes,
    covered_regions,
    estimate,
    locate,
    region_of,
)
from cystomap.atlas.projection import Projection, SurfaceRays
from cystomap.atlas.regions import region_grid
from cystomap.compare import CompareConfig, Landmark, SessionPaths, compare_sessions
from cystomap.compare.registration import Similarity
from cystomap.errors import InputError
from cystomap.evaluate import evaluate_changes, evaluate_session
from cystomap.evaluate.anatomy import border_distance
from cystomap.evaluate.config import EvalConfig
from cystomap.evaluate.session import _align, _load_models
from cystomap.evaluate.truth import load_truth
from cystomap.phantom import PhantomConfig

# a frame that is not the world's: neck along -x+z, anterior along +y+z (orthogonal)
NECK = np.array([-1.0, 0.0, 1.0]) / math.sqrt(2)
ANT = np.array([0.3, 0.9, 0.3]) / np.linalg.norm([0.3, 0.9, 0.3])
ANT = (ANT - (ANT @ NECK) * NECK) / np.linalg.norm(ANT - (ANT @ NECK) * NECK)
FRAME = Anatomy(np.array([5.0, -2.0, 1.0]), NECK, ANT)


def sphere(radius: float = 50.0, centre: np.ndarray = FRAME.origin):
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_sphere(radius, 96)
    return np.asarray(m.vertices) + centre, np.asarray(m.triangles)


def test_clock_and_regions_of_the_cardinal_directions() -> None:
    a, n, left = FRAME.anterior, FRAME.neck, FRAME.left
    pts = FRAME.origin + 40 * np.array([a, left, -a, -left, n, -n,
                                        (a + left) / math.sqrt(2), (n + 2 * left) / math.sqrt(5)])
    hours, polar = FRAME.clock_polar(pts)
    assert hours[:4] == pytest.approx([12, 3, 6, 9])
    assert hours[6] == pytest.approx(1.5)
    assert polar[4] == pytest.approx(0, abs=1e-6) and polar[5] == pytest.approx(180)
    assert list(FRAME.regions(pts)) == ["anterior wall", "left lateral wall", "posterior wall",
                                        "right lateral wall", "trigone/neck", "dome",
                                        "left lateral wall", "left lateral wall"]
    assert list(region_of([11.9, 0.6, 7.49], [44.0, 136.0, 90.0])) == [
        "trigone/neck", "dome", "posterior wall"]


def test_atlas_axes_put_the_neck_at_the_bottom_and_the_left_on_the_right() -> None:
    proj = Projection("equirectangular", 360, 180, FRAME.origin, atlas_axes(FRAME))
    col, row = proj.direction_to_pixel(np.array([FRAME.neck, -FRAME.neck, -FRAME.anterior,
                                                 FRAME.left, -FRAME.left]))
    assert row[0] == pytest.approx(179.5) and row[1] == pytest.approx(-0.5)
    assert col[2] == pytest.approx(179.5)  # posterior wall in the centre
    assert col[3] == pytest.approx(269.5) and col[4] == pytest.approx(89.5)  # left right of it
    # round trip through the JSON contract (a reflection is a valid axes matrix)
    back = Projection.from_json(json.loads(json.dumps(proj.to_json())))
    assert np.allclose(back.pixel_to_direction(10.0, 20.0), proj.pixel_to_direction(10.0, 20.0))


def test_distance_from_the_neck_is_the_arc_on_a_sphere() -> None:
    v, f = sphere()
    rays = SurfaceRays(v, f, origin=FRAME.origin)
    ang = np.radians([10.0, 60.0, 120.0, 175.0])
    perp = FRAME.anterior
    pts = FRAME.origin + 50 * (np.cos(ang)[:, None] * FRAME.neck + np.sin(ang)[:, None] * perp)
    rows = locate(FRAME, pts, rays)
    got = np.array([r["distance_from_neck_mm"] for r in rows])
    assert got == pytest.approx(50 * ang, rel=0.01)
    assert [r["clock"] for r in rows] == [12.0] * 4


def _at(polar_deg: float, hours: float, radius: float = 50.0) -> np.ndarray:
    p, t = math.radians(polar_deg), math.radians(30 * hours)
    side = math.cos(t) * FRAME.anterior + math.sin(t) * FRAME.left
    return FRAME.origin + radius * (math.cos(p) * FRAME.neck + math.sin(p) * side)


def test_a_patch_on_a_border_straddles_it() -> None:
    """Centroid's region first; the other regions its disc covers after it (STRADDLE_RULE).
    On a 50 mm sphere 1 h of clock at the equator is 26 mm of wall, 10 deg of polar 8.7 mm."""
    pts = np.array([_at(90, 3.0), _at(90, 1.6), _at(90, 1.6), _at(50, 6.0), _at(140, 0.2)])
    got = covered_regions(FRAME, pts, [20.0, 5.0, 10.0, 10.0, 4.0])
    assert got == [["left lateral wall"], ["left lateral wall"],
                   ["left lateral wall", "anterior wall"], ["posterior wall", "trigone/neck"],
                   ["dome"]]
    rows = locate(FRAME, pts[:3], diameters=[20.0, 5.0, 10.0])
    assert [r["straddles"] for r in rows] == ["", "", "anterior wall"]
    assert "straddles" not in locate(FRAME, pts[:1])[0]  # the phantom's lesions.csv columns
    # how far from the nearest border, on the wall: 0.1 h at the equator, 5 deg of polar
    assert border_distance(FRAME, pts[[1, 3]]) == pytest.approx(
        [50 * math.radians(3.0), 50 * math.radians(5.0)], rel=1e-3)


def test_region_grid_lies_on_the_borders() -> None:
    v, f = sphere()
    rays = SurfaceRays(v, f, origin=FRAME.origin)
    grid = region_grid(FRAME, rays, step_deg=3.0)
    assert len(grid["lines"]) == 6  # two caps' circles, four meridians
    pts = np.vstack([np.array(line) for line in grid["lines"]])
    assert np.linalg.norm(pts - FRAME.origin, axis=1) == pytest.approx(50.0, rel=0.01)
    hours, polar = FRAME.clock_polar(pts)
    on_cap = np.minimum(np.abs(polar - 45.0), np.abs(polar - 135.0)) < 0.5
    starts = np.array([1.5, 4.5, 7.5, 10.5])
    on_meridian = np.abs((hours[:, None] - starts + 6) % 12 - 6).min(axis=1) < 0.02
    assert (on_cap | on_meridian).all()
    assert on_cap.sum() > 200 and on_meridian.sum() > 100
    names = [lab["text"] for lab in grid["labels"]]
    assert sorted(names) == sorted(["trigone/neck", "posterior wall", "left lateral wall",
                                    "right lateral wall", "anterior wall", "dome"])
    at = np.array([lab["xyz"] for lab in grid["labels"]])
    assert list(FRAME.regions(at)) == names  # each name inside its region


def _entry(roll_deg: float = 0.0, skip: int = 0) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Cameras entering a sphere through the neck along its axis, image up = anterior rotated
    by ``roll_deg`` clockwise (seen from the neck), then turning to look around."""
    from scipy.spatial.transform import Rotation

    up = Rotation.from_rotvec(-FRAME.neck * math.radians(roll_deg)).apply(FRAME.anterior)
    rots, cens = [], []
    for k in range(40):
        c = FRAME.origin + FRAME.neck * (60.0 - 4.0 * min(k, 10))
        view = -FRAME.neck if k < 10 else Rotation.from_rotvec(
            FRAME.left * math.radians(9.0 * (k - 9))).apply(-FRAME.neck)
        u = up - (up @ view) * view
        u /= np.linalg.norm(u)
        rots.append(np.stack([np.cross(-u, view), -u, view], axis=1))  # x = y × z
        cens.append(c)
    names = [f"f{k:06d}" for k in range(40)]
    return names[skip:], np.array(rots)[skip:], np.array(cens)[skip:]


def test_estimate_from_the_entry_and_the_overrides() -> None:
    v, f = sphere()
    rays = SurfaceRays(v, f, origin=FRAME.origin)
    est = estimate(*_entry(), FRAME.origin, rays)
    assert est.neck @ FRAME.neck > math.cos(math.radians(0.5))
    assert est.anterior @ FRAME.anterior > math.cos(math.radians(0.5))
    assert "entry" in est.source and "still in the urethra" in est.source
    # a recording that starts inside the wall: the entry path followed back to it
    inside = estimate(*_entry(skip=3), FRAME.origin, rays)
    assert inside.neck @ FRAME.neck > math.cos(math.radians(0.5))
    assert "path followed back" in inside.source
    # the scope entered rolled by 90 deg (image up = patient's left): given, it is undone
    rolled = estimate(*_entry(90.0), FRAME.origin, rays)
    assert rolled.anterior @ FRAME.left > 0.99
    fixed = estimate(*_entry(90.0), FRAME.origin, rays, AnatomyHint(entry_roll_deg=90.0))
    assert fixed.anterior @ FRAME.anterior > 0.999
    # a recording without the entry: neck and anterior points given
    p_neck = tuple(FRAME.origin + 50 * FRAME.neck)
    p_ant = tuple(FRAME.origin + 30 * FRAME.anterior + 10 * FRAME.neck)
    given = estimate(*_entry(skip=20), FRAME.origin, rays,
                     AnatomyHint.from_mapping({"neck_xyz": " ".join(map(str, p_neck)),
                                               "anterior_xyz": list(p_ant)}))
    assert given.neck @ FRAME.neck > 0.9999 and given.anterior @ FRAME.anterior > 0.9999
    with pytest.raises(InputError, match="neck_xyz"):
        AnatomyHint.from_mapping({"neck_xyz": "1 2"})


# --------------------------------------------------------------------------- phantom


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    cache = os.environ.get("CYSTOMAP_TEST_CACHE")  # shared with the compare tests' s1, s2
    root = Path(cache) / "compare" if cache else tmp_path_factory.mktemp("anatomy")
    base = PhantomConfig(n_frames=N_FRAMES, cube_face_px=CUBE)
    return {"s1": build_session(root / "s1", 1, base, Similarity()),
            "s2": build_session(root / "s2", 2, base, B_FRAME)}


def _world(meta: dict, sim3) -> tuple[np.ndarray, np.ndarray]:
    a = Anatomy.from_json(meta["anatomy"])
    return a.neck @ sim3.rotation.T, a.anterior @ sim3.rotation.T


def test_phantom_sessions_find_their_neck_and_roll(pair: dict[str, Path]) -> None:
    """Each session's frame against the truth, and the two sessions against each other
    (each in its own model frame; no compare stage)."""
    world = {}
    for name, root in pair.items():
        res = evaluate_session(root / "truth", root / "sfm", root / "mesh" / "surface.ply",
                               root / "atlas")
        an = res["anatomy"]
        assert an["neck_error_deg"] < 3.0, (name, an)
        assert an["roll_abs_error_deg"] < 6.0, (name, an)
        if name == "s2":  # the lesions' regions in the estimated frame are the truth's
            assert an["regions_n"] == 6 and an["regions_correct"] == 6, an["lesions"]
        meta = json.loads((root / "atlas" / "atlas.json").read_text())
        _, sim3 = _align(load_truth(root / "truth"), _load_models(root / "sfm", EvalConfig(), []),
                         EvalConfig(), [])
        world[name] = _world(meta, sim3)
        assert set(meta["regions"]) == {"trigone/neck", "posterior wall", "left lateral wall",
                                        "right lateral wall", "anterior wall", "dome"}
        assert (root / "atlas" / "regions.png").is_file()
    (n1, a1), (n2, a2) = world["s1"], world["s2"]
    assert math.degrees(math.acos(np.clip(n1 @ n2, -1, 1))) < 3.0
    assert math.degrees(math.acos(np.clip(a1 @ a2, -1, 1))) < 6.0


def test_changes_and_landmarks_have_their_region(pair: dict[str, Path], tmp_path: Path) -> None:
    a, b = pair["s1"], pair["s2"]
    les = pd.read_csv(b / "truth" / "lesions.csv")
    assert {"region", "clock", "distance_from_neck_mm"} <= set(les.columns)
    out = tmp_path / "cmp"
    site = tuple(les[["x", "y", "z"]].to_numpy(float)[0])  # world = A's model frame
    compare_sessions(SessionPaths.from_root(a), SessionPaths.from_root(b), out,
                     CompareConfig(), landmarks=[Landmark("lesion1", point=site)])
    table = pd.read_csv(out / "changes.csv")
    assert {"region", "clock", "distance_from_neck_mm", "straddles"} <= set(table.columns)
    score = evaluate_changes(b / "truth", b / "sfm", out / "changes.csv")["lesions"]
    # as test_compare's bound: at 48 frames, strips of the wall are painted from fewer than
    # min_views frames and are not compared (black in difference.png), and which lesions fall
    # in one varies with floating point between machines (5 of 6 found on one, 4 on another:
    # the 10 mm lesion in such a strip, the 30 mm one cut by one); this test is about regions
    assert score["n_matched"] >= 4
    assert score["region_accuracy"] == 1.0, score["lesions"]
    # clock within half an hour and distance within 15 % of the truth for matched lesions
    for e in score["lesions"]:
        if e["detected"]:
            det = table.iloc[e["detection_row"]]
            true = les[les["id"] == e["id"]].iloc[0]
            dh = (det["clock"] - true["clock"] + 6) % 12 - 6
            assert abs(dh) < 0.5, (det, true)
            dist_true = true["distance_from_neck_mm"] * B_FRAME.scale  # B's model units
            assert abs(det["distance_from_neck_mm"] - dist_true) < 0.15 * dist_true + 3.0
    with open(out / "landmarks.csv", newline="") as fh:
        row = next(csv.DictReader(fh))
    assert row["region"] == les["region"].iloc[0]
