"""Our cloth material in NVIDIA Newton's units (VBD solver, Newton 1.8): pure numpy, no Newton needed.

The energies behind the conversion (read in ``newton/_src/solvers/vbd/particle_vbd_kernels.py``) are in
`torch_diffavatar.sim_newton`'s docstring and docs/ASSETS.md ("Material in Newton's units"). In short:
Newton's membrane is isotropic stable Neo-Hookean (Lamé μ = ``tri_ke``, λ = ``tri_ka`` [N/m]), equal to
second order in the strain to ours with ``k_uu = k_vv = λ + 2μ``, ``k_uv = μ``, ``ν = λ/(λ+2μ)``; ours is
orthotropic, so ours → Newton keeps the shear and the geometric mean of the axial stiffnesses and loses
the anisotropy and the Poisson coupling (`membrane_conversion_loss` says by how much). Newton's bending
takes one stiffness per interior edge, ``edge_ke = k_b · 3|ē|/(Ā1+Ā2)`` [N] (exact).

The asset export (`assets.write_assets`, ``material_newton.json``) and `sim_newton` both use this module,
so the export needs neither Newton nor Warp.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from torch_diffavatar.sim.material import ClothMaterial

# what ours -> Newton keeps besides the axial stiffness λ + 2μ = √(k_uu k_vv) (`membrane_to_newton`)
MEMBRANE_KEEPS = ("shear", "stretch")


def membrane_to_newton(
    k_uu: float, k_vv: float, k_uv: float, poisson: float = 0.0, *, keep: str = "shear"
) -> tuple[float, float]:
    """Our membrane stiffnesses [N/m] (and coupling ν [-]) -> Newton's (tri_ke = μ, tri_ka = λ) [N/m].

    Both keep the axial stiffness ``λ + 2μ = √(k_uu k_vv)``. ``keep="shear"``: μ = k_uv (λ >= 0), our
    coupling ν is dropped (Newton's is then λ); ``keep="stretch"``: λ = ν√(k_uu k_vv) (our coupling, so a
    strip pulled with its width free is as stiff as ours), μ = (√(k_uu k_vv) − λ)/2 (the shear is dropped).
    Both are exact on ours' isotropic subset (k_uu = k_vv, ν = (k − 2k_uv)/k).
    """
    axial = float(np.sqrt(k_uu * k_vv))
    if keep == "shear":
        mu = float(k_uv)
        return mu, max(axial - 2.0 * mu, 0.0)
    if keep == "stretch":
        lam = float(poisson) * axial
        return 0.5 * (axial - lam), lam
    raise ValueError(f"unknown keep {keep!r}; use one of {', '.join(MEMBRANE_KEEPS)}")


def membrane_from_newton(tri_ke: float, tri_ka: float) -> dict[str, float]:
    """Newton's (tri_ke = μ, tri_ka = λ) [N/m] -> our ``k_uu, k_vv, k_uv`` [N/m] and ``poisson`` [-] with
    the same energy to second order in the strain."""
    axial = float(tri_ka) + 2.0 * float(tri_ke)
    return {"k_uu": axial, "k_vv": axial, "k_uv": float(tri_ke), "poisson": float(tri_ka) / axial}


def bend_to_newton(bend_stiffness: float, edge_weight: np.ndarray, edge_length: np.ndarray) -> np.ndarray:
    """(E,) Newton edge_ke [N] of our k_b [N·m] on edges with weights ``3|ē|²/(Ā1+Ā2)`` (E,) [-] and
    rest lengths (E,) [m]."""
    return float(bend_stiffness) * np.asarray(edge_weight) / np.asarray(edge_length)


def bend_from_newton(edge_ke: np.ndarray, edge_weight: np.ndarray, edge_length: np.ndarray) -> float:
    """Our k_b [N·m] of Newton's (E,) edge_ke [N]: the mean of ``edge_ke |ē| / w`` (exact when uniform)."""
    return float(np.mean(np.asarray(edge_ke) * np.asarray(edge_length) / np.asarray(edge_weight)))


@dataclass(frozen=True)
class NewtonMaterial:
    """Newton's raw cloth parameters (VBD).

    Attributes:
        tri_ke: membrane Lamé μ [N/m]; tri_ka: Lamé λ [N/m]; tri_kd: membrane damping [s].
        edge_ke: (E,) bending stiffness per interior edge of the model [N]; edge_kd: bending damping [s].
        density: mass per rest area [kg/m²].
        soft_contact_mu: cloth-body Coulomb friction [-]; particle_radius: contact thickness [m].
    """

    tri_ke: float
    tri_ka: float
    tri_kd: float
    edge_ke: np.ndarray
    edge_kd: float
    density: float
    soft_contact_mu: float
    particle_radius: float

    def summary(self) -> dict:
        """JSON-friendly raw parameters (edge_ke as its mean, min and max)."""
        return {
            "tri_ke_N_per_m": self.tri_ke,
            "tri_ka_N_per_m": self.tri_ka,
            "tri_kd_s": self.tri_kd,
            "edge_ke_N": {
                "mean": float(np.mean(self.edge_ke)),
                "min": float(np.min(self.edge_ke)),
                "max": float(np.max(self.edge_ke)),
            },
            "edge_kd_s": self.edge_kd,
            "density_kg_per_m2": self.density,
            "soft_contact_mu": self.soft_contact_mu,
            "particle_radius_m": self.particle_radius,
        }


def material_to_newton(
    material: ClothMaterial,
    edge_weight: np.ndarray,
    edge_length: np.ndarray,
    *,
    tri_kd: float = 1.0e-5,
    edge_kd: float = 0.0,
    keep: str = "shear",
) -> NewtonMaterial:
    """Our `ClothMaterial` (floats) on edges (E,) weights / (E,) rest lengths [m] -> `NewtonMaterial`
    (``keep``: the membrane conversion, `membrane_to_newton`)."""
    mu, lam = membrane_to_newton(
        *(float(getattr(material, k)) for k in ("k_uu", "k_vv", "k_uv", "poisson")), keep=keep
    )
    return NewtonMaterial(
        tri_ke=mu,
        tri_ka=lam,
        tri_kd=tri_kd,
        edge_ke=bend_to_newton(float(material.bend_stiffness), edge_weight, edge_length),
        edge_kd=edge_kd,
        density=float(material.areal_density),
        soft_contact_mu=float(material.friction),
        particle_radius=float(material.thickness),
    )


def material_from_newton(
    newton_material: NewtonMaterial, edge_weight: np.ndarray, edge_length: np.ndarray
) -> ClothMaterial:
    """`NewtonMaterial` -> our `ClothMaterial` (damping left at ours: Newton's damps differently)."""
    m = newton_material
    return ClothMaterial(
        areal_density=m.density,
        **membrane_from_newton(m.tri_ke, m.tri_ka),
        bend_stiffness=bend_from_newton(m.edge_ke, edge_weight, edge_length),
        friction=m.soft_contact_mu,
        thickness=m.particle_radius,
    )


def edge_geometry(model, rest_uv: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(E,) bending weights ``3|ē|²/(Ā1+Ā2)`` [-] and (E,) rest lengths [m] of ``model``'s interior edges
    (`ClothModel`), from the (V, 2) panel rest coordinates [m] (the length: the root mean square of the
    edge's lengths in its two panels)."""
    rest = model.rest_data(rest_uv.to(model.dtype))
    u = rest_uv.double()[model.edge_panel_vertices.cpu()]  # (E, 4, 2)
    sq = 0.5 * (((u[:, 1] - u[:, 0]) ** 2).sum(-1) + ((u[:, 3] - u[:, 2]) ** 2).sum(-1))
    return rest.edge_weight.double().cpu().numpy(), sq.sqrt().numpy()


def _voigt_stiffness(axial_u: float, axial_v: float, coupling: float, shear: float) -> np.ndarray:
    """(3, 3) small-strain stiffness on ``[E00, E11, E01]`` (energy ``½ Cᵀ K C``) [N/m]."""
    return np.array([[axial_u, coupling, 0.0], [coupling, axial_v, 0.0], [0.0, 0.0, 4.0 * shear]])


def membrane_conversion_loss(material: ClothMaterial, keep: str = "shear") -> dict[str, float]:
    """What ours → Newton (`membrane_to_newton` with ``keep``) changes of ``material``'s membrane, at small
    strain.

    Newton's membrane is isotropic: both axial stiffnesses become ``λ + 2μ = √(k_uu k_vv)``; with
    ``keep="shear"`` the shear stays ``k_uv`` and the coupling becomes ``λ`` (ours: ``ν√(k_uu k_vv)``).
    ``uniaxial_*`` is the stiffness of a strip pulled along one axis with its width free (``a − c²/b`` of
    the 2×2 axial block) [N/m]: what a hanging panel feels, and where the coupling Newton adds shows (λ ≫ μ
    for woven cloth, whose shear is soft, so Newton's strip is several times softer than ours); with
    ``keep="stretch"`` it is kept and ``shear_newton_N_per_m`` is what changes. ``stiffness_relative_error``:
    the spectral norm of the difference of the two (3, 3) stiffnesses over ours'.
    """
    kuu, kvv, kuv, nu = (float(getattr(material, k)) for k in ("k_uu", "k_vv", "k_uv", "poisson"))
    mu, lam = membrane_to_newton(kuu, kvv, kuv, nu, keep=keep)
    axial, coupling = lam + 2.0 * mu, nu * float(np.sqrt(kuu * kvv))
    ours = _voigt_stiffness(kuu, kvv, coupling, kuv)
    newton = _voigt_stiffness(axial, axial, lam, mu)
    return {
        "k_uu_relative_change": axial / kuu - 1.0,
        "k_vv_relative_change": axial / kvv - 1.0,
        "coupling_ours_N_per_m": coupling,
        "coupling_newton_N_per_m": lam,
        "uniaxial_u_ours_N_per_m": kuu - coupling**2 / kvv,
        "uniaxial_v_ours_N_per_m": kvv - coupling**2 / kuu,
        "uniaxial_newton_N_per_m": axial - lam**2 / axial,
        "shear_ours_N_per_m": kuv,
        "shear_newton_N_per_m": mu,
        "lambda_clamped_at_zero": bool(np.sqrt(kuu * kvv) < 2.0 * kuv),
        "stiffness_relative_error": float(np.linalg.norm(ours - newton, 2) / np.linalg.norm(ours, 2)),
    }


@dataclass(frozen=True)
class NewtonCloth:
    """The seam-merged garment as Newton's VBD model takes it (arrays; numpy, CPU).

    Attributes:
        tri_vertices: (F, 3) int64 simulated (draped.obj) vertices of each triangle.
        tri_rest_uv: (F, 3, 2) float64 rest coordinates [m] of each corner in its own panel (a merged seam
            vertex has one per adjacent panel, so Newton's rest matrix and area are set per triangle).
        vert_mass: (Vs,) float64 lumped masses ``density × rest area / 3`` [kg].
        edge_indices: (E, 4) int64 interior edges in Newton's ``add_edges`` order ``(o0, o1, v0, v1)``:
            the edge runs v0–v1, o0 and o1 are the opposite corners of its triangles (v0, v1, o0) and
            (v1, v0, o1) (ours `ClothModel.edge_quads` ``(v0, v1, o0, o1)``).
        edge_rest_length: (E,) float64 rest lengths [m] (root mean square of the edge's two panel lengths).
        spring_pairs: None, or (S, 2) int64 vertex pairs joined by zero-length springs (the seams of an
            unmerged garment: one particle per panel vertex).
    """

    tri_vertices: np.ndarray
    tri_rest_uv: np.ndarray
    vert_mass: np.ndarray
    edge_indices: np.ndarray
    edge_rest_length: np.ndarray
    spring_pairs: np.ndarray | None = None

    @property
    def edge_count(self) -> int:
        return int(self.edge_indices.shape[0])


def newton_cloth_from_arrays(
    tri_vertices, tri_rest_uv, edge_indices, edge_rest_length, density: float, vert_count: int
) -> NewtonCloth:
    """`NewtonCloth` of exported arrays (see its attributes); the masses are lumped from the rest areas
    (`constraints.vert_lumped_mass`, as ours) at ``density`` [kg/m²]."""
    from torch_diffavatar.sim.constraints import vert_lumped_mass

    tri = np.asarray(tri_vertices, dtype=np.int64).reshape(-1, 3)
    uv = np.asarray(tri_rest_uv, dtype=np.float64).reshape(-1, 3, 2)
    area = 0.5 * np.abs(np.linalg.det(np.stack((uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]), axis=-1)))
    mass = vert_lumped_mass(
        torch.from_numpy(area), torch.from_numpy(tri), int(vert_count), ClothMaterial(areal_density=density)
    )
    return NewtonCloth(
        tri_vertices=tri,
        tri_rest_uv=uv,
        vert_mass=mass.numpy(),
        edge_indices=np.asarray(edge_indices, dtype=np.int64).reshape(-1, 4),
        edge_rest_length=np.asarray(edge_rest_length, dtype=np.float64).reshape(-1),
    )


def newton_cloth(model, rest_uv: torch.Tensor, density: float) -> NewtonCloth:
    """`NewtonCloth` of our seam-merged `ClothModel` ``model`` with (V, 2) rest coordinates [m]."""
    _, edge_length = edge_geometry(model, rest_uv)
    uv = rest_uv.double().cpu().numpy()[model.tri_panel_vertices.cpu().numpy()]  # (F, 3, 2)
    quads = model.edge_quads.cpu().numpy()
    return newton_cloth_from_arrays(
        model.tri_vertices.cpu().numpy(),
        uv,
        quads[:, [2, 3, 0, 1]],
        edge_length,
        density,
        model.vert_count,
    )


def vertex_coloring(vert_count: int, cloth: NewtonCloth) -> list[np.ndarray]:
    """Greedy colouring of ``cloth``'s vertices (first fit, in index order) so that no triangle edge, bending
    pair (o0, o1) or spring joins two vertices of one colour: Newton's VBD solves one colour at a time in
    parallel (its own `ModelBuilder.color` leaves springs out). Returns the (k,) vertex ids of each colour."""
    t, e = cloth.tri_vertices, cloth.edge_indices
    links = [t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]], e[:, [0, 1]]]
    if cloth.spring_pairs is not None:
        links.append(np.asarray(cloth.spring_pairs).reshape(-1, 2))
    pairs = np.concatenate(links)
    neighbours: list[list[int]] = [[] for _ in range(vert_count)]
    for a, b in pairs.tolist():
        if a != b:
            neighbours[a].append(b)
            neighbours[b].append(a)
    color = np.full(vert_count, -1, dtype=np.int64)
    for v in range(vert_count):
        used = {int(color[n]) for n in neighbours[v]}
        c = 0
        while c in used:
            c += 1
        color[v] = c
    return [np.flatnonzero(color == c) for c in range(int(color.max()) + 1)]
