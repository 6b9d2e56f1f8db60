"""Functions on the unit sphere sampled on an icosphere: the grid, its Laplacian, and the
barycentric interpolation of vertex values at arbitrary directions (the mesh stage's radial fit)."""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp

from cystomap.geometry.raycast import MeshRays


def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere (vertices on the sphere, outward-oriented faces)."""
    t = (1 + math.sqrt(5)) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                  [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                  [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                  [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        uniq, inv = np.unique(edges, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        mid = v[uniq[:, 0]] + v[uniq[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = len(f)
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        ab, bc, ca = (inv[:m] + len(v), inv[m : 2 * m] + len(v), inv[2 * m :] + len(v))
        f = np.concatenate([np.stack([a, ab, ca], 1), np.stack([b, bc, ab], 1),
                            np.stack([c, ca, bc], 1), np.stack([ab, bc, ca], 1)])
        v = np.vstack([v, mid])
    return v, f


def mesh_edges(f: np.ndarray) -> np.ndarray:
    """(E, 2) unique undirected edges of the triangles ``f``, each as (smaller, larger)."""
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def vertex_adjacency(f: np.ndarray, n: int) -> sp.csr_matrix:
    """Sparse (n, n) 0/1 adjacency of the vertices of the triangles ``f``."""
    e = mesh_edges(f)
    return sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                         shape=(n, n)).tocsr()


def sphere_laplacian(v: np.ndarray, f: np.ndarray) -> sp.csr_matrix:
    """Uniform graph Laplacian scaled to approximate Laplace-Beltrami on the unit sphere."""
    n = len(v)
    e = mesh_edges(f)
    adj = vertex_adjacency(f, n)
    deg = np.asarray(adj.sum(axis=1)).ravel()
    h = float(np.mean(np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)))
    # On a regular triangular grid of spacing h: mean(neighbours) - f ≈ h²/4 · Δf.
    return (4.0 / h**2) * (sp.diags(1.0 / deg) @ adj - sp.identity(n)).tocsr()


def direction_weights(
    dirs: np.ndarray, sphere_v: np.ndarray, sphere_f: np.ndarray
) -> sp.csr_matrix:
    """Sparse (N, V) barycentric interpolation of vertex values at unit directions ``dirs``."""
    ans = MeshRays(sphere_v, sphere_f, origin=np.zeros(3)).cast_raw(np.zeros(3), dirs)
    tri = ans["primitive_ids"].astype(np.int64)
    uv = ans["primitive_uvs"].astype(np.float64)
    miss = tri >= len(sphere_f)  # INVALID_ID: only for degenerate directions
    tri[miss] = 0
    bary = np.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
    bary[miss] = 1.0 / 3.0
    rows = np.repeat(np.arange(len(dirs)), 3)
    return sp.csr_matrix((bary.ravel(), (rows, sphere_f[tri].ravel())),
                         shape=(len(dirs), len(sphere_v)))
