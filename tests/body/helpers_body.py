"""Shared by the segmentation tests: points sampled on the default Anny body, with their body parts."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class SampledBody:
    """The default body and points sampled evenly on it.

    Attributes:
        verts: (Vb, 3) [m]; faces: (Fb, 3); parts: (Vb,) index into `PART_NAMES`; waist: its
            `BodyModel.waist_height` [m].
        points: (N, 3) [m] on the surface; normals: (N, 3) their faces' unit normals; name: (N,) the part
            name of each point's face.
    """

    verts: np.ndarray
    faces: np.ndarray
    parts: np.ndarray
    waist: float
    points: np.ndarray
    normals: np.ndarray
    name: np.ndarray


def sampled_default_body(anny_model, count: int = 20000, seed: int = 0) -> SampledBody:
    """``count`` points sampled evenly (``seed``) on the default `BodyModel` of ``anny_model``."""
    import torch
    import trimesh

    from torch_diffavatar.body.model import BodyModel
    from torch_diffavatar.body.parts import PART_NAMES, vertex_parts

    body = BodyModel(anny_model=anny_model)
    with torch.no_grad():
        out = body()
    verts, faces = out.vertices[0].double().numpy(), body.faces.numpy()
    mesh = trimesh.Trimesh(verts, faces, process=False)
    points, face = trimesh.sample.sample_surface_even(mesh, count, seed=seed)
    parts = vertex_parts(anny_model).numpy()
    name = np.array(PART_NAMES)[parts[faces[face, 0]]]
    waist = body.waist_height(out.joints[0])
    return SampledBody(verts, faces, parts, waist, points, mesh.face_normals[face], name)
