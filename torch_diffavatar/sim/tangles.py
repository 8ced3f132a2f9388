"""Cloth edges that pass through the body: a drape tangled with a part thinner than its edges.

The contacts keep cloth *vertices* outside the body (`collision`); an edge whose two vertices lie on either
side of a part thinner than the edge (toes, fingers) passes through that part unseen. Such a drape is
tangled: when the part moves it drags the edge along, friction holds the vertices on either side, and the
cloth tears there. The fit of a captured pair of trousers whose legs pooled over the feet carried such
edges through the toes from its first drape to its result (8 there), and blew up 0.27 s into a walk;
without friction the same drape walked (docs/BENCHMARKS.md, "Floor-length trousers in a walk").
"""

from __future__ import annotations

import numpy as np
import torch

NEAR_BODY = 0.02  # [m]: the ends of a tangled edge lie within the cloth's thickness of the body (3 mm)


def mesh_edges(faces: torch.Tensor) -> torch.Tensor:
    """(E, 2) int64 the distinct edges (lower index first) of the triangles ``faces`` (F, 3)."""
    f = faces.to(torch.int64)
    e = torch.cat((f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]])).sort(dim=1).values
    return torch.unique(e, dim=0)


def edges_through_body(
    x: torch.Tensor, faces: torch.Tensor, body_verts: torch.Tensor, body_faces: torch.Tensor
) -> torch.Tensor:
    """The cloth edges that pass through a part of the body thinner than they are: each enters the body by
    one face and leaves it by a face turned away from that one (their normals more than 90° apart). An edge
    that clips a rounded part near its surface (a long edge wrapped round a wrist) enters and leaves by
    faces turned nearly alike, and one with an end inside the body crosses once (a penetrating vertex):
    neither is listed.

    Args:
        x: (Vs, 3) cloth positions [m]; faces: (F, 3) its triangles (sim vertex ids).
        body_verts: (Vb, 3) [m]; body_faces: (Fb, 3) the body, a closed surface.

    Returns:
        (K, 2) int64 the tangled edges' vertex ids (lower first), in `mesh_edges` order; (0, 2) when none.
        Only edges with both ends within `NEAR_BODY` of the body are looked at.
    """
    import trimesh

    from torch_diffavatar.sim.collision import detect_contacts

    x, body_verts = x.detach().cpu().to(torch.float64), body_verts.detach().cpu().to(torch.float64)
    body_faces = body_faces.cpu().to(torch.int64)
    edges = mesh_edges(faces.cpu())
    # both ends of an edge through a part lie on its surface: only edges with both ends near the body are
    # cast (the rays cost ~0.5 ms each)
    near = torch.zeros(x.shape[0], dtype=torch.bool)
    near[detect_contacts(x, body_verts, body_faces, NEAR_BODY).vert] = True
    edges = edges[near[edges[:, 0]] & near[edges[:, 1]]]
    if edges.shape[0] == 0:
        return edges
    p = x.numpy()
    a, b = p[edges[:, 0].numpy()], p[edges[:, 1].numpy()]
    length = np.linalg.norm(b - a, axis=1)
    ok = length > 1e-12
    direction = np.zeros_like(a)
    direction[ok] = (b - a)[ok] / length[ok, None]
    body = trimesh.Trimesh(body_verts.numpy(), body_faces.numpy(), process=False)
    rays = np.nonzero(ok)[0]
    hits, ray, tri = body.ray.intersects_location(a[rays], direction[rays], multiple_hits=True)
    ray = rays[ray]
    t = np.einsum("ij,ij->i", hits - a[ray], direction[ray])
    keep = (t > 0) & (t < length[ray])  # trimesh reports a crossing on a shared edge or corner once
    ray, t, normal = ray[keep], t[keep], body.face_normals[tri[keep]]
    if ray.size == 0:
        return edges[:0]
    order = np.lexsort((t, ray))
    ray, normal = ray[order], normal[order]
    starts = np.flatnonzero(np.r_[True, ray[1:] != ray[:-1]])
    ends = np.r_[starts[1:], len(ray)] - 1
    # in by one face and out by one facing the other way: through a part. An edge that only clips a
    # rounded part (a long edge wrapped round a wrist) goes in and out by faces facing nearly alike.
    through = (ends > starts) & ((normal[starts] * normal[ends]).sum(axis=1) < 0)
    return edges[torch.as_tensor(ray[starts[through]], dtype=torch.int64)]
