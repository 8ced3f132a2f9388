"""The asset's material in NVIDIA Newton's units: ``material_newton.json`` beside ``material.json``.

`newton_material_dict` is what `assets.write_assets` writes (pure numpy: Newton need not be installed);
`read_newton_material` reads it back into `sim.newton_units.NewtonCloth` + `NewtonMaterial`, which
`sim_newton.newton_drape` settles (`scripts/newton_check.py`). The conversion is
`sim.newton_units.material_to_newton`; docs/ASSETS.md ("Material in Newton's units") gives the formulas.

Layout (SI; indices 0-based into draped.obj's vertices):

* ``parameters``: ``tri_ke``, ``tri_ka``, ``tri_kd``, ``edge_kd``, ``density``, ``soft_contact_mu``,
  ``particle_radius``, each ``{"value", "unit", "meaning"}`` (Newton's argument names);
* ``bending``: our ``bend_stiffness`` [N·m], the rule ``edge_ke = k_b · 3|e|/(A1+A2)`` and edge_ke's range;
* ``membrane_keep``: which membrane conversion ``parameters`` use (`EXPORT_MEMBRANE`, ``"stretch"``);
* ``membrane_conversion_loss``: what the isotropic membrane changes (`newton_units.membrane_conversion_loss`);
* ``membrane_alternative``: tri_ke / tri_ka of the other conversion (``"shear"``), and its loss;
* ``edges``: ``indices`` (E, 4) in ``ModelBuilder.add_edges`` order (o0, o1, v0, v1), ``rest_length_m``
  (E,) and ``edge_ke_N`` (E,), per interior edge of draped.obj's seam-merged mesh;
* ``held_vertices``: (A,) vertices a waist-held garment (skirt, trousers) is pinned by on the body.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch

from torch_diffavatar.pattern.garment_mesh import GarmentMesh
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.newton_units import (
    MEMBRANE_KEEPS,
    NewtonCloth,
    NewtonMaterial,
    bend_to_newton,
    edge_geometry,
    material_to_newton,
    membrane_conversion_loss,
    membrane_to_newton,
    newton_cloth,
    newton_cloth_from_arrays,
)

NEWTON_SOLVER = "newton.solvers.SolverVBD (Newton 1.8.0, Warp 1.19.0)"

# the membrane conversion of ``parameters`` (`newton_units.membrane_to_newton`); the other one is written as
# ``membrane_alternative``. Keeping our stretch put Newton's drape of a fitted dress and skirt closer to
# ours than keeping our shear (Chamfer 12.0 vs 15.2 mm and 16.2 vs 20.4 mm) and settled it 4-5x sooner
# (docs/BENCHMARKS.md, "Newton cross-check").
EXPORT_MEMBRANE = "stretch"

# Newton's name -> (NewtonMaterial attribute, unit, meaning)
NEWTON_PARAMETERS = {
    "tri_ke": ("tri_ke", "N/m", "membrane Lame mu of the stable Neo-Hookean triangle (add_triangles) = k_uv"),
    "tri_ka": ("tri_ka", "N/m", "membrane Lame lambda = max(sqrt(k_uu k_vv) - 2 k_uv, 0)"),
    "tri_kd": ("tri_kd", "s", "membrane damping (Newton's; ours damps velocities instead)"),
    "edge_kd": ("edge_kd", "s", "bending damping"),
    "density": ("density", "kg/m^2", "= areal_density: particle mass = density x rest area / 3, lumped"),
    "soft_contact_mu": ("soft_contact_mu", "-", "= friction: cloth-body Coulomb friction"),
    "particle_radius": ("particle_radius", "m", "= thickness: contact radius of each particle"),
}


def _float_material(material: ClothMaterial) -> ClothMaterial:
    """``material`` with plain floats (a fitted field may be a tensor that requires grad)."""
    values = {f.name: getattr(material, f.name) for f in fields(material)}
    return ClothMaterial(**{k: float(v.detach() if torch.is_tensor(v) else v) for k, v in values.items()})


def newton_material_dict(garment: GarmentMesh, rest_uv: torch.Tensor, material: ClothMaterial) -> dict:
    """``material_newton.json`` (module docstring) of ``material`` on ``garment`` with (V, 2) rest
    coordinates ``rest_uv`` [m]."""
    from torch_diffavatar.sim.model import ClothModelBuilder

    material = _float_material(material)
    model = ClothModelBuilder(material).add_garment(garment).finalize(dtype=torch.float64)
    uv = rest_uv.detach().cpu().double()
    weight, length = edge_geometry(model, uv)
    newton = material_to_newton(material, weight, length, keep=EXPORT_MEMBRANE)
    cloth = newton_cloth(model, uv, newton.density)
    return {
        "solver": NEWTON_SOLVER,
        "conversion": "torch_diffavatar.sim.newton_units.material_to_newton (docs/ASSETS.md, "
        "'Material in Newton's units'); exact at small strain for an isotropic material, see "
        "membrane_conversion_loss for what an orthotropic one loses",
        "membrane_keep": EXPORT_MEMBRANE,
        "parameters": {
            name: {"value": float(getattr(newton, attr)), "unit": unit, "meaning": meaning}
            for name, (attr, unit, meaning) in NEWTON_PARAMETERS.items()
        },
        "bending": {
            "bend_stiffness_N_m": float(material.bend_stiffness),
            "rule": "edge_ke = bend_stiffness * 3|e| / (A1 + A2) per interior edge (rest length |e|, rest "
            "areas A1, A2 of its triangles); edge_rest_length = |e|; rest angle 0",
            "edge_ke_N": newton.summary()["edge_ke_N"],
        },
        "membrane_conversion_loss": membrane_conversion_loss(material, EXPORT_MEMBRANE),
        "membrane_alternative": _membrane_alternative(material),
        "edges": {
            "order": "(o0, o1, v0, v1) as newton.ModelBuilder.add_edges takes them: edge v0-v1, o0 and o1 "
            "the opposite corners",
            "indices": cloth.edge_indices.tolist(),
            "rest_length_m": cloth.edge_rest_length.tolist(),
            "edge_ke_N": newton.edge_ke.tolist(),
        },
        "held_vertices": model.attach_vertices.cpu().tolist(),
    }


def _membrane_alternative(material: ClothMaterial) -> dict:
    """The membrane conversion other than `EXPORT_MEMBRANE` (`newton_units.membrane_to_newton`): its
    tri_ke, tri_ka and loss."""
    keep = next(k for k in MEMBRANE_KEEPS if k != EXPORT_MEMBRANE)
    mu, lam = membrane_to_newton(
        *(float(getattr(material, k)) for k in ("k_uu", "k_vv", "k_uv", "poisson")), keep=keep
    )
    return {
        "keep": keep,
        "note": "shear: mu = k_uv, lambda = max(sqrt(k_uu k_vv) - 2 k_uv, 0); stretch: lambda = poisson "
        "sqrt(k_uu k_vv), mu = (sqrt(k_uu k_vv) - lambda) / 2; scripts/newton_check.py --membrane " + keep,
        "tri_ke": {"value": mu, "unit": "N/m"},
        "tri_ka": {"value": lam, "unit": "N/m"},
        "membrane_conversion_loss": membrane_conversion_loss(material, keep=keep),
    }


@dataclass(frozen=True)
class NewtonExport:
    """An asset's garment as Newton takes it (`read_newton_material`).

    Attributes:
        cloth: the seam-merged mesh, rest shapes, masses and edges (`NewtonCloth`).
        material: Newton's parameters (`NewtonMaterial`, ``edge_ke`` per edge of ``cloth``).
        held_vertices: (A,) int64 draped.obj vertices to pin on the body (maybe empty).
        membrane_keep: the membrane conversion of ``material`` (``"shear"`` or ``"stretch"``).
        bend_stiffness: our k_b [N·m] (the file's ``bending``), for edges other than the exported ones.
    """

    cloth: NewtonCloth
    material: NewtonMaterial
    held_vertices: np.ndarray
    membrane_keep: str
    bend_stiffness: float


def read_newton_material(assets, membrane: str | None = None) -> NewtonExport:
    """The `NewtonExport` of an asset folder read by `assets.load_assets`: ``material_newton.json`` with
    draped.obj's triangles and their rest.obj ``vt`` corners. ``membrane`` (``"shear"`` / ``"stretch"``,
    `newton_units.MEMBRANE_KEEPS`): which membrane conversion's tri_ke / tri_ka to take, ``parameters``' or
    ``membrane_alternative``'s; None: ``parameters``'.

    Raises:
        InputError: no ``material_newton.json`` (an asset written before it existed) or edges that do not
            fit the mesh.
    """
    from torch_diffavatar.errors import InputError, read_json_file

    entry = assets.manifest["files"].get("material_newton_json")
    path = Path(assets.path) / (entry["path"] if entry else "material_newton.json")
    data = read_json_file(path, f"{path}: missing; write the assets again (write_assets writes it)")
    p, edges = data["parameters"], data["edges"]
    g = assets.garment
    indices = np.asarray(edges["indices"], dtype=np.int64).reshape(-1, 4)
    edge_ke = np.asarray(edges["edge_ke_N"], dtype=np.float64)
    if (
        len(indices)
        and (indices.min() < 0 or indices.max() >= g.sim_vert_count)
        or len(edge_ke) != len(indices)
    ):
        raise InputError(f"{path}: edges do not fit draped.obj's {g.sim_vert_count} vertices")
    tri = g.tri_vertices.numpy()
    cloth = newton_cloth_from_arrays(
        g.vert_to_sim.numpy()[tri],
        assets.rest_uv.double().numpy()[tri],
        indices,
        edges["rest_length_m"],
        p["density"]["value"],
        g.sim_vert_count,
    )
    if membrane is not None and membrane != data.get("membrane_keep"):
        alternative = data.get("membrane_alternative", {})
        if alternative.get("keep") != membrane:
            raise InputError(f"{path}: no {membrane!r} membrane; one of {', '.join(MEMBRANE_KEEPS)}")
        p = dict(p, **{k: alternative[k] for k in ("tri_ke", "tri_ka")})
    material = NewtonMaterial(
        **{attr: float(p[name]["value"]) for name, (attr, _, _) in NEWTON_PARAMETERS.items()}, edge_ke=edge_ke
    )
    held = np.asarray(data.get("held_vertices", []), dtype=np.int64)
    keep = membrane or data.get("membrane_keep", "shear")
    return NewtonExport(cloth, material, held, keep, float(data["bending"]["bend_stiffness_N_m"]))


def unmerged_newton_export(assets, export: NewtonExport) -> NewtonExport:
    """``export`` on the asset's UNMERGED panel meshes: one particle per rest.obj vertex, the seams as
    zero-length springs on seams.json's ``stitch_pairs`` (`NewtonCloth.spring_pairs`), the bending on the
    panels' interior edges by the file's rule (``edge_ke = k_b 3|e|/(A1+A2)``; no edge across a seam), the
    held vertices every panel vertex of a held draped vertex. Same material otherwise."""
    from dataclasses import replace

    from torch_diffavatar.sim.model import ClothModelBuilder

    g, uv = assets.garment, assets.rest_uv.double()
    model = ClothModelBuilder(ClothMaterial()).add_garment(g, merge_seams=False).finalize(dtype=torch.float64)
    weight, length = edge_geometry(model, uv)
    cloth = replace(
        newton_cloth(model, uv, export.material.density), spring_pairs=g.stitch_pairs.reshape(-1, 2).numpy()
    )
    material = replace(export.material, edge_ke=bend_to_newton(export.bend_stiffness, weight, length))
    held = np.flatnonzero(np.isin(g.vert_to_sim.numpy(), export.held_vertices))
    return replace(export, cloth=cloth, material=material, held_vertices=held)
