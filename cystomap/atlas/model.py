"""Textured 3-D model: atlas UVs on the surface mesh, written as OBJ (+ MTL) and glTF 2.0 GLB.

Texture coordinates come from the atlas projection (u = column, v = row, both in [0, 1]). Two
places need care, both solved by cutting the mesh along meridians (half-planes through the
polar axis of the atlas frame) before assigning UVs:

* the seam at azimuth ±180°: the mesh is cut along it and the cut vertices get u = 0 on one
  side and u = 1 on the other, so no triangle spans the whole texture;
* the poles, where all azimuths meet: a vertex is inserted where the polar axis pierces the
  mesh, and the mesh is also cut every ``meridian_step_deg`` degrees of azimuth, so the
  triangles around a pole are thin wedges whose u-span is at most that step (the pole vertex
  takes the wedge's mid-azimuth).

The cut mesh is the same surface (cut vertices lie on the original edges; no T-junctions).
"""

from __future__ import annotations

import json
import logging
import math
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cystomap.atlas.projection import Projection, SurfaceRays

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TexturedMesh:
    """Positions (V, 3) and outward normals shared by wedges; per-corner UVs (F, 3, 2)."""

    vertices: np.ndarray
    normals: np.ndarray
    faces: np.ndarray
    corner_uv: np.ndarray  # u right, v down (glTF convention), in [0, 1]

    def max_u_span(self) -> float:
        u = self.corner_uv[..., 0]
        return float((u.max(axis=1) - u.min(axis=1)).max())

    def wedges(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-vertex arrays for formats that need them: (vertex index, uv, faces)."""
        key_uv = np.round(self.corner_uv.reshape(-1, 2) * 2**24).astype(np.int64)
        keys = np.column_stack([self.faces.reshape(-1), key_uv])
        uniq, first, inv = np.unique(keys, axis=0, return_index=True, return_inverse=True)
        uv = self.corner_uv.reshape(-1, 2)[first]
        return uniq[:, 0], uv, inv.reshape(-1, 3)


def uv_unwrap(
    vertices: np.ndarray, faces: np.ndarray, proj: Projection, meridian_step_deg: float = 15.0
) -> TexturedMesh:
    """Cut the mesh at the seam, the poles and every ``meridian_step_deg``; assign atlas UVs."""
    from cystomap.geometry.trimesh import vertex_normals

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    scale = float(np.linalg.norm(v - proj.barycentre, axis=1).mean())
    v, f = _insert_poles(v, f, proj)
    n_cuts = max(1, round(360.0 / meridian_step_deg))
    for k in range(n_cuts):
        phi = -math.pi + k * 2 * math.pi / n_cuts
        v, f = _cut_half_plane(v, f, proj, phi, 1e-9 * scale)
    q = (v - proj.barycentre) @ proj.axes.T
    rxy = np.hypot(q[:, 0], q[:, 1])
    on_axis = rxy <= 1e-7 * scale
    az = np.arctan2(q[:, 1], q[:, 0])
    el = np.arctan2(q[:, 2], rxy)
    centroid = q[f].mean(axis=1)
    az_ref = np.arctan2(centroid[:, 1], centroid[:, 0])
    az_c = az[f]
    az_c = az_c + 2 * np.pi * np.round((az_ref[:, None] - az_c) / (2 * np.pi))
    axis_c = on_axis[f]
    if axis_c.any():  # pole vertices: the mid-azimuth of the face's other corners
        others = np.where(axis_c, np.nan, az_c)
        mid = np.nanmean(np.where(np.isnan(others).all(axis=1, keepdims=True), 0.0, others), axis=1)
        az_c = np.where(axis_c, mid[:, None], az_c)
    col, row = proj.angles_to_pixel(az_c, el[f])
    uv = np.stack([(col + 0.5) / proj.width, (row + 0.5) / proj.height], axis=-1)
    uv = np.clip(uv, 0.0, 1.0)
    return TexturedMesh(v, vertex_normals(v, f), f, uv)


def _insert_poles(v: np.ndarray, f: np.ndarray, proj: Projection) -> tuple[np.ndarray, np.ndarray]:
    """Split the faces pierced by the polar axis with a vertex at the piercing point."""
    rays = SurfaceRays(v, f, origin=proj.barycentre)
    for sign in (1.0, -1.0):
        d = sign * proj.axes[2]
        t, tri = rays.cast(proj.barycentre, d[None])
        if tri[0] < 0:
            log.warning("the polar axis (%+d) misses the mesh; pole not inserted", int(sign))
            continue
        p = proj.barycentre + t[0] * d
        a, b, c = f[tri[0]]
        new = len(v)
        v = np.vstack([v, p])
        f = np.vstack([np.delete(f, tri[0], axis=0), [[a, b, new], [b, c, new], [c, a, new]]])
    return v, f


def _cut_half_plane(
    v: np.ndarray, f: np.ndarray, proj: Projection, phi: float, eps: float
) -> tuple[np.ndarray, np.ndarray]:
    """Split the faces crossed by the meridian half-plane at azimuth ``phi``."""
    q = (v - proj.barycentre) @ proj.axes.T
    normal = np.array([-math.sin(phi), math.cos(phi), 0.0])
    inward = np.array([math.cos(phi), math.sin(phi), 0.0])
    s = q @ normal
    s[np.abs(s) <= eps] = 0.0
    side = np.sign(s)
    fs = side[f]
    cand = np.flatnonzero((fs.max(axis=1) > 0) & (fs.min(axis=1) < 0))
    if len(cand) == 0:
        return v, f
    new_pts: list[np.ndarray] = []
    edge_vertex: dict[tuple[int, int], int] = {}

    def crossing(i: int, j: int) -> int | None:
        if side[i] * side[j] >= 0:
            return None
        key = (min(i, j), max(i, j))
        if key in edge_vertex:
            return edge_vertex[key]
        w = s[i] / (s[i] - s[j])
        x = q[i] + w * (q[j] - q[i])
        if x @ inward <= 0:
            return None
        edge_vertex[key] = len(v) + len(new_pts)
        new_pts.append(v[i] + w * (v[j] - v[i]))
        return edge_vertex[key]

    out_faces: list[list[int]] = []
    drop: list[int] = []
    for fi in cand:
        a, b, c = (int(x) for x in f[fi])
        tri = (a, b, c)
        xs = [crossing(tri[k], tri[(k + 1) % 3]) for k in range(3)]
        n_cross = sum(x is not None for x in xs)
        if n_cross == 2:
            k = next(k for k in range(3) if xs[k] is not None and xs[(k + 2) % 3] is not None)
            # the vertex tri[k] is alone on its side: edges (k, k+1) and (k+2, k) are crossed
            p0, p1, p2 = tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]
            x01, x20 = xs[k], xs[(k + 2) % 3]
            assert x01 is not None and x20 is not None
            out_faces += [[p0, x01, x20], [x01, p1, p2], [x01, p2, x20]]
            drop.append(fi)
        elif n_cross == 1:
            k = next(k for k in range(3) if xs[k] is not None)
            p0, p1, p2 = tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]
            x01 = xs[k]
            assert x01 is not None
            if side[p2] == 0:
                out_faces += [[p0, x01, p2], [x01, p1, p2]]
                drop.append(fi)
            else:  # the half-plane ends inside this face (pole not inserted): leave it
                log.debug("face %d: meridian %.1f° ends inside it", fi, math.degrees(phi))
    if not drop:
        return v, f
    f = np.vstack([np.delete(f, drop, axis=0), np.asarray(out_faces, dtype=np.int64)])
    return np.vstack([v, np.asarray(new_pts).reshape(-1, 3)]), f


# --------------------------------------------------------------------------- writers


def write_obj(out_dir: Path, mesh: TexturedMesh, texture_name: str = "texture.png",
              stem: str = "model") -> Path:
    """``stem.obj`` + ``stem.mtl`` referring to ``texture_name`` (OBJ v = 1 − glTF v)."""
    obj, mtl = out_dir / f"{stem}.obj", out_dir / f"{stem}.mtl"
    mtl.write_text(
        "# cystomap textured bladder wall\n"
        "newmtl wall\nKa 1.000 1.000 1.000\nKd 1.000 1.000 1.000\nKs 0.000 0.000 0.000\n"
        f"d 1.0\nillum 1\nmap_Kd {texture_name}\n"
    )
    uv = mesh.corner_uv.reshape(-1, 2)
    key = np.round(uv * 2**24).astype(np.int64)
    _, first, uv_idx = np.unique(key, axis=0, return_index=True, return_inverse=True)
    uv_u = uv[first]
    uv_idx = uv_idx.reshape(-1, 3) + 1
    fv = mesh.faces + 1
    lines = [f"# cystomap textured bladder wall (mm, SfM frame)\nmtllib {mtl.name}\no wall\n"]
    lines.append(_rows("v", mesh.vertices, "%.5f"))
    lines.append(_rows("vt", np.column_stack([uv_u[:, 0], 1.0 - uv_u[:, 1]]), "%.7f"))
    lines.append(_rows("vn", mesh.normals, "%.5f"))
    lines.append("usemtl wall\ns 1\n")
    cols = np.stack([fv, uv_idx, fv], axis=-1).reshape(len(fv), 9)
    lines.append(_rows("f", cols, "%d/%d/%d %d/%d/%d %d/%d/%d", joined=True))
    obj.write_text("".join(lines))
    return obj


def _rows(tag: str, arr: np.ndarray, fmt: str, joined: bool = False) -> str:
    if len(arr) == 0:
        return ""
    if joined:
        row_fmt = f"{tag} {fmt}\n"
    else:
        row_fmt = f"{tag} " + " ".join([fmt] * arr.shape[1]) + "\n"
    return "".join(row_fmt % tuple(r) for r in arr.tolist())


def write_glb(path: Path, mesh: TexturedMesh, texture_png: bytes, name: str = "bladder wall",
              unit_scale: float = 0.001) -> Path:
    """A self-contained glTF 2.0 binary: one textured, double-sided primitive.

    Positions are stored in mm; the node scales them by ``unit_scale`` (glTF's unit is the
    metre). The texture wraps around in u (azimuth is periodic) and is clamped in v.
    """
    vidx, uv, faces = mesh.wedges()
    pos = mesh.vertices[vidx].astype("<f4")
    nrm = mesh.normals[vidx].astype("<f4")
    tex = uv.astype("<f4")
    idx = faces.astype("<u4").reshape(-1)
    blobs = [pos.tobytes(), nrm.tobytes(), tex.tobytes(), idx.tobytes(), texture_png]
    views, offset, binary = [], 0, bytearray()
    targets = [34962, 34962, 34962, 34963, None]
    for blob, target in zip(blobs, targets, strict=True):
        pad = (-offset) % 4
        binary += b"\x00" * pad
        offset += pad
        view = {"buffer": 0, "byteOffset": offset, "byteLength": len(blob)}
        if target is not None:
            view["target"] = target
        views.append(view)
        binary += blob
        offset += len(blob)
    binary += b"\x00" * ((-len(binary)) % 4)
    doc = {
        "asset": {"version": "2.0", "generator": "cystomap"},
        "scene": 0,
        "scenes": [{"name": name, "nodes": [0]}],
        "nodes": [{"name": name, "mesh": 0, "scale": [unit_scale] * 3}],
        "meshes": [{"name": name, "primitives": [{
            "attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2},
            "indices": 3, "material": 0, "mode": 4}]}],
        "materials": [{"name": "wall", "doubleSided": True, "pbrMetallicRoughness": {
            "baseColorTexture": {"index": 0}, "metallicFactor": 0.0, "roughnessFactor": 1.0}}],
        "textures": [{"sampler": 0, "source": 0}],
        "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 10497, "wrapT": 33071}],
        "images": [{"bufferView": 4, "mimeType": "image/png", "name": "atlas"}],
        "buffers": [{"byteLength": len(binary)}],
        "bufferViews": views,
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": len(pos), "type": "VEC3",
             "min": pos.min(axis=0).tolist(), "max": pos.max(axis=0).tolist()},
            {"bufferView": 1, "componentType": 5126, "count": len(nrm), "type": "VEC3"},
            {"bufferView": 2, "componentType": 5126, "count": len(tex), "type": "VEC2"},
            {"bufferView": 3, "componentType": 5125, "count": len(idx), "type": "SCALAR",
             "min": [int(idx.min())], "max": [int(idx.max())]},
        ],
    }
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * ((-len(js)) % 4)
    total = 12 + 8 + len(js) + 8 + len(binary)
    with open(path, "wb") as fh:
        fh.write(struct.pack("<4sII", b"glTF", 2, total))
        fh.write(struct.pack("<I4s", len(js), b"JSON"))
        fh.write(js)
        fh.write(struct.pack("<I4s", len(binary), b"BIN\x00"))
        fh.write(bytes(binary))
    return path


def read_glb(path: Path) -> tuple[dict, bytes]:
    """The JSON document and binary chunk of a GLB (for checks and tests)."""
    data = Path(path).read_bytes()
    magic, version, total = struct.unpack_from("<4sII", data, 0)
    if magic != b"glTF" or version != 2 or total != len(data):
        raise ValueError(f"{path}: not a glTF 2.0 binary")
    jlen, jtype = struct.unpack_from("<I4s", data, 12)
    doc = json.loads(data[20 : 20 + jlen])
    blen, btype = struct.unpack_from("<I4s", data, 20 + jlen)
    if jtype != b"JSON" or btype != b"BIN\x00":
        raise ValueError(f"{path}: unexpected chunk types")
    return doc, data[28 + jlen : 28 + jlen + blen]
