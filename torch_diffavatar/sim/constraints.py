"""Pure functions for the cloth constraints: rest data from the 2D pattern and constraint energies.

Everything here is differentiable (plain torch) in the rest coordinates ``rest_uv`` and in the material
tensors, so the fit can back-propagate into the pattern and the material, and the equilibrium adjoint can
take derivatives of the energies ``U(x; θ)``. Paper §3.2 and appendix A; the constraint functions match
the kernels in `sim/reference.py`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torch_diffavatar.geometry import green_strain
from torch_diffavatar.sim.material import ClothMaterial


def tri_rest_geometry(rest_uv: torch.Tensor, tri_panel_vertices: torch.Tensor):
    """Inverse rest edge matrices and rest areas of the triangles.

    Args:
        rest_uv: (V, 2) panel-vertex rest coordinates [m].
        tri_panel_vertices: (F, 3) int64 panel-vertex ids.

    Returns:
        tri_rest_inv: (F, 2, 2) inverse of ``D̄ = [ū0 − ū2, ū1 − ū2]`` [1/m].
        tri_area: (F,) rest area [m²] (positive whatever the orientation in uv).
    """
    u = rest_uv[tri_panel_vertices]  # (F, 3, 2)
    d = torch.stack((u[:, 0] - u[:, 2], u[:, 1] - u[:, 2]), dim=-1)  # (F, 2, 2)
    det = d[:, 0, 0] * d[:, 1, 1] - d[:, 0, 1] * d[:, 1, 0]
    inv = torch.stack(
        (torch.stack((d[:, 1, 1], -d[:, 0, 1]), -1), torch.stack((-d[:, 1, 0], d[:, 0, 0]), -1)), 1
    )
    return inv / det[:, None, None], 0.5 * det.abs()


def _scalar(value, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(value, dtype=like.dtype, device=like.device)


def membrane_stiffness(material: ClothMaterial, like: torch.Tensor) -> torch.Tensor:
    """(3, 3) stiffness K [N/m] of the energy density ``ψ = ½ Cᵀ K C``, C = [E00, E11, E01]."""
    kuu, kvv = _scalar(material.k_uu, like), _scalar(material.k_vv, like)
    kuv, nu = _scalar(material.k_uv, like), _scalar(material.poisson, like)
    c = nu * torch.sqrt(kuu * kvv)
    z = torch.zeros_like(kuu)
    return torch.stack(
        (torch.stack((kuu, c, z)), torch.stack((c, kvv, z)), torch.stack((z, z, 4.0 * kuv))),
    )


def tri_stretch_compliance(tri_area: torch.Tensor, material: ClothMaterial) -> torch.Tensor:
    """(F, 3, 3) XPBD compliance ``α = (Ā K)⁻¹`` of each triangle's strain block [1/(N·m)]."""
    k_inv = torch.linalg.inv(membrane_stiffness(material, tri_area))
    return (k_inv[None] / tri_area[:, None, None]).contiguous()


def edge_bend_weight(
    rest_uv: torch.Tensor, edge_panel_vertices: torch.Tensor, edge_tris: torch.Tensor, tri_area: torch.Tensor
) -> torch.Tensor:
    """(E,) geometric weight ``3|ē|²/(Ā1 + Ā2)`` of the discrete-shell bending energy [-].

    Args:
        rest_uv: (V, 2) [m]; edge_panel_vertices: (E, 4) int64 the edge's two endpoints as panel vertices
            of its first triangle, then of its second (they differ across a seam); edge_tris: (E, 2)
            int64; tri_area: (F,) [m²].

    ``|ē|²`` is the mean of the squared rest lengths seen from the two triangles.
    """
    u = rest_uv[edge_panel_vertices]  # (E, 4, 2)
    l1 = ((u[:, 1] - u[:, 0]) ** 2).sum(-1)
    l2 = ((u[:, 3] - u[:, 2]) ** 2).sum(-1)
    return 1.5 * (l1 + l2) / tri_area[edge_tris].sum(-1)


def edge_bend_compliance(edge_weight: torch.Tensor, material: ClothMaterial) -> torch.Tensor:
    """(E,) compliance ``1/(k_b · weight)`` [1/(N·m)]."""
    return 1.0 / (_scalar(material.bend_stiffness, edge_weight) * edge_weight)


def vert_lumped_mass(
    tri_area: torch.Tensor, tri_vertices: torch.Tensor, vert_count: int, material: ClothMaterial
) -> torch.Tensor:
    """(Vs,) lumped masses [kg]: each triangle gives a third of ``Ā · areal_density`` to each corner."""
    share = (tri_area * _scalar(material.areal_density, tri_area) / 3.0)[:, None].expand(-1, 3)
    return tri_area.new_zeros(vert_count).index_add(0, tri_vertices.reshape(-1), share.reshape(-1))


@dataclass(frozen=True)
class RestData:
    """Everything the stepping needs that derives from ``rest_uv`` and the material (differentiable).

    Attributes:
        tri_rest_inv: (F, 2, 2) [1/m]; tri_area: (F,) [m²]; tri_compliance: (F, 3, 3) [1/(N·m)];
        edge_rest_angle: (E,) [rad]; edge_weight: (E,) [-]; edge_compliance: (E,) [1/(N·m)];
        vert_mass: (Vs,) [kg]; vert_inv_mass: (Vs,) [1/kg] (0 for pinned vertices);
        attach_height: (A,) target heights y of the attached vertices [m] (`ClothModel.attach_height`, or
        the drape's own, e.g. a fitted waistband height);
        material: the `ClothMaterial` used.
    """

    tri_rest_inv: torch.Tensor
    tri_area: torch.Tensor
    tri_compliance: torch.Tensor
    edge_rest_angle: torch.Tensor
    edge_weight: torch.Tensor
    edge_compliance: torch.Tensor
    vert_mass: torch.Tensor
    vert_inv_mass: torch.Tensor
    attach_height: torch.Tensor
    material: ClothMaterial


# ------------------------------------------------------------------------------------- constraints


def dihedral_angles(x: torch.Tensor, edge_quads: torch.Tensor) -> torch.Tensor:
    """(E,) signed dihedral angle [rad] per interior edge (convention of `sim/reference.py`)."""
    x0, x1, x2, x3 = x[edge_quads].unbind(1)
    e = x1 - x0
    n1 = torch.linalg.cross(e, x2 - x0)
    n2 = torch.linalg.cross(x0 - x1, x3 - x1)
    e_hat = e / e.norm(dim=-1, keepdim=True)
    return torch.atan2((torch.linalg.cross(n1, n2) * e_hat).sum(-1), (n1 * n2).sum(-1))


def stretch_energy(
    x: torch.Tensor, tri_vertices: torch.Tensor, rest: RestData, material: ClothMaterial | None = None
) -> torch.Tensor:
    """() membrane energy ``Σ Ā ½ Cᵀ K C`` [J]."""
    c = green_strain(x, tri_vertices, rest.tri_rest_inv)
    k = membrane_stiffness(material or rest.material, x)
    return 0.5 * (rest.tri_area * ((c @ k) * c).sum(-1)).sum()


def bend_energy(
    x: torch.Tensor, edge_quads: torch.Tensor, rest: RestData, material: ClothMaterial | None = None
) -> torch.Tensor:
    """() bending energy ``Σ ½ k_b w (θ − θ̄)²`` [J]."""
    theta = dihedral_angles(x, edge_quads)
    kb = _scalar((material or rest.material).bend_stiffness, x)
    return 0.5 * kb * (rest.edge_weight * (theta - rest.edge_rest_angle) ** 2).sum()


def gravity_energy(x: torch.Tensor, vert_mass: torch.Tensor, gravity: torch.Tensor) -> torch.Tensor:
    """() potential energy ``−Σ m_i g·x_i`` [J]; gravity (3,) [m/s²]."""
    return -(vert_mass[:, None] * x * gravity).sum()
