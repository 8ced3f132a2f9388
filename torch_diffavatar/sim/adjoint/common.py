"""Pieces shared by the two adjoints: the material split, the saved forward data, gradient bookkeeping.

The differentiable inputs of a drape are the panel rest coordinates ``rest_uv`` (V, 2), the body vertices
(Vb, 3), the attached vertices' target heights (A,) and the material tensors that require grad (0-dim
fields of `ClothMaterial`). They travel through `_Drape.apply` as explicit tensors; `material_with`
rebuilds the material from them inside the forward/backward so autograd sees every leaf.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import torch

from torch_diffavatar.sim.collision import Contacts
from torch_diffavatar.sim.forward_drape import DrapeConfig
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.model import ClothModel

# Material fields whose gradient both adjoints provide (they enter the rest data / the energy).
DIFFERENTIABLE_MATERIAL_FIELDS = ("bend_stiffness", "k_uu", "k_vv", "k_uv", "poisson", "areal_density")


def material_tensor_fields(material: ClothMaterial) -> tuple[tuple[str, ...], tuple[torch.Tensor, ...]]:
    """Names and values of the material fields that are tensors requiring grad.

    Raises:
        ValueError: a field outside `DIFFERENTIABLE_MATERIAL_FIELDS` (damping, friction, thickness)
            requires grad, or a differentiable field is not a 0-dim tensor.
    """
    names, values = [], []
    for f in dataclasses.fields(material):
        value = getattr(material, f.name)
        if not (isinstance(value, torch.Tensor) and value.requires_grad):
            continue
        if f.name not in DIFFERENTIABLE_MATERIAL_FIELDS:
            raise ValueError(
                f"ClothMaterial.{f.name} requires grad but drape() differentiates only "
                f"{DIFFERENTIABLE_MATERIAL_FIELDS}; pass it as a float or detach it"
            )
        if value.ndim != 0:
            raise ValueError(f"ClothMaterial.{f.name} must be a 0-dim tensor, got shape {tuple(value.shape)}")
        names.append(f.name)
        values.append(value)
    return tuple(names), tuple(values)


def material_with(material: ClothMaterial, names: tuple[str, ...], values) -> ClothMaterial:
    """``material`` with the fields ``names`` replaced by ``values`` (tensors)."""
    if not names:
        return material
    return dataclasses.replace(material, **dict(zip(names, values)))


@dataclass
class DrapeSetup:
    """What the forward and backward share (rides on ``ctx``; no tensors that need saving).

    Attributes:
        model: the cloth model; material: the material WITHOUT the differentiable fields' graph (their
            values are passed separately); material_names: names of the differentiable material fields;
        body_faces: (Fb, 3) int64 or None; config: drape options; x0: (Vs, 3) start positions [m];
        v0: (Vs, 3) start velocities [m/s]; options: the adjoint's own options (a dataclass);
        stats: caller-owned dict that forward/backward fill with diagnostics (or None);
        linearization: the start state's `linearization.Linearization` (the equilibrium adjoint predicts
            the drape's end with it), or None.
    """

    model: ClothModel
    material: ClothMaterial
    material_names: tuple[str, ...]
    body_faces: torch.Tensor | None
    config: DrapeConfig
    x0: torch.Tensor
    v0: torch.Tensor
    options: object
    stats: dict | None = None
    linearization: object | None = None
    saved: dict = field(default_factory=dict)

    def record(self, **values) -> None:
        if self.stats is not None:
            self.stats.update(values)


@dataclass
class Gradients:
    """One adjoint's result: gradients of the scalar objective for each differentiable input (or None)."""

    rest_uv: torch.Tensor | None = None
    body_verts: torch.Tensor | None = None
    attach_height: torch.Tensor | None = None
    material: tuple[torch.Tensor | None, ...] = ()


def contacts_subset(contacts: Contacts, keep: torch.Tensor) -> Contacts:
    """The contacts selected by the (C,) bool mask ``keep``."""
    return Contacts(contacts.vert[keep], contacts.tri[keep], contacts.bary[keep])
