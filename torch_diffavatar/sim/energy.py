"""The drape energy ``U(x; θ)`` whose minimiser XPBD approximates, and its sparse Hessian.

``U = stretch + bend + gravity + stitches + attachments + active contacts`` (paper §3.2: XPBD's compliance
α is the inverse stiffness, ``U = ½ Cᵀ α⁻¹ C``). Stretch, bending and gravity reuse `sim/constraints.py`;
the zero-length stitches and the waist attachments are ``½ |C|²/α`` with the solver's compliances; an
active contact (vertex i frozen on body triangle t with barycentrics b) is the stiff quadratic
``½ k_c (s_i − thickness)²`` on its signed distance ``s_i = (x_i − p(b, body))·n(body)`` to the plane of
the triangle (the XPBD contact projection's constraint, `collision.signed_distance_along_normal`), so U
is a smooth function of x, rest_uv, the material and the body vertices.

`hessian_elements` returns per-element Hessian blocks (exact, or projected to PSD for Newton) and
`assemble_csr` scatters them into a CSR matrix over the free degrees of freedom.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torch_diffavatar.sim import collision, constraints
from torch_diffavatar.sim.collision import Contacts
from torch_diffavatar.sim.constraints import RestData
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.model import ClothModel


@dataclass(frozen=True)
class EnergyParams:
    """Constants of the drape energy that are not material fields.

    Attributes:
        gravity: (3,) gravitational acceleration [m/s²].
        stitch_compliance: zero-length stitch compliance [m/N].
        attach_compliance: waist attachment compliance [m/N].
        contact_stiffness: stiffness k_c of the active-contact quadratic [N/m].
    """

    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)
    stitch_compliance: float = 1e-5
    attach_compliance: float = 1e-5
    contact_stiffness: float = 1e4


def drape_energy(
    x: torch.Tensor,
    model: ClothModel,
    rest: RestData,
    material: ClothMaterial,
    params: EnergyParams,
    *,
    body_verts: torch.Tensor | None = None,
    body_faces: torch.Tensor | None = None,
    contacts: Contacts | None = None,
) -> torch.Tensor:
    """() total energy [J] at positions ``x`` (Vs, 3) [m] (differentiable in every tensor argument).

    Args:
        rest: ``model.rest_data(rest_uv, material)``; material: the same material.
        body_verts: (Vb, 3) [m]; body_faces: (Fb, 3) int64; contacts: the frozen active contact set.
    """
    u = constraints.stretch_energy(x, model.tri_vertices, rest, material)
    if model.edge_count:
        u = u + constraints.bend_energy(x, model.edge_quads, rest, material)
    u = u + constraints.gravity_energy(x, rest.vert_mass, x.new_tensor(params.gravity))
    if model.stitch_vertices.shape[0]:
        a, b = model.stitch_vertices[:, 0], model.stitch_vertices[:, 1]
        u = u + 0.5 / params.stitch_compliance * ((x[a] - x[b]) ** 2).sum()
    if model.attach_vertices.shape[0]:
        dy = x[model.attach_vertices, 1] - model.attach_height
        u = u + 0.5 / params.attach_compliance * (dy**2).sum()
    if contacts is not None and contacts.count:
        s = collision.signed_distance_along_normal(x, body_verts, body_faces, contacts)
        u = u + 0.5 * params.contact_stiffness * ((s - material.thickness) ** 2).sum()
    return u


_TRI_LOCAL = torch.tensor([[0, 1, 2]])
_QUAD_LOCAL = torch.tensor([[0, 1, 2, 3]])


def _tri_energy(xe, rest_inv, area, k):
    c = constraints.green_strain(xe, _TRI_LOCAL.to(xe.device), rest_inv[None])[0]
    return 0.5 * area * (c @ k @ c)


def _edge_energy(xe, weight, rest_angle, kb):
    theta = constraints.dihedral_angles(xe, _QUAD_LOCAL.to(xe.device))[0]
    return 0.5 * kb * weight * (theta - rest_angle) ** 2


def _psd(h: torch.Tensor) -> torch.Tensor:
    """Project symmetric blocks (K, n, n) to PSD by clamping negative eigenvalues to 0."""
    if h.shape[0] == 0:
        return h
    evals, evecs = torch.linalg.eigh(0.5 * (h + h.transpose(1, 2)))
    return (evecs * evals.clamp_min(0.0)[:, None, :]) @ evecs.transpose(1, 2)


def hessian_elements(
    x: torch.Tensor,
    model: ClothModel,
    rest: RestData,
    material: ClothMaterial,
    params: EnergyParams,
    *,
    body_verts: torch.Tensor | None = None,
    body_faces: torch.Tensor | None = None,
    contacts: Contacts | None = None,
    project: bool = False,
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Per-element Hessian blocks of `drape_energy` with respect to x (no autograd through them).

    Returns:
        a list of (dofs (K, n) int64 global dof ids 3·vertex + axis, blocks (K, n, n)); with
        ``project=True`` the stretch and bending blocks are projected to PSD (projected Newton).
    """
    from torch.func import hessian, vmap

    x = x.detach()
    out = []
    k = constraints.membrane_stiffness(material, x).detach()
    tri = model.tri_vertices
    h_tri = vmap(hessian(_tri_energy), in_dims=(0, 0, 0, None))(
        x[tri], rest.tri_rest_inv.detach(), rest.tri_area.detach(), k
    ).reshape(-1, 9, 9)
    out.append((_dofs(tri), _psd(h_tri) if project else h_tri))
    if model.edge_count:
        kb = torch.as_tensor(material.bend_stiffness, dtype=x.dtype, device=x.device).detach()
        quads = model.edge_quads
        h_edge = vmap(hessian(_edge_energy), in_dims=(0, 0, 0, None))(
            x[quads], rest.edge_weight.detach(), rest.edge_rest_angle.detach(), kb
        ).reshape(-1, 12, 12)
        out.append((_dofs(quads), _psd(h_edge) if project else h_edge))
    eye = torch.eye(3, dtype=x.dtype, device=x.device)
    if model.stitch_vertices.shape[0]:
        blk = torch.cat((torch.cat((eye, -eye), 1), torch.cat((-eye, eye), 1)), 0) / params.stitch_compliance
        ns = model.stitch_vertices.shape[0]
        out.append((_dofs(model.stitch_vertices), blk.expand(ns, 6, 6)))
    if model.attach_vertices.shape[0]:
        blk = torch.zeros(3, 3, dtype=x.dtype, device=x.device)
        blk[1, 1] = 1.0 / params.attach_compliance
        na = model.attach_vertices.shape[0]
        out.append((_dofs(model.attach_vertices[:, None]), blk.expand(na, 3, 3)))
    if contacts is not None and contacts.count:
        _, n = collision.contact_frames(body_verts.detach(), body_faces, contacts)
        out.append((_dofs(contacts.vert[:, None]), params.contact_stiffness * n[:, :, None] * n[:, None, :]))
    return out


def _dofs(verts: torch.Tensor) -> torch.Tensor:
    """(K, 3m) global dof ids of the (K, m) vertex ids."""
    return (3 * verts[:, :, None] + torch.arange(3, device=verts.device)).reshape(verts.shape[0], -1)


def assemble_csr(
    elements: list[tuple[torch.Tensor, torch.Tensor]], free_index: torch.Tensor, free_count: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Scatter element blocks into a CSR matrix over the free dofs (pinned dofs dropped).

    Args:
        elements: from `hessian_elements`.
        free_index: (3Vs,) int64 position of each dof among the free ones, −1 for pinned dofs.
        free_count: number of free dofs ``n``.

    Returns:
        crow (n+1,) int64, col (nnz,) int64, val (nnz,) — sorted columns, duplicates summed.
    """
    rows, cols, vals = [], [], []
    for dofs, blocks in elements:
        m = dofs.shape[1]
        r = free_index[dofs][:, :, None].expand(-1, m, m)
        c = free_index[dofs][:, None, :].expand(-1, m, m)
        keep = (r >= 0) & (c >= 0)
        rows.append(r[keep])
        cols.append(c[keep])
        vals.append(blocks[keep])
    r, c, v = torch.cat(rows), torch.cat(cols), torch.cat(vals)
    key = r * free_count + c
    uniq, inverse = torch.unique(key, return_inverse=True)
    val = v.new_zeros(uniq.shape[0]).index_add_(0, inverse, v)
    row, col = uniq // free_count, uniq % free_count
    crow = torch.zeros(free_count + 1, dtype=torch.int64, device=v.device)
    crow[1:] = torch.cumsum(torch.bincount(row, minlength=free_count), 0)
    return crow, col, val
