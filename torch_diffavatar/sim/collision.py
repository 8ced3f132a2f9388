"""Cloth–body collision: vertex–triangle contacts against any triangle mesh, with friction.

Detection (`detect_contacts`, no autograd) runs once per step: for every cloth vertex the closest body
triangle within a band. The response (`contact_frames`, `project_contacts`, `apply_friction`) is plain,
out-of-place torch and recomputes the contact point (barycentric point on the stored triangle) and the
face normal from the CURRENT ``body_verts`` each time, so the projected positions are a differentiable
function of the body vertices (paper eq. 6). Limitations: no self-collision, no edge–edge contacts, one
contact per cloth vertex, the body is static within a step.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torch_diffavatar.sim import ops


@dataclass(frozen=True)
class Contacts:
    """Cloth vertices near the body and their closest body triangle.

    Attributes:
        vert: (C,) int64 cloth (simulated) vertex ids.
        tri: (C,) int64 body face ids.
        bary: (C, 3) barycentric coordinates of the closest point on ``tri`` at detection time.
    """

    vert: torch.Tensor
    tri: torch.Tensor
    bary: torch.Tensor

    @property
    def count(self) -> int:
        return int(self.vert.shape[0])


class BodyIndex:
    """The closest-point grid of a body mesh, built once for a body that does not move (no autograd).

    `detect_contacts` (``index=``) then skips the per-call grid build; the contacts are bit-identical to
    the ones without an index (`ops.closest_point_query`). Holds a copy of the mesh it was built from:
    `matches` tells whether it applies to a given (verts, faces). Without the C++ extension (or with
    ``use_extension=False``) it holds no grid and queries fall back to `ops.closest_point_on_mesh`.

    Args:
        body_verts: (Vb, 3) [m]; body_faces: (Fb, 3) int64.
        cell_size: grid cell edge [m]; None picks the op's default (mean triangle size). Only the speed
            depends on it.
    """

    def __init__(
        self,
        body_verts: torch.Tensor,
        body_faces: torch.Tensor,
        *,
        cell_size: float | None = None,
        use_extension=True,
    ):
        self.verts = body_verts.detach().clone().contiguous()
        self.faces = body_faces.detach().clone().contiguous()
        self.use_extension = use_extension
        self.grid = None
        if ops.closest_point_index_available(self.verts.device, use_extension):
            self.grid = ops.closest_point_index(
                self.verts, self.faces, 0.0 if cell_size is None else cell_size
            )

    def matches(self, body_verts: torch.Tensor, body_faces: torch.Tensor) -> bool:
        """True when (body_verts, body_faces) equal the mesh this index was built from."""
        return (
            body_verts.shape == self.verts.shape
            and body_faces.shape == self.faces.shape
            and body_verts.dtype == self.verts.dtype
            and body_verts.device == self.verts.device
            and torch.equal(body_faces, self.faces)
            and torch.equal(body_verts.detach(), self.verts)
        )

    def closest_point(self, points: torch.Tensor, max_dist: float):
        """(tri, bary, dist) of `ops.closest_point_on_mesh` (points, verts, faces, max_dist)."""
        points = points.detach().contiguous()
        if self.grid is not None and points.device.type == "cpu":
            return ops.closest_point_query(points, self.verts, self.faces, self.grid, max_dist)
        return ops.closest_point_on_mesh(
            points, self.verts, self.faces, max_dist, use_extension=self.use_extension
        )


def detect_contacts(
    x: torch.Tensor,
    body_verts: torch.Tensor,
    body_faces: torch.Tensor,
    band: float,
    *,
    use_extension=True,
    index: BodyIndex | None = None,
) -> Contacts:
    """Closest body triangle of every cloth vertex within ``band`` [m] (no autograd).

    Args:
        x: (Vs, 3) cloth positions [m]; body_verts: (Vb, 3) [m]; body_faces: (Fb, 3) int64.
        index: a `BodyIndex` of exactly (body_verts, body_faces) to reuse (ValueError otherwise).
    """
    with torch.no_grad():
        if index is not None:
            if not index.matches(body_verts, body_faces):
                raise ValueError("index was built for another body mesh")
            tri, bary, _ = index.closest_point(x, band)
        else:
            tri, bary, _ = ops.closest_point_on_mesh(
                x.detach().contiguous(),
                body_verts.detach().contiguous(),
                body_faces.contiguous(),
                band,
                use_extension=use_extension,
            )
        vert = torch.nonzero(tri >= 0).squeeze(1)
    return Contacts(vert, tri[vert], bary[vert])


def contact_frames(body_verts: torch.Tensor, body_faces: torch.Tensor, contacts: Contacts):
    """Contact points and unit outward face normals from the current body (differentiable).

    Returns:
        point: (C, 3) [m]; normal: (C, 3) unit right-hand normal of the contact triangle.
    """
    corners = body_verts[body_faces[contacts.tri]]  # (C, 3, 3)
    point = (contacts.bary[:, :, None] * corners).sum(1)
    n = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return point, n / n.norm(dim=-1, keepdim=True).clamp_min(1e-20)


def project_contacts(
    x: torch.Tensor,
    vert_inv_mass: torch.Tensor,
    body_verts: torch.Tensor,
    body_faces: torch.Tensor,
    contacts: Contacts,
    thickness,
):
    """Push contact vertices to ``thickness`` outside the body along the face normal (out of place).

    Args:
        x: (Vs, 3) [m]; vert_inv_mass: (Vs,) (pinned vertices do not move); thickness: [m].

    Returns:
        x: (Vs, 3) projected positions; depth: (C,) correction applied [m] (0 where none);
        normal: (C, 3) contact normals.
    """
    point, normal = contact_frames(body_verts, body_faces, contacts)
    s = ((x[contacts.vert] - point) * normal).sum(-1) - thickness
    movable = vert_inv_mass[contacts.vert] > 0
    depth = torch.where(movable, torch.clamp(-s, min=0.0), torch.zeros_like(s))
    return x.index_add(0, contacts.vert, normal * depth[:, None]), depth, normal


def apply_friction(
    x: torch.Tensor, x_start: torch.Tensor, contacts: Contacts, normal: torch.Tensor, depth: torch.Tensor, mu
) -> torch.Tensor:
    """Position-based Coulomb friction (Macklin et al. 2014, §6.1) on the step's tangential motion.

    For each contact with a normal correction ``depth`` > 0 in this substep, the tangential displacement
    ``dt = P_t (x − x_start)`` is cancelled when ``|dt| < mu·depth`` (static) and reduced by ``mu·depth``
    otherwise (kinetic). Returns the new (Vs, 3) positions (out of place).
    """
    d = x[contacts.vert] - x_start[contacts.vert]
    dt_ = d - (d * normal).sum(-1, keepdim=True) * normal
    length = dt_.norm(dim=-1)
    limit = mu * depth
    scale = torch.where(length <= limit, torch.ones_like(length), limit / length.clamp_min(1e-20))
    scale = torch.where(depth > 0, scale, torch.zeros_like(scale))
    return x.index_add(0, contacts.vert, -dt_ * scale[:, None])


def signed_distance_along_normal(x: torch.Tensor, body_verts, body_faces, contacts: Contacts) -> torch.Tensor:
    """(C,) signed distance [m] of each contact vertex above its contact triangle's plane."""
    point, normal = contact_frames(body_verts, body_faces, contacts)
    return ((x[contacts.vert] - point) * normal).sum(-1)
