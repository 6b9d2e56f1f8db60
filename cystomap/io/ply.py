"""PLY files: the one writer (meshes and point clouds, binary little-endian) and mesh reading."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cystomap.errors import InputError


def write_ply(path: Path, verts: np.ndarray, faces: np.ndarray | None = None,
              normals: np.ndarray | None = None, colors: np.ndarray | None = None,
              comment: str = "cystomap mesh (mm)") -> Path:
    """Binary little-endian PLY: float x y z (nx ny nz) (uchar red green blue), int faces.

    ``faces`` None writes a point cloud (no face element).
    """
    verts = np.asarray(verts)
    props = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    columns = [verts]
    if normals is not None:
        props += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
        columns.append(np.asarray(normals))
    if colors is not None:
        props += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        columns.append(np.asarray(colors))
    vdata = np.empty(len(verts), dtype=props)
    names = iter(n for n, _ in props)
    for col in columns:
        for i in range(3):
            vdata[next(names)] = col[:, i]
    kind = {"<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", f"comment {comment}",
              f"element vertex {len(verts)}", *(f"property {kind[t]} {n}" for n, t in props)]
    fdata = None
    if faces is not None:
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
        fdata = np.empty(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
        fdata["n"] = 3
        fdata["i"] = faces
    header.append("end_header")
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(vdata.tobytes())
        if fdata is not None:
            fh.write(fdata.tobytes())
    return path


def read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (float64) and faces (int64) of a triangle mesh file; InputError if unusable."""
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise InputError(f"mesh {path} not found")
    m = o3d.io.read_triangle_mesh(str(path))
    v = np.asarray(m.vertices, dtype=np.float64)
    f = np.asarray(m.triangles, dtype=np.int64)
    if len(v) == 0 or len(f) == 0:
        raise InputError(f"mesh {path}: no triangles (not a triangle mesh, or unreadable)")
    return v, f
