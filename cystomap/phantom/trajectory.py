"""Camera path of a phantom session: enter through the urethra, scan the wall, come back.

The scan is described by the wall point the camera aims at (a direction ``u`` from the
session barycentre, following smooth waypoints in azimuth/elevation) and the camera sits
``d`` mm before that point along a view direction tilted 10-18 deg from ``u`` (so the camera
moves on a ~20 mm orbit around the barycentre and SfM has parallax):

1. entry: from inside the urethra tube up through the aperture, looking at the start point,
   upright as a urologist enters (image up = the patient's anterior, ``geometry.ANTERIOR``);
   the roll then turns to that of the dome pass over its first stretch;
2. a pass over the dome (up the meridian of the start azimuth, over the top, down the other
   side);
3. a full sweep around the side wall at about +6 deg elevation;
4. a full retroflexed sweep around the neck at about -42 deg elevation;
5. back up to the start point and down to the aperture (closing the loop).

The image's short axis follows the direction of the sweep (long axis across it, which
widens the band each sweep covers). Frames are spaced evenly in "rotation + 0.8 deg per mm
of translation", so the path scales with ``n_frames``. Session 2 starts at another azimuth
and sweeps the other way. With ``trajectory: recording`` the same path is travelled on the
timing of a urologist's recording instead (pauses, returns, fast bends, hand tremor; see
:mod:`cystomap.phantom.recording`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline

from cystomap.phantom.config import PhantomConfig
from cystomap.phantom.geometry import Bladder, direction, rng, unit

STREAM_PATH = 10
DEG_PER_MM = 0.7
ENTRY_DEPTH_MM = 10.0  # camera start: this far inside the urethra below the aperture
EXIT_HEIGHT_MM = 6.0  # camera end: this far above the aperture
ENTRY_ROLL_RAMP = 0.06  # share of the scan over which the upright entry roll turns to the sweep's


@dataclass
class Trajectory:
    rotations: np.ndarray  # (n, 3, 3) camera-to-world
    centres: np.ndarray  # (n, 3) camera centres, mm
    targets: np.ndarray  # (n, 3) aimed wall point per frame
    phase: list[str]  # per frame: entry / dome / side / neck / return / exit
    # per frame, recording mode only: scan / pause / bend / back (None for the sweep)
    motion: list[str] | None = None

    def rotation_steps_deg(self) -> np.ndarray:
        r = self.rotations
        rel = np.einsum("nji,njk->nik", r[:-1], r[1:])
        c = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)
        return np.degrees(np.arccos(c))

    def translation_steps_mm(self) -> np.ndarray:
        return np.linalg.norm(np.diff(self.centres, axis=0), axis=1)


def _waypoints(sign: float) -> tuple[np.ndarray, list[str]]:
    """(phi, el) waypoints in degrees; phi = azimuth travelled from the start (x sign)."""
    pts: list[tuple[float, float, str]] = []
    for el in (8, 30, 52, 72):
        pts.append((0, el, "dome"))
    for el in (76, 56, 38):
        pts.append((180, el, "dome"))
    pts += [(200, 20, "side"), (226, 8, "side")]
    for k in range(1, 9):
        pts.append((226 + 30 * k, 6, "side"))
    base = 226 + 30 * 8
    pts += [(base + 26, -10, "neck"), (base + 50, -30, "neck"), (base + 78, -42, "neck")]
    start = base + 78
    for k in range(1, 9):
        pts.append((start + 30 * k, -42, "neck"))
    end = start + 30 * 8
    pts += [(end + 24, -20, "return"), (end + 44, 4, "return")]
    arr = np.array([(p[0] * sign, p[1]) for p in pts], dtype=np.float64)
    return arr, [p[2] for p in pts]


def _wall_radius(scene, bladder: Bladder, u: np.ndarray) -> np.ndarray:
    from cystomap.phantom.wall_rays import cast

    t = cast(scene, np.broadcast_to(bladder.barycentre, u.shape), u)["t_hit"]
    return np.where(np.isfinite(t), t, np.nanmedian(np.where(np.isfinite(t), t, np.nan)))


def _frames(view: np.ndarray, tangent: np.ndarray) -> np.ndarray:
    """Camera-to-world rotations: z = view, y = tangent projected off z, x = y × z."""
    y = tangent - np.einsum("ij,ij->i", tangent, view)[:, None] * view
    y = unit(y)
    x = np.cross(y, view)
    return np.stack([x, y, view], axis=2)


def _transport(view: np.ndarray, first: np.ndarray) -> np.ndarray:
    """Parallel-transported (minimal-rotation) frames along the view directions."""
    out = np.empty((len(view), 3, 3))
    out[0] = first
    for k in range(1, len(view)):
        a, b = view[k - 1], view[k]
        axis = np.cross(a, b)
        s, c = np.linalg.norm(axis), float(a @ b)
        r = out[k - 1]
        if s > 1e-12:
            kx = axis / s
            kk = np.array([[0, -kx[2], kx[1]], [kx[2], 0, -kx[0]], [-kx[1], kx[0], 0]])
            rk = np.eye(3) + s * kk + (1 - c) * (kk @ kk)
            r = rk @ r
        out[k] = r
    return out


def _oriented_frames(view: np.ndarray, tangent: np.ndarray, labels: np.ndarray,
                     jitter: np.ndarray, ramp: int = 0) -> np.ndarray:
    """Camera rotations: the image's short axis follows ``tangent`` (the sweep; during the
    entry, -anterior, so image up is anterior) during the entry, the dome pass and the side
    sweep; elsewhere the roll is held (minimal rotation), which saves a full extra turn of
    roll around the neck. The roll turns from the entry's to the sweep's over the ``ramp``
    samples after the entry (the shorter way round)."""
    from scipy.ndimage import gaussian_filter1d

    locked = _frames(view, tangent)
    pt = _transport(view, locked[0])
    x, y = pt[:, :, 0], pt[:, :, 1]
    yl = locked[:, :, 1]
    psi = np.arctan2(-np.einsum("ij,ij->i", yl, x), np.einsum("ij,ij->i", yl, y))
    entry = np.flatnonzero(labels == "entry")
    if len(entry) and ramp > 0:
        e = int(entry[-1]) + 1
        psi[:e] = np.unwrap(psi[:e])
        after = np.unwrap(psi[e:])
        step = after[0] - psi[e - 1]
        after -= step - (step + np.pi) % (2 * np.pi) + np.pi  # continue the shorter way
        s = np.clip(np.arange(len(after)) / ramp, 0, 1)
        w = s * s * (3 - 2 * s)
        psi[e:] = (1 - w) * psi[e - 1] + w * after
    else:
        psi = np.unwrap(psi)
    lock = np.isin(labels, ["entry", "dome", "side"]).astype(float)
    last = int(np.flatnonzero(lock)[-1])
    hold = psi.copy()
    hold[last:] = psi[last]
    lam = gaussian_filter1d(lock, 60.0, mode="nearest")
    lam[: last - 180] = np.maximum(lam[: last - 180], lock[: last - 180])
    ang = hold + lam * (psi - hold) + jitter
    c, s = np.cos(ang)[:, None], np.sin(ang)[:, None]
    return np.stack([c * x + s * y, -s * x + c * y, view], axis=2)


def make_trajectory(cfg: PhantomConfig, session: int, bladder: Bladder, scene) -> Trajectory:
    """The session's camera path: evenly spaced (``sweep``) or on a recording's timing."""
    rot, cen, tgt, lab, cum = _dense_path(cfg, session, bladder, scene)
    n = cfg.frame_count
    if cfg.trajectory == "recording":
        from cystomap.phantom.recording import recording_timing, with_tremor

        g = rng(cfg, STREAM_PATH + session, 1)
        share, motion = recording_timing(n, cfg.fps, g)
        traj = _resample(rot, cen, tgt, lab, cum, share * cum[-1])
        traj.rotations = with_tremor(traj.rotations, cfg.fps, g)
        traj.motion = motion
        return traj
    return _resample(rot, cen, tgt, lab, cum, np.linspace(0, cum[-1], n))


def _dense_path(cfg: PhantomConfig, session: int, bladder: Bladder, scene,
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Dense samples of the path: rotations, centres, targets, phase labels and the
    cumulative image motion ("rotation + DEG_PER_MM deg per mm") along it."""
    g = rng(cfg, STREAM_PATH + session)
    az0 = float(g.uniform(-180, 180))
    sign = 1.0 if session == 1 else -1.0
    wp, labels = _waypoints(sign)
    wdir = direction(az0 + wp[:, 0], wp[:, 1])
    # spline through the waypoint directions, parameter = cumulative angle
    ang = np.arccos(np.clip(np.einsum("ij,ij->i", wdir[:-1], wdir[1:]), -1, 1))
    knots = np.r_[0, np.cumsum(ang)]
    spline = CubicSpline(knots, wdir, bc_type="natural")
    # smooth random modulation (distance, tilt, roll jitter)
    ph = g.uniform(0, 2 * np.pi, size=6)
    total = knots[-1]
    # dense samples of the scan part
    m = 3000
    q = np.linspace(0, total, m)
    u = unit(spline(q))
    tan = unit(spline(q, 1) - np.einsum("ij,ij->i", spline(q, 1), u)[:, None] * u)
    f = q / total
    dist = 72 + 5 * np.sin(2 * np.pi * 3.1 * f + ph[0]) + 2 * np.sin(2 * np.pi * 7.3 * f + ph[1])
    # two close looks at the wall: one during the side sweep (to ~33 mm), one at the neck
    lab_q = np.array(labels, dtype=object)[
        np.clip(np.searchsorted(knots, q, side="right") - 1, 0, len(labels) - 1)]
    for name, depth in (("side", 40.0), ("neck", 25.0)):
        idx = np.flatnonzero(lab_q == name)
        fc = f[idx[0]] + (f[idx[-1]] - f[idx[0]]) * g.uniform(0.3, 0.7)
        dist = dist - depth * np.exp(-(((f - fc) / 0.018) ** 2))
    tilt = np.radians(14 + 4 * np.sin(2 * np.pi * 2.3 * f + ph[2]))
    gam = ph[3] + 0.6 * np.sin(2 * np.pi * 1.3 * f + ph[5])
    side = np.cross(u, tan)
    e = unit(np.cos(gam)[:, None] * tan + np.sin(gam)[:, None] * side)
    w = unit(np.cos(tilt)[:, None] * u + np.sin(tilt)[:, None] * e)
    rho = _wall_radius(scene, bladder, u)
    target = bladder.barycentre + rho[:, None] * u
    centre = target - dist[:, None] * w
    # keep the camera well inside: at most 65 % of the wall distance from the barycentre
    rel = centre - bladder.barycentre
    r_c = np.linalg.norm(rel, axis=1)
    lim = 0.65 * _wall_radius(scene, bladder, unit(rel))
    over = r_c > lim
    centre[over] = bladder.barycentre + rel[over] * (lim[over] / r_c[over])[:, None]
    roll = np.radians(4) * np.sin(2 * np.pi * 1.1 * f + ph[4])
    # entry and exit (camera translates, aims at the start point)
    ap = bladder.vertices[bladder.rim].mean(0)
    axis = unit(bladder.barycentre - ap)
    c_in = ap - ENTRY_DEPTH_MM * axis
    c_out = ap + EXIT_HEIGHT_MM * axis
    k_in = 200
    s_in = np.linspace(0, 1, k_in)
    sm_in = s_in * s_in * (3 - 2 * s_in)
    cen_in = c_in + sm_in[:, None] * (centre[0] - c_in)
    s_out = np.linspace(0, 1, k_in)
    sm_out = s_out * s_out * (3 - 2 * s_out)
    cen_out = centre[-1] + sm_out[:, None] * (c_out - centre[-1])
    all_c = np.concatenate([cen_in[:-1], centre, cen_out[1:]])
    all_t = np.concatenate([np.repeat(target[:1], k_in - 1, 0), target,
                            np.repeat(target[-1:], k_in - 1, 0)])
    # entry: the image's down axis is -anterior (image up = anterior, off the view direction)
    ant = np.asarray(bladder.anatomy["anterior"])
    all_tan = np.concatenate([np.repeat(-ant[None], k_in - 1, 0), tan,
                              np.repeat(tan[-1:], k_in - 1, 0)])
    all_roll = np.concatenate([np.full(k_in - 1, roll[0]), roll, np.full(k_in - 1, roll[-1])])
    # phase labels per dense sample
    lab = lab_q
    all_lab = np.concatenate([np.full(k_in - 1, "entry", dtype=object), lab,
                              np.full(k_in - 1, "exit", dtype=object)])
    view = unit(all_t - all_c)
    rot = _oriented_frames(view, all_tan, all_lab, all_roll, round(ENTRY_ROLL_RAMP * m))
    # even spacing in rotation + translation
    rel_r = np.einsum("nji,njk->nik", rot[:-1], rot[1:])
    dang = np.degrees(np.arccos(np.clip((np.trace(rel_r, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    dtr = np.linalg.norm(np.diff(all_c, axis=0), axis=1)
    # image motion: rotation scaled by (target distance from barycentre / camera distance)
    rho_all = np.linalg.norm(all_t - bladder.barycentre, axis=1)
    d_all = np.linalg.norm(all_t - all_c, axis=1)
    zoom = np.clip(rho_all / d_all, 1.0, 3.0)[1:]
    cum = np.r_[0, np.cumsum(np.hypot(dang * zoom, DEG_PER_MM * dtr))]
    return rot, all_c, all_t, all_lab, cum


def _resample(rot, cen, tgt, lab, cum, want: np.ndarray) -> Trajectory:
    """Poses at the path positions ``want`` (in ``cum`` units), interpolated between the dense
    neighbours (exact spacing)."""
    from scipy.spatial.transform import Rotation, Slerp

    n = len(want)
    pick = np.searchsorted(cum, want).clip(0, len(cum) - 1)
    i1 = np.clip(np.searchsorted(cum, want, side="left"), 1, len(cum) - 1)
    i0 = i1 - 1
    span = np.maximum(cum[i1] - cum[i0], 1e-12)
    a = np.clip((want - cum[i0]) / span, 0, 1)
    rots = []
    for j in range(n):
        slerp = Slerp([0.0, 1.0], Rotation.from_matrix(rot[[i0[j], i1[j]]]))
        rots.append(slerp([a[j]]).as_matrix()[0])
    r = np.array(rots)
    c = cen[i0] + a[:, None] * (cen[i1] - cen[i0])
    t = tgt[i0] + a[:, None] * (tgt[i1] - tgt[i0])
    labels = [str(lab[k]) for k in pick]
    return Trajectory(r, c, t, labels)
