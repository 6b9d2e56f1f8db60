"""The report's interactive 3-D views: the surface mesh coloured from an atlas-projected image.

The textured model of the atlas stage carries the atlas as a texture; the report's viewer
(plotly.js ``mesh3d``) colours vertices instead. So the session's surface mesh is subdivided
(or simplified) to about ``model_vertices`` vertices and every vertex takes the colour of the
atlas pixel its direction from the atlas barycentre falls in (the atlas projection contract of
``atlas.json``), from a copy of the atlas smoothed to the vertex spacing (no aliasing).

Geometry and colours are stored compactly (base64 of little-endian float32 / uint32 / uint8
arrays) and turned into plotly traces by the report's script; views of the same mesh share
its geometry (session B's model and its changes highlighted).
"""

from __future__ import annotations

import base64
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cystomap.atlas.projection import Projection
from cystomap.images import sample_bilinear

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Geometry:
    """A triangle mesh for the viewer: float32 vertices (n, 3), uint32 faces (m, 3)."""

    vertices: np.ndarray
    faces: np.ndarray

    @property
    def mean_edge(self) -> float:
        v, f = self.vertices.astype(np.float64), self.faces
        if not len(f):
            return 0.0
        e = np.concatenate([v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 1]], v[f[:, 0]] - v[f[:, 2]]])
        return float(np.linalg.norm(e, axis=1).mean())

    def to_json(self) -> dict[str, Any]:
        """Compact form: positions quantised to 16 bits over the bounding box (about 0.003 mm
        on a 170 mm bladder), face indices 16-bit when there are fewer than 65536 vertices."""
        v = self.vertices.astype(np.float64)
        lo = v.min(axis=0) if len(v) else np.zeros(3)
        hi = v.max(axis=0) if len(v) else np.ones(3)
        step = np.maximum(hi - lo, 1e-9) / 65535.0
        q = np.clip(np.rint((v - lo) / step), 0, 65535).astype("<u2")
        small = len(v) < 65536
        faces = self.faces.astype("<u2" if small else "<u4")
        return {"n": len(v), "m": len(self.faces), "origin": lo.tolist(), "step": step.tolist(),
                "positions": _b64(q), "index_bits": 16 if small else 32, "faces": _b64(faces)}


@dataclass(frozen=True)
class Marker:
    """A labelled point drawn over a 3-D view (a change's centroid)."""

    xyz: tuple[float, float, float]
    label: str
    hover: str


@dataclass(frozen=True)
class View:
    """One 3-D view: a geometry (by key), per-vertex RGB and optional markers."""

    geometry: str
    colours: np.ndarray  # (n, 3) uint8
    markers: list[Marker] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"geometry": self.geometry, "colours": _b64(self.colours.astype(np.uint8)),
                "markers": [{"x": m.xyz[0], "y": m.xyz[1], "z": m.xyz[2], "label": m.label,
                             "hover": m.hover} for m in self.markers]}


def _b64(arr: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(arr).tobytes()).decode("ascii")


def load_geometry(mesh_ply: Path, target_vertices: int) -> Geometry:
    """The surface mesh, midpoint-subdivided while it stays within ``target_vertices``, or
    quadric-simplified to about that many vertices when it has more."""
    import open3d as o3d

    from cystomap.mesh import read_mesh

    v, f = read_mesh(mesh_ply)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(f))
    n0 = len(v)
    if n0 > target_vertices:
        mesh = mesh.simplify_quadric_decimation(target_number_of_triangles=max(4, 2 * target_vertices - 4))
    else:
        n = n0
        while n * 4 <= target_vertices:
            mesh = mesh.subdivide_midpoint(number_of_iterations=1)
            n = len(mesh.vertices)
    verts = np.asarray(mesh.vertices, dtype=np.float32)
    faces = np.asarray(mesh.triangles, dtype=np.uint32)
    log.info("3-D view of %s: %d -> %d vertices, %d faces", mesh_ply, n0, len(verts), len(faces))
    return Geometry(verts, faces)


def vertex_colours(geometry: Geometry, proj: Projection, rgb: np.ndarray) -> np.ndarray:
    """(n, 3) uint8: the colour of ``rgb`` (an image in the atlas projection ``proj``, any
    size) at each vertex, smoothed over about one vertex spacing."""
    import cv2

    h, w = rgb.shape[:2]
    v = geometry.vertices.astype(np.float64)
    radius = float(np.median(np.linalg.norm(v - proj.barycentre, axis=1))) if len(v) else 1.0
    spacing_rad = geometry.mean_edge / max(radius, 1e-9)
    pixels_per_vertex = spacing_rad / (2 * math.pi / w)
    img = rgb
    if pixels_per_vertex > 1.5:
        new_w = max(8, round(w / pixels_per_vertex))
        new_h = max(4, round(h * new_w / w))
        img = cv2.resize(rgb, (new_w, new_h), interpolation=cv2.INTER_AREA)
    ih, iw = img.shape[:2]
    # The contract is for the full-size atlas; rescale continuous pixel coordinates.
    scaled = Projection(proj.kind, iw, ih, proj.barycentre, proj.axes)
    col, row = scaled.point_to_pixel(v)
    out = sample_bilinear(img, col, row, wrap_columns=True)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def lifted(points: np.ndarray, centre: np.ndarray, fraction: float = 0.04) -> np.ndarray:
    """Points moved outwards from ``centre`` by ``fraction`` of their distance (markers on
    the wall stay visible from outside the model)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    return centre + (p - centre) * (1 + fraction)
