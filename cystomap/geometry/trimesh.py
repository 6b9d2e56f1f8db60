"""Measures of a triangle mesh: face areas, enclosed volume and its centroid, vertex normals,
topology (pymeshlab), point-to-surface distances."""

from __future__ import annotations

from typing import Any

import numpy as np

from cystomap.geometry.raycast import MeshRays


def triangle_areas(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    a, b, c = (verts[faces[:, i]] for i in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def mesh_volume(verts: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume of a closed mesh (positive for outward-oriented faces)."""
    a, b, c = (verts[faces[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def volume_centroid(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Centre of mass of the solid bounded by a closed mesh."""
    o = verts.mean(axis=0)
    a, b, c = (verts[faces[:, i]] - o for i in range(3))
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    total = vol.sum()
    if abs(total) < 1e-300:
        return o
    return o + ((a + b + c) / 4.0 * vol[:, None]).sum(axis=0) / total


def vertex_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    a, b, c = (verts[faces[:, i]] for i in range(3))
    fn = np.cross(b - a, c - a)
    vn = np.zeros_like(verts)
    for i in range(3):
        np.add.at(vn, faces[:, i], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)


def topology(verts: np.ndarray, faces: np.ndarray) -> dict[str, Any]:
    """Watertight (no boundary edge), two-manifold (edges and vertices), genus (pymeshlab)."""
    import pymeshlab as ml

    ms = ml.MeshSet()
    ms.add_mesh(ml.Mesh(vertex_matrix=verts, face_matrix=faces.astype(np.int32)))
    t = ms.get_topological_measures()
    manifold = bool(t["is_mesh_two_manifold"]) and t["non_two_manifold_vertices"] == 0
    return {
        "watertight": manifold and t["boundary_edges"] == 0 and t["number_holes"] == 0,
        "manifold": manifold,
        "genus": int(t["genus"]),
        "components": int(t["connected_components_number"]),
    }


def point_distances(verts: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Unsigned distance of each point to the mesh (open3d, float32 about the mesh centre)."""
    if len(points) == 0:
        return np.zeros(0)
    return MeshRays(verts, faces).distance(points)
