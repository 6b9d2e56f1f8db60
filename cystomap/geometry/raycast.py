"""Ray casting and distances on a triangle mesh: the one wrapper of open3d's RaycastingScene.

open3d computes in float32, so the mesh is moved to about ``origin`` (by default the mean of
its vertices) before it is handed over, and every query is moved the same way: millimetre
bladders far from the SfM origin keep their precision.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def cast_rays(scene: Any, origins: np.ndarray, dirs: np.ndarray,
              nthreads: int = 0) -> dict[str, np.ndarray]:
    """Cast rays (float32) on an open3d scene: numpy t_hit, primitive_ids, primitive_uvs."""
    import open3d as o3d

    rays = np.empty((len(dirs), 6), np.float32)
    rays[:, :3] = origins
    rays[:, 3:] = dirs
    ans = scene.cast_rays(o3d.core.Tensor(rays), nthreads=nthreads)
    return {"t_hit": ans["t_hit"].numpy(), "primitive_ids": ans["primitive_ids"].numpy(),
            "primitive_uvs": ans["primitive_uvs"].numpy()}


class MeshRays:
    """Ray and distance queries on a triangle mesh (float32 about ``origin``)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray,
                 origin: np.ndarray | None = None) -> None:
        import open3d as o3d

        self._o3d = o3d
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.origin = self.vertices.mean(axis=0) if origin is None else np.asarray(origin, float)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor((self.vertices - self.origin).astype(np.float32)),
            o3d.core.Tensor(self.faces.astype(np.uint32)))
        a, b, c = (self.vertices[self.faces[:, i]] for i in range(3))
        n = np.cross(b - a, c - a)
        self.face_normals = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)

    def cast_raw(self, origins: np.ndarray, directions: np.ndarray,
                 nthreads: int = 0) -> dict[str, np.ndarray]:
        """open3d's answer (``t_hit``, ``primitive_ids``, ``primitive_uvs``, …) as numpy."""
        d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        o = np.broadcast_to(np.asarray(origins, dtype=np.float64) - self.origin, d.shape)
        return cast_rays(self.scene, o, d, nthreads)

    def cast(self, origins: np.ndarray, directions: np.ndarray,
             nthreads: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Hit distance along unit ``directions`` (inf if none) and face index (-1 if none)."""
        ans = self.cast_raw(origins, directions, nthreads)
        t = ans["t_hit"].astype(np.float64)
        tri = ans["primitive_ids"].astype(np.int64)
        miss = ~np.isfinite(t)
        tri[miss] = -1
        t[miss] = np.inf
        return t, tri

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance of each point to the mesh."""
        pts = (np.asarray(points, dtype=np.float64) - self.origin).astype(np.float32)
        if len(pts) == 0:
            return np.zeros(0)
        return self.scene.compute_distance(self._o3d.core.Tensor(pts)).numpy().astype(np.float64)

    def triangle_normals(self, tri: np.ndarray) -> np.ndarray:
        """Unit normals of the faces ``tri``."""
        return self.face_normals[np.asarray(tri, dtype=np.int64)]


def scene_of(vertices: np.ndarray, faces: np.ndarray) -> Any:
    """A bare open3d RaycastingScene of a mesh in its own coordinates (for renderers)."""
    return MeshRays(vertices, faces, origin=np.zeros(3)).scene
