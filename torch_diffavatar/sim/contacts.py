"""Cloth–body contacts and their differentiable response (paper eq. 6), below the kernels that use them.

A contact pairs a cloth vertex with a body triangle and a barycentric point on it; `sim/collision.py`
detects them (no autograd). The response here is plain, out-of-place torch that recomputes the contact
point and the face normal from the CURRENT ``body_verts``, so projected positions are a differentiable
function of the body vertices. The XPBD frame (`reference.xpbd_frame`), the energy of the equilibrium
adjoint and the detection all share these functions; this module imports only torch, so the kernels
below `sim/ops.py` can use it without an import cycle.

A vertex may have several contacts (in a valley of the body, `collision.detect_contacts`'s ``valley``; by a
foot, the floor, its ``floor``). The C++ op answers a vertex's contacts one after the other, in their order;
each function here does the same, as passes over `Contacts.layers` (a vertex's first contact in the first
pass, its second in the next, …): contacts of different vertices do not interact, so the passes give the
op's result.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import torch


@dataclass(frozen=True)
class Contacts:
    """Cloth vertices near the body and their closest body triangle.

    Attributes:
        vert: (C,) int64 cloth (simulated) vertex ids.
        tri: (C,) int64 body face ids.
        bary: (C, 3) barycentric coordinates of the closest point on ``tri`` at detection time.

    A vertex listed twice has two contacts, answered in the order listed (`layers`).
    """

    vert: torch.Tensor
    tri: torch.Tensor
    bary: torch.Tensor

    @property
    def count(self) -> int:
        return int(self.vert.shape[0])

    @cached_property
    def layers(self) -> list[torch.Tensor] | None:
        """None when no vertex is listed twice; else the contacts as passes, (C_k,) int64 ids each: pass k
        holds every vertex's (k + 1)-th contact, in the listed order."""
        return occurrence_layers(self.vert)


def occurrence_layers(vert: torch.Tensor) -> list[torch.Tensor] | None:
    """`Contacts.layers` of the (C,) vertex ids ``vert``."""
    n = vert.shape[0]
    if n < 2:
        return None
    order = torch.argsort(vert, stable=True)
    sv = vert[order]
    first = torch.ones(n, dtype=torch.bool, device=vert.device)
    first[1:] = sv[1:] != sv[:-1]
    if bool(first.all()):
        return None
    pos = torch.arange(n, device=vert.device)
    run_start = torch.cummax(torch.where(first, pos, torch.zeros_like(pos)), 0).values
    rank = torch.empty_like(pos)
    rank[order] = pos - run_start
    return [torch.nonzero(rank == k).squeeze(1) for k in range(int(rank.max()) + 1)]


def _by_layer(layers, fn, x, *per_contact):
    """Run ``fn(x, *per_contact_k) -> (x, out_k)`` pass by pass over ``layers`` (one pass of everything when
    None); returns (x, out (C, ...) in the listed order)."""
    if layers is None:
        return fn(x, *per_contact)
    outs, ids = [], []
    for idx in layers:
        x, out = fn(x, *(t[idx] for t in per_contact))
        outs.append(out)
        ids.append(idx)
    out = torch.cat(outs)
    return x, out.new_zeros(out.shape).index_copy(0, torch.cat(ids), out)


def unit_normals(corners: torch.Tensor) -> torch.Tensor:
    """(..., 3) unit right-hand normals of the triangles with corners (..., 3, 3) [m] (0 where degenerate)."""
    n = torch.linalg.cross(corners[..., 1, :] - corners[..., 0, :], corners[..., 2, :] - corners[..., 0, :])
    return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-20)


def contact_frames(body_verts: torch.Tensor, body_faces: torch.Tensor, contacts: Contacts):
    """Contact points and unit outward face normals from the current body (differentiable).

    Returns:
        point: (C, 3) [m]; normal: (C, 3) unit right-hand normal of the contact triangle.
    """
    corners = body_verts[body_faces[contacts.tri]]  # (C, 3, 3)
    return (contacts.bary[:, :, None] * corners).sum(1), unit_normals(corners)


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
    movable = (vert_inv_mass.detach()[contacts.vert] > 0).to(x.dtype)
    x, depth = push_out(x, contacts.vert, point, normal, movable, thickness, contacts.layers)
    return x, depth, normal


def push_out(x, vert, point, normal, movable, thickness, layers=None) -> tuple[torch.Tensor, torch.Tensor]:
    """`project_contacts` with the contact frames given (the XPBD frame computes them once per call).

    Args:
        x: (Vs, 3) [m]; vert: (C,) int64; point, normal: (C, 3) from `contact_frames`; movable: (C,)
            1 for a free vertex, 0 for a pinned one; thickness: [m]; layers: `Contacts.layers`.

    Returns:
        x: (Vs, 3) projected positions (out of place); depth: (C,) correction applied [m].
    """

    def one_pass(x, vert, point, normal, movable):
        s = ((x[vert] - point) * normal).sum(-1) - thickness
        depth = (-s).clamp_min(0.0) * movable
        return x.index_add(0, vert, normal * depth[:, None]), depth

    return _by_layer(layers, one_pass, x, vert, point, normal, movable)


def apply_friction(
    x: torch.Tensor, x_start: torch.Tensor, contacts: Contacts, normal: torch.Tensor, depth: torch.Tensor, mu
) -> torch.Tensor:
    """Position-based Coulomb friction (Macklin et al. 2014, §6.1) on the step's tangential motion.

    For each contact with a normal correction ``depth`` > 0 in this substep, the tangential displacement
    ``dt = P_t (x − x_start)`` is cancelled when ``|dt| < mu·depth`` (static) and reduced by ``mu·depth``
    otherwise (kinetic). Returns the new (Vs, 3) positions (out of place).
    """

    def one_pass(x, vert, normal, depth):
        d = x[vert] - x_start[vert]
        dt_ = d - (d * normal).sum(-1, keepdim=True) * normal
        length = dt_.norm(dim=-1)
        limit = mu * depth
        scale = torch.where(length <= limit, torch.ones_like(length), limit / length.clamp_min(1e-20))
        scale = torch.where(depth > 0, scale, torch.zeros_like(scale))
        return x.index_add(0, vert, -dt_ * scale[:, None]), depth

    return _by_layer(contacts.layers, one_pass, x, contacts.vert, normal, depth)[0]


def damp_bounce(
    v: torch.Tensor, contacts: Contacts, normal: torch.Tensor, depth: torch.Tensor, bounce: float
) -> torch.Tensor:
    """Velocities (Vs, 3) after each contact with a normal correction ``depth`` > 0 in this substep kept only
    ``bounce`` of its outward normal velocity (``XPBDConfig.contact_bounce``; out of place)."""

    def one_pass(v, vert, normal, depth):
        vn = (v[vert] * normal).sum(-1)
        cut = torch.where(depth > 0, (1.0 - bounce) * vn.clamp_min(0.0), torch.zeros_like(vn))
        return v.index_add(0, vert, -cut[:, None] * normal), depth

    return _by_layer(contacts.layers, one_pass, v, contacts.vert, normal, depth)[0]


def signed_distance_along_normal(x: torch.Tensor, body_verts, body_faces, contacts: Contacts) -> torch.Tensor:
    """(C,) signed distance [m] of each contact vertex above its contact triangle's plane."""
    point, normal = contact_frames(body_verts, body_faces, contacts)
    return ((x[contacts.vert] - point) * normal).sum(-1)
