"""Stage ``mesh``: the sparse SfM cloud → a closed, watertight, manifold surface of the wall.

The bladder wall is seen from inside and is star-shaped about its barycentre (the reference
study assumes every face is visible from there). The surface is therefore fitted as a radial
function r(direction) about a centre c:

1. SfM points with short tracks or large reprojection errors are dropped; statistical outliers
   are removed and the rest is binned into voxels (even density, less noise).
2. A robust ellipsoid fitted to all points carries the global shape: it is where the surface
   relaxes to where the scan did not look.
3. On an icosphere grid of directions, r = ellipsoid + s is fitted by robust (Huber, IRLS)
   regularised least squares: each point pulls the barycentric interpolation of r at its
   direction towards its distance from c; a bending penalty ||Δs||² (Laplace-Beltrami on the
   unit sphere; ``smooth_degree``) keeps the surface smooth and a weak pull s → 0 makes it
   relax to the ellipsoid over ``hole_decay_deg`` away from the data. The surface is closed
   whatever was seen; the atlas's coverage says what was really seen.
4. c starts at the ellipsoid's centre and is replaced by the volume centroid of the fitted
   surface (``center_iterations`` times).
5. Local relief (``relief``, off by default; :mod:`cystomap.mesh_relief`): where the points the
   smooth fit rejected agree with each other (their median residual around a direction beyond
   ``reject_k`` robust standard deviations, into the cavity), r follows them: a raised lesion
   stands out of the wall instead of being smoothed into it.
6. The icosphere with its vertices pushed to r (closed, genus 0 by construction) is remeshed to
   even triangles (pymeshlab isotropic remeshing) and kept only if it stays watertight and
   two-manifold.

Outputs (``out_dir``): ``surface.ply`` (binary little-endian PLY, SfM frame and units (mm when
the SfM model is metric), outward vertex normals) and ``mesh.json``: vertex/face counts,
watertight, manifold, genus, volume_ml, area_mm2, extents (bounding box size), barycentre
(volume centroid), and distances of the SfM points to the surface (mean/median/p95, all points
and the filtered ones).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from cystomap.errors import InputError, StageError
from cystomap.geometry.pointcloud import statistical_inliers, voxel_bin
from cystomap.geometry.quadric import Ellipsoid, fit_ellipsoid, sphere_fit
from cystomap.geometry.sphere import direction_weights, icosphere, sphere_laplacian
from cystomap.geometry.trimesh import (
    mesh_volume,
    point_distances,
    topology,
    triangle_areas,
    vertex_normals,
    volume_centroid,
)
from cystomap.io.colmap import find_model_dir, load_reconstruction
from cystomap.io.ply import read_mesh, write_ply
from cystomap.mesh_relief import local_relief, relief_summary
from cystomap.outputs import atomic_dir, software_versions, write_json
from cystomap.settings import setting, validate

log = logging.getLogger(__name__)

# the stage, and the core names older callers (report, tests) import from here
__all__ = [
    "MeshConfig", "SparseCloud", "SurfaceFit", "build_mesh", "find_model_dir",
    "fit_closed_surface", "icosphere", "load_reconstruction", "load_sparse_cloud",
    "mesh_volume", "point_distances", "read_mesh", "remove_outliers", "topology",
    "triangle_areas", "vertex_normals", "volume_centroid", "voxel_bin", "write_ply",
]


@dataclass(frozen=True)
class MeshConfig:
    """Settings of the ``mesh`` stage (lengths relative to the cloud, so unit-free)."""

    # SfM points seen in fewer images than this are dropped (when read from the COLMAP model).
    min_track_length: int = setting(2, ">= 0")
    # SfM points with a larger mean reprojection error (pixels) are dropped; 0 keeps all.
    max_reprojection_error_px: float = setting(4.0, ">= 0")
    # Statistical outlier removal: neighbours per point, and the cut in standard deviations
    # of the mean neighbour distance (0 neighbours = off).
    outlier_neighbors: int = setting(16, ">= 0")
    outlier_std_ratio: float = setting(2.5, "> 0")
    # Points are binned (averaged) in voxels of this fraction of the median distance of the
    # points from the centre (0 = no binning).
    voxel_fraction: float = setting(0.02, "[0, 0.5)")
    # Direction grid of the radial fit: icosphere with 10·4^n + 2 vertices.
    icosphere_subdivisions: int = setting(5, "[1, 7]")
    # Smoothness of r(direction): shapes up to about this spherical-harmonic degree pass,
    # finer detail (below ~180°/degree) and noise are smoothed away. Larger = less smoothing.
    smooth_degree: float = setting(10.0, "> 0")
    # Where there are no points, the surface relaxes from the seen wall to the best-fitting
    # ellipsoid over about this angle (degrees, seen from the centre).
    hole_decay_deg: float = setting(20.0, "> 0")
    # Robust reweighting rounds (Huber) of the radial fit, and the Huber threshold in robust
    # standard deviations (1.4826·MAD) of the residuals.
    robust_iterations: int = setting(4, ">= 0")
    huber_k: float = setting(1.5, "> 0")
    # Points farther than this many robust standard deviations from the fit get no weight.
    reject_k: float = 4.0
    # Local relief (cystomap/mesh_relief.py): where the well-triangulated SfM points the smooth
    # fit rejected agree (their median residual around a direction beyond reject_k robust
    # standard deviations, into the cavity), the surface follows them: raised lesions stand out
    # of the wall. Off by default: on 36 FROC pairs it halved the centroid error of papillary
    # lesions but lost two lesions beside the neck (docs/measurements.md, "Raised lesions in the mesh").
    relief: bool = setting(False)
    # Refits about the volume centroid of the previous fit.
    center_iterations: int = setting(2, ">= 0")
    # Isotropic remeshing to even triangles (pymeshlab); the edge length is this fraction of
    # the mean radius (0 = keep the radial icosphere mesh).
    remesh_edge_fraction: float = setting(0.03, "[0, 0.5)")
    # Iterations of the isotropic remeshing.
    remesh_iterations: int = setting(4, ">= 1")
    # At least this many points must remain after filtering.
    min_points: int = setting(50, ">= 10")

    def __post_init__(self) -> None:
        validate(self, "mesh", {"reject_k > huber_k": self.reject_k > self.huber_k})


# --------------------------------------------------------------------------- stage entry point


def build_mesh(sfm_dir: Path, out_dir: Path, cfg: MeshConfig | None = None) -> Path:
    """Fit the closed wall surface to the SfM cloud in ``sfm_dir``; write ``out_dir``.

    Returns ``out_dir`` holding ``surface.ply`` and ``mesh.json``. Raises :class:`InputError`
    if the SfM output cannot be read and :class:`StageError` if no usable surface results.
    """
    cfg = cfg or MeshConfig()
    sfm_dir, out_dir = Path(sfm_dir), Path(out_dir)
    t0 = time.perf_counter()
    cloud = load_sparse_cloud(sfm_dir, cfg)
    log.info("%s: %d points read, %d kept after track/error filters", cloud.source,
             cloud.n_read, len(cloud.points))
    fit = fit_closed_surface(cloud.points, cfg, hint_centre=cloud.camera_centre,
                             relief_points=cloud.well_triangulated)
    verts, faces = fit.vertices, fit.faces
    topo = topology(verts, faces)
    if not (topo["watertight"] and topo["manifold"]):
        raise StageError(f"{sfm_dir}: the fitted surface is not closed and manifold ({topo})")
    normals = vertex_normals(verts, faces)
    dist_all = point_distances(verts, faces, cloud.all_points)
    dist_used = point_distances(verts, faces, cloud.points)
    bary = volume_centroid(verts, faces)
    vol = mesh_volume(verts, faces)
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    info: dict[str, Any] = {
        "units": "mm",
        "frame": "sfm",
        "method": "robust regularised radial fit about the barycentre (icosphere), "
                  "isotropic remeshing" if fit.remeshed else "robust regularised radial fit",
        "vertices": len(verts),
        "faces": len(faces),
        "watertight": topo["watertight"],
        "manifold": topo["manifold"],
        "genus": topo["genus"],
        "volume_ml": vol / 1000.0,
        "area_mm2": float(triangle_areas(verts, faces).sum()),
        "extents": (hi - lo).tolist(),
        "bbox_min": lo.tolist(),
        "bbox_max": hi.tolist(),
        "barycentre": bary.tolist(),
        "mean_radius": fit.mean_radius,
        "points_read": cloud.n_read,
        "points_filtered": len(cloud.points),
        "points_fitted": fit.n_fitted,
        "points_inlier_share": fit.inlier_share,
        "relief": fit.relief,
        "point_distance": _dist_stats(dist_all),
        "point_distance_filtered": _dist_stats(dist_used),
        "seconds": round(time.perf_counter() - t0, 2),
    }
    with atomic_dir(out_dir) as tmp:
        write_ply(tmp / "surface.ply", verts, faces, normals)
        write_json(tmp / "mesh.json", {**info, "software": software_versions()})
    log.info("%s: %d vertices, %d faces, %.1f ml, mean point distance %.3f mm (%.1f s)",
             out_dir / "surface.ply", len(verts), len(faces), vol / 1000.0,
             info["point_distance"]["mean"], info["seconds"])
    return out_dir


def _dist_stats(d: np.ndarray) -> dict[str, float]:
    if len(d) == 0:
        return {"n": 0, "mean": math.nan, "median": math.nan, "p95": math.nan}
    return {"n": len(d), "mean": float(d.mean()), "median": float(np.median(d)),
            "p95": float(np.percentile(d, 95))}


# --------------------------------------------------------------------------- reading the cloud


@dataclass(frozen=True)
class SparseCloud:
    source: Path
    points: np.ndarray  # (N, 3) after track-length / error filters
    all_points: np.ndarray  # (M, 3) every point read
    camera_centre: np.ndarray | None  # mean of the registered camera centres, if known
    n_read: int
    well_triangulated: np.ndarray  # (K, 3) the points the relief trusts (see load_sparse_cloud)


def load_sparse_cloud(sfm_dir: Path, cfg: MeshConfig) -> SparseCloud:
    """Points of the COLMAP model (filtered by track length and error) or of ``points.ply``."""
    if not sfm_dir.is_dir():
        raise InputError(f"SfM directory {sfm_dir} not found")
    if find_model_dir(sfm_dir) is not None:
        rec = load_reconstruction(sfm_dir)
        pts3d = list(rec.points3D.values())
        if not pts3d:
            raise InputError(f"{sfm_dir}: the COLMAP model has no 3-D points")
        xyz = np.array([p.xyz for p in pts3d], dtype=np.float64).reshape(-1, 3)
        err = np.array([p.error for p in pts3d], dtype=np.float64)
        track = np.array([p.track.length() for p in pts3d], dtype=np.int64)
        keep = np.ones(len(xyz), dtype=bool)
        if all(track == 0):  # a model without observations (e.g. points imported): keep all
            pass
        else:
            keep &= track >= cfg.min_track_length
            if cfg.max_reprojection_error_px > 0:
                keep &= ~(err > cfg.max_reprojection_error_px)
        centres = [img.projection_center() for img in rec.images.values() if img.has_pose]
        centre = np.mean(centres, axis=0) if centres else None
        # the relief trusts points triangulated at least as well as the cloud's median point
        # (reprojection error and track length): a cluster of floaters, triangulated from a few
        # close views at a common wrong depth, agrees with itself as well as a tumour's top does
        good = keep.copy()
        if keep.any() and not all(track == 0):
            good &= (err <= np.median(err[keep])) & (track >= np.median(track[keep]))
        return SparseCloud(sfm_dir, xyz[keep], xyz, centre, len(xyz), xyz[good])
    ply = sfm_dir / "points.ply"
    if not ply.is_file():
        raise InputError(f"{sfm_dir}: neither a COLMAP model nor points.ply found")
    import open3d as o3d

    xyz = np.asarray(o3d.io.read_point_cloud(str(ply)).points, dtype=np.float64)
    if len(xyz) == 0:
        raise InputError(f"{ply}: no points (unreadable or empty point cloud)")
    return SparseCloud(ply, xyz, xyz, None, len(xyz), xyz)


# --------------------------------------------------------------------------- the radial fit


@dataclass(frozen=True)
class SurfaceFit:
    vertices: np.ndarray
    faces: np.ndarray
    centre: np.ndarray
    mean_radius: float
    n_fitted: int
    inlier_share: float
    remeshed: bool
    relief: dict[str, Any]


def fit_closed_surface(
    points: np.ndarray, cfg: MeshConfig, hint_centre: np.ndarray | None = None,
    relief_points: np.ndarray | None = None,
) -> SurfaceFit:
    """Closed star-shaped surface fitted to ``points`` (see the module docstring); the local
    relief from ``relief_points`` (default: ``points`` after the outlier removal)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    points = points[np.isfinite(points).all(axis=1)]
    if len(points) < cfg.min_points:
        raise StageError(f"only {len(points)} usable SfM points (need {cfg.min_points})")
    points = remove_outliers(points, cfg)
    unbinned = points
    centre = initial_centre(points, hint_centre)
    scale = float(np.median(np.linalg.norm(points - centre, axis=1)))
    if cfg.voxel_fraction > 0:
        points = voxel_bin(points, cfg.voxel_fraction * scale)
    if len(points) < cfg.min_points:
        raise StageError(
            f"only {len(points)} SfM points left after filtering (need {cfg.min_points})")
    base = fit_ellipsoid(points)
    if base is None or not base.contains(centre):
        log.warning("no ellipsoid fits the cloud; unseen regions relax to a sphere")
        base = Ellipsoid.sphere(centre, scale)
    else:
        centre = base.centre
    sphere_v, sphere_f = icosphere(cfg.icosphere_subdivisions)
    lap = sphere_laplacian(sphere_v, sphere_f)
    radii = weights = None
    for it in range(cfg.center_iterations + 1):
        radii, weights = fit_radial(points, centre, sphere_v, sphere_f, lap, cfg, base)
        verts = centre + radii[:, None] * sphere_v
        new_centre = volume_centroid(verts, sphere_f)
        shift = float(np.linalg.norm(new_centre - centre))
        log.info("radial fit %d about %s: mean radius %.2f, centroid shift %.3f", it,
                 np.round(centre, 2).tolist(), radii.mean(), shift)
        if it == cfg.center_iterations or shift < 1e-3 * radii.mean():
            break
        if not base.contains(new_centre):
            break
        centre = new_centre
    assert radii is not None and weights is not None
    relief: dict[str, Any] = {"enabled": cfg.relief}
    if cfg.relief:
        # every point, not the voxels' means: a dome's top holds few
        pts = unbinned if relief_points is None else np.asarray(relief_points, np.float64)
        found = local_relief(pts, centre, sphere_v, sphere_f, radii, cfg.reject_k)
        log.info(relief_summary(found, float(radii.mean())))
        if np.all(radii + found.offset > 0):
            radii = radii + found.offset
            relief.update(found.info())
        else:
            log.warning("local relief left out: it would turn the surface inside out")
    verts = centre + radii[:, None] * sphere_v
    faces = sphere_f
    remeshed = False
    if cfg.remesh_edge_fraction > 0:
        try:
            rv, rf = isotropic_remesh(verts, faces, cfg.remesh_edge_fraction * float(radii.mean()),
                                      cfg.remesh_iterations)
        except Exception as exc:  # pymeshlab failures are not fatal: the radial mesh is valid
            log.warning("isotropic remeshing failed (%s); keeping the radial mesh", exc)
        else:
            topo = topology(rv, rf)
            if topo["watertight"] and topo["manifold"] and topo["genus"] == 0:
                verts, faces, remeshed = rv, rf, True
            else:
                log.warning("isotropic remeshing broke the topology (%s); keeping the radial mesh",
                            topo)
    return SurfaceFit(verts, faces, volume_centroid(verts, faces), float(radii.mean()),
                      len(points), float((weights > 0).mean()), remeshed, relief)


def remove_outliers(points: np.ndarray, cfg: MeshConfig) -> np.ndarray:
    """Statistical outlier removal (mean distance to the k nearest neighbours)."""
    if cfg.outlier_neighbors <= 0 or len(points) <= cfg.outlier_neighbors + 1:
        return points
    keep = statistical_inliers(points, cfg.outlier_neighbors, cfg.outlier_std_ratio)
    log.info("outlier removal: %d of %d points dropped", int((~keep).sum()), len(points))
    return points[keep]


def initial_centre(points: np.ndarray, hint: np.ndarray | None) -> np.ndarray:
    """A robust least-squares sphere centre; the camera centroid if the sphere is implausible."""
    centre = sphere_fit(points)
    med = np.median(points, axis=0)
    spread = float(np.median(np.linalg.norm(points - med, axis=1)))
    if centre is None or np.linalg.norm(centre - med) > 2.0 * spread:
        centre = hint if hint is not None else points.mean(axis=0)
    return np.asarray(centre, dtype=np.float64)


def fit_radial(
    points: np.ndarray,
    centre: np.ndarray,
    sphere_v: np.ndarray,
    sphere_f: np.ndarray,
    lap: sp.csr_matrix,
    cfg: MeshConfig,
    base: Ellipsoid,
) -> tuple[np.ndarray, np.ndarray]:
    """Radius per icosphere vertex about ``centre`` and the final weight of each point.

    r = ellipsoid + s: the ellipsoid ``base`` (fitted to all points) carries the global shape
    and is what unseen regions relax to; s is a smooth field (bending penalty) fitted to the
    residuals, pulled weakly to 0 far from data (decay over ``hole_decay_deg``).
    """
    rel = points - centre
    r_obs = np.linalg.norm(rel, axis=1)
    ok = r_obs > 1e-9 * max(float(r_obs.max()), 1e-300)
    rel, r_obs = rel[ok], r_obs[ok]
    dirs = rel / r_obs[:, None]
    a = direction_weights(dirs, sphere_v, sphere_f)
    n_v = len(sphere_v)
    lam = 1.0 / (cfg.smooth_degree * (cfg.smooth_degree + 1)) ** 2
    mu = lam / math.radians(cfg.hole_decay_deg) ** 4
    reg = ((lap.T @ lap) * lam + sp.identity(n_v) * mu) / n_v
    base_v = base.radius(centre, sphere_v)
    base_p = base.radius(centre, dirs)
    w = np.ones(len(r_obs))
    r = base_v
    for it in range(cfg.robust_iterations + 1):
        wn = w / w.sum()
        aw = a.T @ sp.diags(wn)
        lhs = (aw @ a + reg).tocsc()
        s = spla.spsolve(lhs, aw @ (r_obs - base_p))
        r = base_v + s
        res = a @ r - r_obs
        sigma = 1.4826 * float(np.median(np.abs(res))) + 1e-9 * float(np.median(r_obs))
        if it == cfg.robust_iterations:
            break
        ares = np.abs(res) / sigma
        w = np.where(ares <= cfg.huber_k, 1.0, cfg.huber_k / np.maximum(ares, 1e-12))
        w[ares > cfg.reject_k] = 0.0
    if not np.all(np.isfinite(r)) or r.min() <= 0:
        raise StageError("radial fit failed: the cloud is not star-shaped about its centre "
                         f"(radius range {np.nanmin(r):.3g}…{np.nanmax(r):.3g})")
    weights = np.zeros(len(ok))
    weights[ok] = w
    return r, weights


def isotropic_remesh(
    verts: np.ndarray, faces: np.ndarray, edge: float, iterations: int
) -> tuple[np.ndarray, np.ndarray]:
    import pymeshlab as ml

    ms = ml.MeshSet()
    ms.add_mesh(ml.Mesh(vertex_matrix=verts, face_matrix=faces.astype(np.int32)))
    ms.meshing_isotropic_explicit_remeshing(
        iterations=iterations, targetlen=ml.PureValue(edge), adaptive=False,
        maxsurfdist=ml.PureValue(0.25 * edge), checksurfdist=True)
    m = ms.current_mesh()
    return (np.asarray(m.vertex_matrix(), dtype=np.float64),
            np.asarray(m.face_matrix(), dtype=np.int64))


# --------------------------------------------------------------------------- mesh utilities


