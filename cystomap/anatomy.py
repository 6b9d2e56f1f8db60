"""The anatomical frame of a session and the standard bladder regions.

Frame (per session, in its model frame): ``origin`` (the wall's volume centroid, the atlas
barycentre), ``neck`` (unit direction from the origin to the bladder neck) and ``anterior``
(unit, orthogonal to ``neck``). The patient's left is ``anterior × neck`` and the dome is
``-neck``.

Estimated from the scope's entry (:func:`estimate`): the first registered frames look from
the urethra through the neck into the bladder, so the camera of the leading frames that is
farthest out relative to the wall (radially from the origin), when it is beyond the wall (in
the urethra), gives the neck direction, else their path followed back to the wall; while
the scope enters it is held upright, the image's up direction being the patient's anterior:
each entry frame's view direction ``v`` and image-up ``u`` span the plane that contains the
anterior, and the anterior is the direction of that plane orthogonal to the neck,
``(n·v) u − (n·u) v``. Either can be overridden (:class:`AnatomyHint`): the entry's roll (the
image's up was not anterior), or a point at the neck / on the anterior wall (a recording that
does not start with the entry).

Clock position: seen from the neck looking into the bladder (towards the dome) with anterior
up, 12 o'clock = anterior, 3 = patient's left, 6 = posterior, 9 = patient's right; hours in
[0.5, 12.5) so that anterior reads 12.

Regions (directions from the origin; ``polar`` = angle from the neck direction):

* ``trigone/neck``: polar < 45°;
* ``dome``: polar > 135°;
* between them, by clock: ``anterior wall`` 10:30-1:30, ``left lateral wall`` 1:30-4:30,
  ``posterior wall`` 4:30-7:30, ``right lateral wall`` 7:30-10:30.

Atlas drawn in the frame (:func:`atlas_axes`): neck at the bottom, dome at the top, the
posterior wall in the middle, the patient's right wall left of it and the left wall right of
it, the anterior wall at both edges: the wall seen from inside, as when facing the patient
(the bladder opened along its anterior wall and laid flat, mucosa up).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from cystomap.errors import InputError

log = logging.getLogger(__name__)

NECK_CAP_DEG = 45.0  # trigone/neck: within this angle of the neck direction
DOME_CAP_DEG = 45.0  # dome: within this angle of the dome direction
REGIONS = ("trigone/neck", "posterior wall", "left lateral wall", "right lateral wall",
           "anterior wall", "dome")
#: Wall regions by clock hours [start, end) (the anterior one wraps through 12).
WALL_SECTORS = (("anterior wall", 10.5, 1.5), ("left lateral wall", 1.5, 4.5),
                ("posterior wall", 4.5, 7.5), ("right lateral wall", 7.5, 10.5))
#: Columns added to changes.csv and landmarks.csv.
ANATOMY_COLUMNS = ("region", "clock", "distance_from_neck_mm")
#: Leading share of the registered frames searched for the entry (at least ENTRY_MIN_FRAMES).
ENTRY_SHARE = 0.1
ENTRY_MIN_FRAMES = 3
#: Entry frames for the roll: cameras at least this share of the farthest one's radial
#: position (relative to the wall), among the leading frames up to it.
ENTRY_RADIUS_SHARE = 0.5


def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


@dataclass(frozen=True)
class Anatomy:
    """Anatomical frame of one session (model frame)."""

    origin: np.ndarray
    neck: np.ndarray
    anterior: np.ndarray
    source: str = ""

    def __post_init__(self) -> None:
        n = _unit(self.neck)
        a = np.asarray(self.anterior, dtype=np.float64)
        a = a - (a @ n) * n
        if np.linalg.norm(a) < 1e-9:
            raise InputError("anatomy: the anterior direction is parallel to the neck")
        object.__setattr__(self, "origin", np.asarray(self.origin, dtype=np.float64))
        object.__setattr__(self, "neck", n)
        object.__setattr__(self, "anterior", _unit(a))

    @property
    def left(self) -> np.ndarray:
        """The patient's left (anterior × neck)."""
        return np.cross(self.anterior, self.neck)

    def to_json(self) -> dict[str, Any]:
        return {"origin": self.origin.tolist(), "neck": self.neck.tolist(),
                "anterior": self.anterior.tolist(), "left": self.left.tolist(),
                "source": self.source,
                "convention": "unit vectors in the session's model frame; left = anterior x "
                              "neck, dome = -neck; clock seen from the neck, 12 = anterior, "
                              "3 = patient's left (cystomap.anatomy)"}

    @classmethod
    def from_json(cls, meta: dict[str, Any]) -> Anatomy:
        return cls(np.asarray(meta["origin"], float), np.asarray(meta["neck"], float),
                   np.asarray(meta["anterior"], float), str(meta.get("source", "")))

    # ---- angles and regions

    def clock_polar(self, points: Any) -> tuple[np.ndarray, np.ndarray]:
        """Clock hours [0.5, 12.5) and polar angle from the neck (degrees) of model points."""
        d = _unit(np.asarray(points, dtype=np.float64) - self.origin)
        polar = np.degrees(np.arccos(np.clip(d @ self.neck, -1.0, 1.0)))
        theta = np.degrees(np.arctan2(d @ self.left, d @ self.anterior))  # clockwise from A
        hours = np.mod(theta / 30.0, 12.0)
        hours = np.where(hours < 0.5, hours + 12.0, hours)
        return hours, polar

    def regions(self, points: Any) -> np.ndarray:
        """Region name (see the module docstring) of each point (object array)."""
        hours, polar = self.clock_polar(points)
        return region_of(hours, polar)


def region_of(hours: Any, polar: Any) -> np.ndarray:
    """Region names for clock hours and polar angles from the neck (degrees)."""
    hours = np.atleast_1d(np.asarray(hours, dtype=np.float64))
    polar = np.atleast_1d(np.asarray(polar, dtype=np.float64))
    out = np.empty(hours.shape, dtype=object)
    h = np.mod(hours, 12.0)
    for name, lo, hi in WALL_SECTORS:
        sel = (h >= lo) & (h < hi) if lo < hi else (h >= lo) | (h < hi)
        out[sel] = name
    out[polar < NECK_CAP_DEG] = "trigone/neck"
    out[polar > 180.0 - DOME_CAP_DEG] = "dome"
    return out


def atlas_axes(anatomy: Anatomy) -> np.ndarray:
    """Atlas axes (rows x, y, z) in the model frame: x = posterior (the atlas's centre column),
    y = patient's left (right of centre), z = dome (top). A reflection (det −1): the wall is
    seen from inside with the neck at the bottom."""
    return np.stack([-anatomy.anterior, anatomy.left, -anatomy.neck])


def neck_distance(anatomy: Anatomy, rays: Any, points: Any, neck_point: Any = None,
                  step_deg: float = 2.0) -> np.ndarray:
    """Distance (mm) on the wall from the neck to each point, along the wall's meridian (the
    plane through the origin, the neck direction and the point): rays from the origin every
    ``step_deg`` between the two directions meet the mesh ``rays`` (a SurfaceRays); where
    none meets it (an open aperture), the path goes straight on. ``neck_point``: where the
    neck is (default: where the neck direction meets the mesh)."""
    pts = np.atleast_2d(np.asarray(points, dtype=np.float64))
    if neck_point is None:
        t, _ = rays.cast(anatomy.origin, anatomy.neck[None])
        neck_point = anatomy.origin + (t[0] if np.isfinite(t[0]) else 0.0) * anatomy.neck
    neck_point = np.asarray(neck_point, dtype=np.float64)
    d = _unit(pts - anatomy.origin)
    ang = np.arccos(np.clip(d @ anatomy.neck, -1.0, 1.0))
    k = max(2, math.ceil(math.degrees(float(ang.max(initial=0.0))) / step_deg))
    s = np.linspace(0.0, 1.0, k + 1)[1:-1]
    # slerp neck -> d; directions at fractions s of the angle
    perp = d - np.cos(ang)[:, None] * anatomy.neck
    perp = _unit(np.where(np.linalg.norm(perp, axis=1, keepdims=True) > 1e-9, perp,
                          anatomy.anterior))
    a = ang[:, None] * s[None, :]
    dirs = (np.cos(a)[..., None] * anatomy.neck + np.sin(a)[..., None] * perp[:, None, :])
    t, _ = rays.cast(anatomy.origin, dirs.reshape(-1, 3))
    t = t.reshape(len(pts), len(s))
    out = np.empty(len(pts))
    for i in range(len(pts)):
        ok = np.isfinite(t[i])
        path = np.vstack([neck_point[None], anatomy.origin + t[i, ok, None] * dirs[i, ok],
                          pts[i][None]])
        out[i] = float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
    return out


def covered_regions(anatomy: Anatomy, points: Any, diameters: Any,
                    rings: int = 4, per_ring: int = 36) -> list[list[str]]:
    """The regions a patch of each diameter centred at each point covers: the regions of the
    directions (from the origin) within its angular radius (half the diameter over its
    distance from the origin) of its centre's direction; the centre's region first. One name
    = the patch lies inside one region; more = it straddles a border (:data:`STRADDLE_RULE`)."""
    pts = np.atleast_2d(np.asarray(points, dtype=np.float64))
    diam = np.broadcast_to(np.asarray(diameters, dtype=np.float64), (len(pts),))
    rel = pts - anatomy.origin
    dist = np.maximum(np.linalg.norm(rel, axis=1), 1e-12)
    d = rel / dist[:, None]
    # two unit vectors orthogonal to each centre's direction
    ref = np.where(np.abs(d @ anatomy.neck)[:, None] < 0.9, anatomy.neck, anatomy.anterior)
    e1 = _unit(np.cross(d, ref))
    e2 = np.cross(d, e1)
    ang = np.clip(np.nan_to_num(diam / 2.0 / dist), 0.0, math.pi / 2)
    frac = np.arange(1, rings + 1) / rings
    phi = np.linspace(0.0, 2 * math.pi, per_ring, endpoint=False)
    a = ang[:, None, None] * frac[None, :, None]  # (n, rings, 1)
    ring = np.cos(phi)[None, None, :, None] * e1[:, None, None] \
        + np.sin(phi)[None, None, :, None] * e2[:, None, None]
    dirs = np.cos(a)[..., None] * d[:, None, None] + np.sin(a)[..., None] * ring
    out = []
    for i in range(len(pts)):
        names = anatomy.regions(anatomy.origin + np.vstack([d[i][None], dirs[i].reshape(-1, 3)]))
        seen = [str(names[0])]
        seen += sorted({str(x) for x in names[1:]} - {seen[0]}, key=REGIONS.index)
        out.append(seen)
    return out


#: How a patch on a border is named (changes.csv ``region`` / ``straddles``, evaluate).
STRADDLE_RULE = ("a patch is named by the region of its centroid on the wall; when its extent "
                 "(its diameter about the centroid) crosses a region border it straddles, and "
                 "the other regions it covers are listed in 'straddles'; evaluate counts a "
                 "lesion's region right when the region named is one the lesion covers, or "
                 "the lesion's region one the patch is said to straddle")


def locate(anatomy: Anatomy, points: Any, rays: Any = None,
           neck_point: Any = None, diameters: Any = None) -> list[dict[str, Any]]:
    """``region``, ``clock`` (hours, 0.1) and ``distance_from_neck_mm`` of each point (the
    distance is left empty without a mesh); with ``diameters`` (of the patches centred at the
    points) also ``straddles``: the other regions each patch covers, "; "-joined (empty when
    it lies inside its region; see :func:`covered_regions`)."""
    pts = np.atleast_2d(np.asarray(points, dtype=np.float64))
    if len(pts) == 0:
        return []
    hours, polar = anatomy.clock_polar(pts)
    names = region_of(hours, polar)
    dist = (neck_distance(anatomy, rays, pts, neck_point) if rays is not None
            else np.full(len(pts), np.nan))
    out = [{"region": str(names[i]), "clock": round(float(hours[i]), 1),
            "distance_from_neck_mm": (round(float(dist[i]), 2) if np.isfinite(dist[i]) else "")}
           for i in range(len(pts))]
    if diameters is not None:
        for row, cov in zip(out, covered_regions(anatomy, pts, diameters), strict=True):
            row["straddles"] = "; ".join(cov[1:])
    return out


# --------------------------------------------------------------------------- estimation


@dataclass(frozen=True)
class AnatomyHint:
    """Per-session overrides of the estimate (model frame, mm)."""

    # The image's up direction while the scope enters, clockwise from anterior seen from the
    # neck (degrees): 0 = upright, 90 = image up was the patient's left.
    entry_roll_deg: float = 0.0
    # A point at the bladder neck: the neck direction from it (instead of the entry).
    neck_point: tuple[float, float, float] | None = None
    # A point on the anterior wall: the anterior from it (instead of the entry's image up).
    anterior_point: tuple[float, float, float] | None = None

    @classmethod
    def from_mapping(cls, m: dict[str, Any] | None) -> AnatomyHint:
        m = dict(m or {})
        roll = m.get("entry_roll_deg")
        out = cls(float(roll) if roll is not None and roll == roll else 0.0,
                  _point(m.get("neck_xyz"), "neck_xyz"),
                  _point(m.get("anterior_xyz"), "anterior_xyz"))
        if not math.isfinite(out.entry_roll_deg):
            raise InputError("anatomy: entry_roll_deg must be a finite number")
        return out


def _point(value: Any, what: str) -> tuple[float, float, float] | None:
    if value is None or (isinstance(value, float) and value != value) or value == "":
        return None
    if isinstance(value, str):
        value = value.replace(",", " ").split()
    try:
        p = tuple(float(x) for x in value)
    except (TypeError, ValueError):
        raise InputError(f"anatomy: {what} must be three numbers (x y z), got {value!r}") from None
    if len(p) != 3 or not all(math.isfinite(x) for x in p):
        raise InputError(f"anatomy: {what} must be three finite numbers (x y z), got {value!r}")
    return p  # type: ignore[return-value]


def _rotate(v: np.ndarray, axis: np.ndarray, deg: float) -> np.ndarray:
    """Right-handed rotation of ``v`` about unit ``axis`` by ``deg``."""
    a = math.radians(deg)
    return (v * math.cos(a) + np.cross(axis, v) * math.sin(a)
            + axis * (axis @ v) * (1 - math.cos(a)))


def _entry_neck(cen: np.ndarray, out: np.ndarray, origin: np.ndarray,
                rays: Any) -> tuple[np.ndarray, str]:
    """Neck direction from the entry cameras (video order). A camera outside the wall (its
    distance from the origin beyond the wall's in its direction) is still in the urethra,
    which meets the bladder at the neck: the direction of the outermost one. Otherwise (the
    recording starts inside): where the cameras' path, followed back (towards the earlier
    frames), meets the wall; a single camera: its direction."""
    far = int(np.argmax(out))
    if out[far] > 1.0:
        return _unit(cen[far] - origin), "the outermost camera, still in the urethra"
    if len(cen) >= 2:
        c = cen - cen.mean(axis=0)
        d = np.linalg.svd(c, full_matrices=False)[2][0]
        if d @ (cen[0] - cen[-1]) < 0:
            d = -d  # towards the earlier frames (out through the neck)
        inner = int(np.argmin(out))
        t, _ = rays.cast(cen[inner], d[None])
        if np.isfinite(t[0]):
            return _unit(cen[inner] + t[0] * d - origin), "its path followed back to the wall"
    return _unit(cen[far] - origin), "the outermost camera"


def estimate(names: list[str], rotations: np.ndarray, centres: np.ndarray, origin: np.ndarray,
             rays: Any, hint: AnatomyHint | None = None) -> Anatomy:
    """The anatomical frame from registered frames in video order (``rotations``:
    camera-to-world, OpenCV axes; ``centres``: camera centres) about ``origin`` on the mesh
    ``rays`` (a SurfaceRays). See the module docstring."""
    hint = hint or AnatomyHint()
    origin = np.asarray(origin, dtype=np.float64)
    rot = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    cen = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    n = len(cen)
    sources = []
    entry: np.ndarray = np.zeros(0, int)
    if hint.neck_point is None or hint.anterior_point is None:
        if n == 0:
            raise InputError("anatomy: no registered frame to find the scope's entry from")
        lead = min(n, max(ENTRY_MIN_FRAMES, math.ceil(ENTRY_SHARE * n)))
        rel = cen[:lead] - origin
        r = np.linalg.norm(rel, axis=1)
        t, _ = rays.cast(origin, _unit(rel))
        wall = np.where(np.isfinite(t), t, np.nanmedian(np.where(np.isfinite(t), t, np.nan))
                        if np.isfinite(t).any() else 1.0)
        out = r / np.maximum(wall, 1e-9)  # radial position relative to the wall
        k = int(np.argmax(out))
        near = out >= ENTRY_RADIUS_SHARE * out[k]
        lo, hi = k, k
        while lo > 0 and near[lo - 1]:
            lo -= 1
        while hi + 1 < lead and near[hi + 1]:
            hi += 1
        entry = np.arange(lo, hi + 1)
    if hint.neck_point is not None:
        neck = _unit(np.asarray(hint.neck_point) - origin)
        sources.append("neck from the given neck point")
    else:
        neck, how = _entry_neck(cen[entry], out[entry], origin, rays)
        sources.append(f"neck from the scope's entry ({how}; frames {names[entry[0]]}.."
                       f"{names[entry[-1]]}, farthest out {names[k]} at {out[k]:.2f} of the "
                       "wall's distance)")
    if hint.anterior_point is not None:
        ant = _unit(np.asarray(hint.anterior_point) - origin)
        sources.append("anterior from the given anterior point")
    else:
        up = -rot[entry, :, 1]  # image up (OpenCV: y down)
        view = rot[entry, :, 2]
        a = (view @ neck)[:, None] * up - (up @ neck)[:, None] * view
        a = a - (a @ neck)[:, None] * neck
        a *= np.where(np.einsum("ij,ij->i", a, up) < 0, -1.0, 1.0)[:, None]
        ant = a.sum(axis=0)  # longer vectors (well-conditioned frames) count more
        if np.linalg.norm(ant) < 1e-9:
            raise InputError("anatomy: the entry frames' image up is along the neck; give "
                             "anterior_xyz")
        ant = _unit(ant)
        if hint.entry_roll_deg:
            ant = _rotate(ant, -neck, -hint.entry_roll_deg)  # undo the entry's roll
        spread = np.degrees(np.arccos(np.clip(_unit(a) @ ant if not hint.entry_roll_deg
                                              else _unit(a) @ _unit(a.sum(0)), -1, 1)))
        sources.append(
            f"anterior from the image's up while the scope enters ({len(entry)} frame(s) "
            f"{names[entry[0]]}..{names[entry[-1]]}, spread {float(spread.max()):.1f} deg"
            + (f", entry roll {hint.entry_roll_deg:g} deg" if hint.entry_roll_deg else "")
            + ")")
    anatomy = Anatomy(origin, neck, ant, "; ".join(sources))
    log.info("anatomy: %s", anatomy.source)
    return anatomy
