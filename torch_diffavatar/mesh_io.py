"""Wavefront OBJ in/out for triangle meshes and garments (rest-shape UVs in metres)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torch_diffavatar.atomic_file import atomic_write, atomic_write_text
from torch_diffavatar.errors import InputError
from torch_diffavatar.pattern.garment_mesh import GarmentMesh


@dataclass
class ObjMesh:
    """A triangle mesh read from OBJ (0-based indices; polygons fan-triangulated).

    Attributes:
        verts: (V, 3) float64 positions.
        faces: (F, 3) int64 vertex indices.
        uv: (T, 2) float64 texture coordinates, or None.
        uv_faces: (F, 3) int64 indices into ``uv``, or None.
        normals: (N, 3) float64 normals, or None.
        normal_faces: (F, 3) int64 indices into ``normals``, or None.
    """

    verts: torch.Tensor
    faces: torch.Tensor
    uv: torch.Tensor | None = None
    uv_faces: torch.Tensor | None = None
    normals: torch.Tensor | None = None
    normal_faces: torch.Tensor | None = None


def _np(x, dtype) -> np.ndarray | None:
    if x is None:
        return None
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=dtype)


def write_obj(path, verts, faces, uv=None, uv_faces=None, normals=None) -> None:
    """Write a triangle mesh as OBJ.

    Args:
        path: output file.
        verts: (V, 3) positions.
        faces: (F, 3) 0-based vertex indices.
        uv: optional (T, 2) texture coordinates (``vt``).
        uv_faces: optional (F, 3) 0-based indices into ``uv``; defaults to ``faces`` (then T must be V).
        normals: optional (V, 3) per-vertex normals (``vn``, indexed like the vertices).
    """
    v = _np(verts, np.float64)
    f = _np(faces, np.int64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"verts must be (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or (len(f) and (f.min() < 0 or f.max() >= len(v))):
        raise ValueError(f"faces must be (F, 3) indices in [0, {len(v)}), got shape {f.shape}")
    t = _np(uv, np.float64)
    tf = _np(uv_faces, np.int64) if uv_faces is not None else (f if t is not None else None)
    if t is not None and (t.ndim != 2 or t.shape[1] != 2 or tf.shape != f.shape or tf.max() >= len(t)):
        raise ValueError("uv must be (T, 2) and uv_faces (F, 3) indices into it")
    n = _np(normals, np.float64)
    if n is not None and n.shape != v.shape:
        raise ValueError(f"normals must be (V, 3) like verts, got {n.shape}")
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in v]
    if t is not None:
        lines += [f"vt {a:.9g} {b:.9g}" for a, b in t]
    if n is not None:
        lines += [f"vn {a:.6g} {b:.6g} {c:.6g}" for a, b, c in n]
    f1 = f + 1
    if t is not None and n is not None:
        t1 = tf + 1
        lines += [f"f {a}/{ta}/{a} {b}/{tb}/{b} {c}/{tc}/{c}" for (a, b, c), (ta, tb, tc) in zip(f1, t1)]
    elif t is not None:
        t1 = tf + 1
        lines += [f"f {a}/{ta} {b}/{tb} {c}/{tc}" for (a, b, c), (ta, tb, tc) in zip(f1, t1)]
    elif n is not None:
        lines += [f"f {a}//{a} {b}//{b} {c}//{c}" for a, b, c in f1]
    else:
        lines += [f"f {a} {b} {c}" for a, b, c in f1]
    atomic_write_text(path, "\n".join(lines) + "\n")


def read_obj(path: str | os.PathLike) -> ObjMesh:
    """Read ``v``, ``vt``, ``vn`` and ``f`` records of an OBJ file (other records are ignored).

    Raises:
        InputError: missing file or malformed records (with the line number).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: OBJ file not found")
    v, vt, vn, fv, ft, fn = [], [], [], [], [], []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        try:
            if parts[0] == "v":
                v.append([float(x) for x in parts[1:4]])
            elif parts[0] == "vt":
                vt.append([float(x) for x in parts[1:3]])
            elif parts[0] == "vn":
                vn.append([float(x) for x in parts[1:4]])
            elif parts[0] == "f":
                corners = [c.split("/") for c in parts[1:]]
                if len(corners) < 3:
                    raise ValueError("a face needs 3 corners")

                def idx(s: str, count: int) -> int:
                    i = int(s)
                    return i - 1 if i > 0 else count + i

                vi = [idx(c[0], len(v)) for c in corners]
                ti = [idx(c[1], len(vt)) if len(c) > 1 and c[1] else -1 for c in corners]
                ni = [idx(c[2], len(vn)) if len(c) > 2 and c[2] else -1 for c in corners]
                for k in range(1, len(corners) - 1):  # fan triangulation
                    fv.append([vi[0], vi[k], vi[k + 1]])
                    ft.append([ti[0], ti[k], ti[k + 1]])
                    fn.append([ni[0], ni[k], ni[k + 1]])
        except (ValueError, IndexError) as exc:
            raise InputError(f"{path}:{lineno}: malformed OBJ record {line.strip()!r} ({exc})") from exc
    verts = torch.tensor(v, dtype=torch.float64).reshape(-1, 3)
    faces = torch.tensor(fv, dtype=torch.int64).reshape(-1, 3)
    if len(faces) and (faces.min() < 0 or faces.max() >= len(verts)):
        raise InputError(f"{path}: face vertex index out of range (file has {len(verts)} vertices)")
    out = ObjMesh(verts, faces)
    ft_t = torch.tensor(ft, dtype=torch.int64).reshape(-1, 3)
    if vt and len(ft_t) and bool((ft_t >= 0).all()):
        out.uv, out.uv_faces = torch.tensor(vt, dtype=torch.float64).reshape(-1, 2), ft_t
    fn_t = torch.tensor(fn, dtype=torch.int64).reshape(-1, 3)
    if vn and len(fn_t) and bool((fn_t >= 0).all()):
        out.normals, out.normal_faces = torch.tensor(vn, dtype=torch.float64).reshape(-1, 3), fn_t
    return out


def write_garment_obj(path, garment: GarmentMesh, sim_positions: torch.Tensor | None = None) -> None:
    """Write a garment: ``v`` = sim vertices, ``vt`` = 2D rest coordinates [m] (one per panel vertex).

    Faces are ``f v/vt`` with v the sim vertex and vt the panel vertex of each corner, so the file keeps
    both the sewn 3D surface and every panel's flat rest shape.

    Args:
        path: output file.
        garment: the meshed pattern.
        sim_positions: (Vs, 3) positions [m]; default: the initial placement (`GarmentMesh.sim_positions`).
    """
    pos = garment.sim_positions() if sim_positions is None else sim_positions
    if tuple(pos.shape) != (garment.sim_vert_count, 3):
        raise ValueError(f"sim_positions must be ({garment.sim_vert_count}, 3), got {tuple(pos.shape)}")
    write_obj(path, pos, garment.sim_faces, uv=garment.vert_uv, uv_faces=garment.tri_vertices)


def write_ply(path, verts: np.ndarray, faces: np.ndarray) -> None:
    """Write a triangle mesh as binary little-endian PLY (float32 vertices, uint8-count int32 faces): half
    the size of float64, for meshes written every frame (`animate`'s body)."""
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(verts)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    face_rec = np.zeros(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face_rec["n"], face_rec["i"] = 3, faces
    with atomic_write(path) as fh:
        fh.write(header.encode("ascii"))
        fh.write(np.ascontiguousarray(verts, dtype="<f4").tobytes())
        fh.write(face_rec.tobytes())
