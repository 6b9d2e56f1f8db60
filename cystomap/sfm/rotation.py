"""Loop rotations: rotation drift that the epipolar tests cannot see.

The seam and loop tests of :mod:`cystomap.sfm.consistency` measure matches against the model's
epipolar lines, and a rotation error about the axis across the baseline moves the matches
*along* those lines: a chain of low-parallax frames (the scope diving towards a plain wall) can
drift several degrees in rotation with every pair still "agreeing" (seen on a family-B phantom
session, FROC dev seed 303 session 2: 3.4° between frames 0-7 and 65-69, trajectory RMSE
2.4 mm, no pair test failed; the loop pairs spanning the drifted stretch were rejected as if
they were false). Each verified loop pair has its own relative rotation, from its essential
matrix; its discrepancy with the model's relative rotation, as a rotation vector in the world
frame (``R_i^T · (R_pair^T · R_model) · R_i``), is the rotation the model has put between the
two frames' parts of the video, plus the pair's own error.

Only pairs whose geometry COLMAP classed as *calibrated* (the essential matrix explains the
matches better than a homography: enough parallax) are used: on low-parallax pairs the
relative rotation is ill-determined, and neighbouring such pairs err alike (measured against
the truth on three dev sessions: calibrated loop pairs median 0.4-0.8°, planar-or-panoramic
ones 1.9-2.8° with a 90th percentile of 14-26°), which looks like drift. And only pairs the
model puts on the same wall: repeated texture gives loop pairs between frames that do not
overlap, whose geometry is false and rightly rejected; a pair is tested when most of its first
frame's matched points that have a 3-D point project inside its second frame in the model.

Drift is smooth along the video, so loop pairs that link nearly the same two places (both ends
within ``sequential_overlap`` frames) share one discrepancy, while the pairs' own errors are
independent. The statistic is the agreement of neighbouring pairs' discrepancies, ``S = Σ
w_p · w_q`` over neighbouring couples / ``Σ |w_p|²``, each first shortened to at most ``CLIP``
times their median length (one wild pair cannot carry it), then weighed by the square root of
the pair's inlier matches (a pair's rotation is as precise as its matches are many: on a
mosaic-textured session four neighbouring false loop pairs of about 20 matches, 12-32° off the
truth, made an unweighted test nearly flag a model 0.1-0.2° from the truth there). No threshold is set on it:
without drift each discrepancy is noise symmetric about zero, so flipping the signs at random
(``REPLICATES`` times, seeded) gives what noise reaches with these very pairs; the model is
flagged when ``S`` exceeds all but ``ALPHA`` of them. The place and size reported are those of
the group of neighbouring pairs whose mean discrepancy stands out most against its spread.

A self-calibrated session's pairs are measured through its estimated camera, not the prior's
stored matrices (:func:`discrepancies`). The sign-flip null assumes independent pairs, but
neighbouring loop pairs share frames and so errors: on fresh phantom seeds 8 and 9 four of ten
sessions were flagged where the model is within 0.4° of the truth (docs/measurements.md, "The second
mapping on by default"); a null that keeps that dependence is still to be found.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from cystomap.sfm.config import SfmConfig

log = logging.getLogger(__name__)

# sign-flip replicates of the null and the share of them the model's statistic must exceed
REPLICATES = 1000
ALPHA = 0.01
# a group's mean and spread need this many loop pairs
MIN_GROUP = 3
# pycolmap.TwoViewGeometryConfiguration.CALIBRATED
CALIBRATED = 2
# discrepancies longer than this many times the median are shortened to it (outliers)
CLIP = 3.0


@dataclass
class Discrepancies:
    """Loop pairs (indices into the video-ordered names), the model's rotation error between
    their two frames as measured by each (world-frame rotation vectors, radians), and the share
    of each pair's matched points the model puts inside its second frame."""

    pairs: np.ndarray  # (N, 2) int
    rotvec: np.ndarray  # (N, 3)
    landing: np.ndarray  # (N,)
    inliers: np.ndarray  # (N,) verified matches of each pair


def _essential_from_rays(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Linear (eight-point) essential matrix of verified inlier rays, x2^T E x1 = 0."""
    a = np.einsum("ni,nj->nij", np.c_[x2, np.ones(len(x2))], np.c_[x1, np.ones(len(x1))])
    e = np.linalg.svd(a.reshape(len(x1), 9))[2][-1].reshape(3, 3)
    u, _, vt = np.linalg.svd(e)
    return u @ np.diag([1.0, 1.0, 0.0]) @ vt


def _relative_rotation(geometry: Any, x1: np.ndarray, x2: np.ndarray) -> np.ndarray | None:
    """The pair's rotation (camera 2 from camera 1) from its essential matrix and its inlier
    rays (normalised image coordinates): of the four decompositions, the one that puts most
    rays in front of both cameras. Estimated from the rays when no matrix is stored. (numpy
    only: OpenCV's calls here made the stage's later output differ from run to run.)"""
    if len(x1) < 8:
        return None
    e = np.asarray(getattr(geometry, "E", np.zeros((3, 3))), dtype=np.float64) \
        if geometry is not None else np.zeros((3, 3))
    if not np.abs(e).sum():
        e = _essential_from_rays(x1, x2)
    u, _, vt = np.linalg.svd(e)
    if np.linalg.det(u) < 0:
        u = -u
    if np.linalg.det(vt) < 0:
        vt = -vt
    w = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    r1 = np.c_[x1, np.ones(len(x1))]
    r2 = np.c_[x2, np.ones(len(x2))]
    best, front = None, -1
    for rot in (u @ w @ vt, u @ w.T @ vt):
        for t in (u[:, 2], -u[:, 2]):
            # depths z1, z2 with z2 r2 = z1 R r1 + t (least squares per ray): both positive
            a1 = r1 @ rot.T
            aa, bb, ab = np.sum(a1 * a1, 1), np.sum(r2 * r2, 1), np.sum(a1 * r2, 1)
            at, bt = a1 @ t, r2 @ t
            det = aa * bb - ab * ab
            ok = np.abs(det) > 1e-12
            z1 = np.where(ok, (-bb * at + ab * bt) / np.where(ok, det, 1.0), 0.0)
            z2 = np.where(ok, (aa * bt - ab * at) / np.where(ok, det, 1.0), 0.0)
            n = int(np.sum((z1 > 0) & (z2 > 0)))
            if n > front:
                best, front = rot, n
    return best


def _relative_rotation_ransac(pts1: Any, pts2: Any, m: np.ndarray, cam1: Any,
                              cam2: Any) -> np.ndarray | None:
    """The pair's rotation (camera 2 from camera 1) from its matches through the cameras
    (pycolmap's LO-RANSAC on the essential matrix; seeded by the caller)."""
    import pycolmap

    if len(m) < 8:
        return None
    xy1 = np.array([pts1[k].xy for k in m[:, 0]], dtype=np.float64).reshape(-1, 2)
    xy2 = np.array([pts2[k].xy for k in m[:, 1]], dtype=np.float64).reshape(-1, 2)
    res = pycolmap.estimate_essential_matrix(xy1, xy2, cam1, cam2)
    return None if res is None else np.asarray(res["cam2_from_cam1"].rotation.matrix())


def _calibrated(geometry: Any) -> bool:
    """COLMAP classed the pair's geometry as calibrated (essential matrix over homography)."""
    config = getattr(geometry, "config", None)
    return config is not None and int(config) == CALIBRATED


def discrepancies(rec: Any, names: list[str], geoms: dict[tuple[int, int], Any],
                  loops: set[tuple[int, int]], from_rays: bool = False) -> Discrepancies:
    """Each verified loop pair's rotation discrepancy with ``rec`` and its landing share (pairs
    of calibrated two-view geometry only). ``from_rays``: the pair's relative pose is estimated
    again from its matches through ``rec``'s camera (pycolmap's LO-RANSAC on the essential
    matrix; seed it first) instead of the stored matrix, which the matching computed with the
    camera it was given: for a self-calibrated scope, the prior, without the lens's distortion
    (held-out uncal:8, k1 -0.2: stored matrices 8.4° from a model 0.14 mm from the truth,
    re-estimated ones 1.2°)."""
    from scipy.spatial.transform import Rotation

    by_name = {rec.image(i).name: i for i in rec.reg_image_ids()}
    pairs, vecs, land, inl = [], [], [], []
    for p in sorted(loops):
        g = geoms.get(p)
        if g is None or not _calibrated(g.geometry):
            continue
        ia, ib = by_name.get(names[p[0]]), by_name.get(names[p[1]])
        if g is None or ia is None or ib is None:
            continue
        im1, im2 = rec.image(ia), rec.image(ib)
        cam1, cam2 = rec.camera(im1.camera_id), rec.camera(im2.camera_id)
        pts1, pts2 = im1.points2D, im2.points2D
        m = g.matches
        if from_rays:
            rot = _relative_rotation_ransac(pts1, pts2, m, cam1, cam2)
        else:
            x1 = np.asarray(cam1.cam_from_img(np.array([pts1[k].xy for k in m[:, 0]]).reshape(-1, 2)))
            x2 = np.asarray(cam2.cam_from_img(np.array([pts2[k].xy for k in m[:, 1]]).reshape(-1, 2)))
            rot = _relative_rotation(g.geometry, x1, x2)
        if rot is None:
            continue
        a, b = im1.cam_from_world(), im2.cam_from_world()
        r1, r2 = np.asarray(a.rotation.matrix()), np.asarray(b.rotation.matrix())
        error = r1.T @ (rot.T @ (r2 @ r1.T)) @ r1
        ids = [pts1[k].point3D_id for k in m[:, 0]]
        xyz = np.array([rec.points3D[i].xyz for i in ids if rec.exists_point3D(i)]).reshape(-1, 3)
        share = 0.0
        if len(xyz):
            x = xyz @ r2.T + np.asarray(b.translation)
            front = x[:, 2] > 0
            if front.any():
                uv = np.asarray(cam2.img_from_cam(x[front])).reshape(-1, 2)
                inside = ((uv[:, 0] >= 0) & (uv[:, 0] < cam2.width)
                          & (uv[:, 1] >= 0) & (uv[:, 1] < cam2.height))
                share = float(inside.sum() / len(xyz))
        pairs.append(p)
        vecs.append(Rotation.from_matrix(error).as_rotvec())
        land.append(share)
        inl.append(len(m))
    return Discrepancies(np.array(pairs, dtype=np.int64).reshape(-1, 2),
                         np.array(vecs, dtype=np.float64).reshape(-1, 3),
                         np.array(land, dtype=np.float64), np.array(inl, dtype=np.float64))


def _groups(pairs: np.ndarray, window: int) -> list[np.ndarray]:
    """For each pair, the pairs whose both ends lie within ``window`` frames of its own."""
    di = np.abs(pairs[:, None, 0] - pairs[None, :, 0]) <= window
    dj = np.abs(pairs[:, None, 1] - pairs[None, :, 1]) <= window
    return [np.flatnonzero(row) for row in di & dj]


def _z(rotvec: np.ndarray, groups: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Each group's mean discrepancy (rotation vector) and its z = |mean| / (sd / sqrt(n))."""
    mean = np.zeros((len(groups), 3))
    z = np.zeros(len(groups))
    for k, g in enumerate(groups):
        if len(g) < MIN_GROUP:
            continue
        w = rotvec[g]
        mean[k] = w.mean(axis=0)
        sd = float(np.sqrt(np.sum((w - mean[k]) ** 2) / (len(g) - 1)))
        z[k] = np.linalg.norm(mean[k]) / max(sd / np.sqrt(len(g)), 1e-12)
    return mean, z


def _clip(rotvec: np.ndarray) -> np.ndarray:
    """Discrepancies shortened to at most CLIP times their median length (a sign-symmetric
    change, so the sign-flip null stays exact): one wild pair cannot carry a group."""
    norm = np.linalg.norm(rotvec, axis=1)
    cap = CLIP * float(np.median(norm)) if len(norm) else 0.0
    scale = np.where(norm > cap, cap / np.maximum(norm, 1e-300), 1.0)
    return rotvec * scale[:, None]


def _agreement(rotvec: np.ndarray, neighbours: np.ndarray) -> float:
    """Sum of the dot products of neighbouring pairs' discrepancies over their squared sum."""
    return float(np.sum(neighbours * (rotvec @ rotvec.T)) / max(np.sum(rotvec ** 2), 1e-300))


def drift_test(pairs: np.ndarray, rotvec: np.ndarray, window: int, seed: int = 0,
               replicates: int = REPLICATES, inliers: np.ndarray | None = None) -> dict[str, Any]:
    """The neighbouring discrepancies' agreement against its sign-flip null (see the module's
    doc): figures for quality.json, ``flagged`` when the null reaches it in at most ALPHA of
    its replicates; the most deviant group's place (frame indices) and mean rotation.
    ``inliers``: each pair's verified matches, to weigh its discrepancy by its precision."""
    groups = _groups(pairs, window) if len(pairs) else []
    if sum(len(g) >= MIN_GROUP for g in groups) == 0:
        return {"checked": False, "pairs_tested": len(pairs),
                "reason": f"no {MIN_GROUP} loop pairs with enough parallax link the same two "
                          "places of the video", "flagged": False}
    rotvec = _clip(rotvec)
    weight = np.ones(len(pairs)) if inliers is None else np.sqrt(inliers / np.median(inliers))
    weighted = rotvec * weight[:, None]
    neighbours = np.zeros((len(pairs), len(pairs)), dtype=bool)
    for k, g in enumerate(groups):
        neighbours[k, g] = True
    np.fill_diagonal(neighbours, False)
    stat = _agreement(weighted, neighbours)
    rng = np.random.default_rng(seed)
    null = np.array([_agreement(weighted * rng.choice((-1.0, 1.0), size=(len(rotvec), 1)),
                                neighbours) for _ in range(replicates)])
    p_value = float((1 + np.sum(null >= stat)) / (replicates + 1))
    mean, z = _z(rotvec, groups)
    worst = int(np.argmax(z))
    g = groups[worst]
    return {
        "checked": True,
        "pairs_tested": len(pairs),
        "window_frames": int(window),
        "agreement": round(stat, 4),
        "agreement_null_max": round(float(null.max()), 4),
        "p_value": round(p_value, 4),
        "median_deg": round(float(np.degrees(np.median(np.linalg.norm(rotvec, axis=1)))), 3),
        "worst_deg": round(float(np.degrees(np.linalg.norm(mean[worst]))), 3),
        "worst_z": round(float(z[worst]), 3),
        "worst_pairs": len(g),
        "worst_frames": [[int(pairs[g, 0].min()), int(pairs[g, 0].max())],
                         [int(pairs[g, 1].min()), int(pairs[g, 1].max())]],
        "flagged": bool(p_value <= ALPHA),
    }


def rotation_check(rec: Any, names: list[str], geoms: dict[tuple[int, int], Any],
                   loops: set[tuple[int, int]], cfg: SfmConfig,
                   from_rays: bool = False) -> dict[str, Any]:
    """Loop rotations against the model (see the module's doc): figures for quality.json's
    ``consistency.rotation`` (frames named), ``flagged`` when the model has turned one place of
    the video against another. ``from_rays`` when the stage estimated the intrinsics (see
    :func:`discrepancies`)."""
    if from_rays:
        import pycolmap

        pycolmap.set_random_seed(cfg.seed)
    d = discrepancies(rec, names, geoms, loops, from_rays)
    same_wall = d.landing > 0.5
    out = drift_test(d.pairs[same_wall], d.rotvec[same_wall], cfg.sequential_overlap, cfg.seed,
                     inliers=d.inliers[same_wall])
    out["loop_pairs"] = len(d.pairs)
    out["loop_pairs_same_wall"] = int(same_wall.sum())
    if out["checked"]:
        (a0, a1), (b0, b1) = out["worst_frames"]
        out["worst_frames"] = [[names[a0], names[a1]], [names[b0], names[b1]]]
        log.info("rotation self-check: %d loop pairs with parallax on the same wall, median %.2f° "
                "from the model; neighbouring ones agree %.2f (sign-flipped: at most %.2f, p "
                "%.4f)%s; most deviant: the %d linking %s-%s to %s-%s, %.2f° off",
                out["pairs_tested"], out["median_deg"], out["agreement"],
                out["agreement_null_max"], out["p_value"], ": rotation drift (warned below)"
                if out["flagged"] else "", out["worst_pairs"], names[a0], names[a1], names[b0],
                names[b1], out["worst_deg"])
    return out
