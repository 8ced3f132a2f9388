"""How a drape's equilibrium moves with its inputs: the linearization that the equilibrium adjoint's
backward builds, kept to predict where the next drape settles (a warm start that lands).

At the drape's end x* the force ∇ₓU(x*; θ) of the drape energy (`sim/energy.py`) is XPBD's residual r*
(about zero). When the inputs change, θ → θ' (the pattern, the body, the waist, the material), the
equilibrium moves, to first order, by ``δx = −H⁻¹ (∇ₓU(x*; θ') − ∇ₓU(x*; θ))`` with H the adjoint's matrix
at (x*, θ) — the matrix the backward has just factored for its own solve, so the prediction costs two
energy gradients and two triangular solves. Subtracting the old force, rather than solving for
∇ₓU(x*; θ') alone, keeps XPBD's residual out of the step: the drape's end is XPBD's fixed point, not U's
minimiser, and the prediction must not move the cloth towards the latter.

`predicted_start` applies it in the next forward when that drape starts exactly at x* (the fit's warm
start); the XPBD drape then settles from the predicted positions as from any start, so the prediction
only changes how many frames the drape needs, and where it stops within the settle test's tolerance.

A `Linearization` holds its inputs (plain tensors, `state_dict`) besides the factor, so that a fit resumed
from a checkpoint rebuilds the very same factor (`adjoint_matrix`, the backward's own assembly) and its
drapes come out bit for bit as in the uninterrupted run.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torch_diffavatar.sim.adjoint.common import DrapeSetup, material_with
from torch_diffavatar.sim.adjoint.linsolve import CholeskyFactor, cholesky_factor
from torch_diffavatar.sim.collision import Contacts, contact_frames
from torch_diffavatar.sim.energy import (
    EnergyParams,
    HessianPattern,
    drape_energy,
    hessian_blocks,
    hessian_pattern,
)

# A predicted move beyond this [m] is not trusted; the drape then starts where it would have without one.
# Measured on the demo dress (2k vertices, scripts/bench_fit.py --reference 200): the fit's first steps
# move the cloth by 1.4-4.5 cm; predictions that large landed drapes 2-5 mm (mean) from a 200-frame drape
# of the same step, against 0.2-0.5 mm without a prediction; below 1 cm they landed 0.2-0.6 mm from it.
MAX_PREDICTED_MOVE = 0.01


@dataclass
class Linearization:
    """The equilibrium adjoint's matrix at a drape's end, and the inputs it was built from.

    Attributes:
        x: (Vs, 3) the drape's end x* [m]; contacts: the active contacts of the energy there (or None);
        rest_uv: (V, 2) [m]; body_verts: (Vb, 3) [m] or None; attach_height: (A,) [m];
        material_names, material_values: the differentiable material fields and their values (0-dim);
        factor: the Cholesky factor of the adjoint's matrix (`adjoint_matrix`) at these inputs; None until
            `factored` builds it (a linearization restored from a checkpoint).
    """

    x: torch.Tensor
    contacts: Contacts | None
    rest_uv: torch.Tensor
    body_verts: torch.Tensor | None
    attach_height: torch.Tensor
    material_names: tuple[str, ...]
    material_values: tuple[torch.Tensor, ...]
    factor: CholeskyFactor | None = None

    def state_dict(self) -> dict:
        """Its inputs as plain tensors and strings (a checkpoint's; the factor is rebuilt from them)."""
        c = self.contacts
        return {
            "x": self.x,
            "contacts": None if c is None else {"vert": c.vert, "tri": c.tri, "bary": c.bary},
            "rest_uv": self.rest_uv,
            "body_verts": self.body_verts,
            "attach_height": self.attach_height,
            "material_names": list(self.material_names),
            "material_values": list(self.material_values),
        }

    @classmethod
    def from_state_dict(cls, state: dict) -> Linearization:
        c = state["contacts"]
        contacts = None if c is None else Contacts(c["vert"], c["tri"], c["bary"])
        names, values = tuple(state["material_names"]), tuple(state["material_values"])
        return cls(
            state["x"], contacts, state["rest_uv"], state["body_verts"], state["attach_height"], names, values
        )

    def matches(self, setup: DrapeSetup) -> bool:
        """True when a drape of ``setup`` starts exactly at this x* with the same differentiable fields."""
        return (
            self.x.shape == setup.x0.shape
            and self.x.dtype == setup.x0.dtype
            and torch.equal(self.x, setup.x0)
            and self.material_names == setup.material_names
            and (self.body_verts is None) == (setup.body_faces is None)
        )

    def factored(self, setup: DrapeSetup, params: EnergyParams, opts) -> CholeskyFactor | None:
        """`factor`, built from the inputs on first use (None when the matrix is not positive definite)."""
        if self.factor is None:
            model = setup.model
            material = material_with(setup.material, self.material_names, self.material_values)
            rest = model.rest_data(self.rest_uv, material, self.attach_height)
            pattern, val = adjoint_matrix(
                self.x, setup, rest, material, params, self.body_verts, self.contacts, opts
            )
            self.factor, _ = cholesky_factor(pattern.crow, pattern.col, val, pattern.solver_cache)
        return self.factor


def free_dofs(rest, model) -> tuple[torch.Tensor, torch.Tensor, int]:
    """(3·Vs,) bool the free dofs, (3·Vs,) int64 their index among them (−1 pinned), their count."""
    free_vert = rest.vert_inv_mass.detach() > 0
    free_dof = free_vert[:, None].expand(-1, 3).reshape(-1)
    idx = torch.full(free_dof.shape, -1, dtype=torch.int64, device=free_dof.device)
    n = int(free_dof.sum())
    idx[free_dof] = torch.arange(n, device=free_dof.device)
    return free_dof, idx, n


def energy_gradient(x, setup: DrapeSetup, rest, material, params, body_verts, contacts):
    """(U (), ∇ₓU (Vs, 3)) of the drape energy at ``x`` (no graph kept)."""
    with torch.enable_grad():
        xl = x.detach().requires_grad_(True)
        u = drape_energy(
            xl, setup.model, rest, material, params,
            body_verts=body_verts, body_faces=setup.body_faces, contacts=contacts,
        )  # fmt: skip
        (g,) = torch.autograd.grad(u, xl)
    return u.detach(), g


def adjoint_matrix(
    x, setup: DrapeSetup, rest, material, params, body_verts, contacts, opts
) -> tuple[HessianPattern, torch.Tensor]:
    """The equilibrium adjoint's matrix over the free dofs at ``x``: its `HessianPattern` and (nnz,) float64
    CSR values — ∇²ₓU (``opts.hessian == "exact"``) or its PSD-projected form plus ``opts.regularization``
    × the largest diagonal entry."""
    model = setup.model
    project = opts.hessian == "projected"
    # float64 element Hessians, assembled through the model's cached CSR pattern (exactly symmetric)
    blocks = hessian_blocks(
        x, model, rest, material, params, body_verts=body_verts, body_faces=setup.body_faces,
        contacts=contacts, project=project, dtype=torch.float64, use_extension=opts.use_extension,
    )  # fmt: skip
    shift = opts.regularization * blocks.max_diagonal() if project and opts.regularization > 0 else 0.0
    free_dof, _, _ = free_dofs(rest, model)
    pattern = hessian_pattern(model, free_dof[0::3])
    return pattern, pattern.assemble(blocks, shift)


def predicted_start(
    setup: DrapeSetup, rest, material, params: EnergyParams, body_verts, opts
) -> tuple[torch.Tensor, float]:
    """The start of the drape of ``setup``: ``setup.x0`` moved by the first-order prediction of its
    `Linearization` (``setup.linearization``) to the new inputs (``rest``, ``material``, ``body_verts``),
    and the largest predicted move [m]; ``setup.x0`` and 0 when there is none that applies (no
    linearization, another start, a matrix that cannot be factored, a move beyond `MAX_PREDICTED_MOVE`)."""
    lin: Linearization | None = setup.linearization
    x0 = setup.x0
    if lin is None or not lin.matches(setup):
        return x0, 0.0
    factor = lin.factored(setup, params, opts)
    if factor is None:
        return x0, 0.0
    model = setup.model
    old_material = material_with(setup.material, lin.material_names, lin.material_values)
    old_rest = model.rest_data(lin.rest_uv, old_material, lin.attach_height)
    _, g_old = energy_gradient(x0, setup, old_rest, old_material, params, lin.body_verts, lin.contacts)
    _, g_new = energy_gradient(x0, setup, rest, material, params, body_verts, lin.contacts)
    free_dof, _, _ = free_dofs(rest, model)
    step = torch.zeros_like(x0).reshape(-1)
    step[free_dof] = -factor.solve((g_new - g_old).reshape(-1)[free_dof].to(torch.float64)).to(x0.dtype)
    step = _held_by_friction(step.reshape(-1, 3), setup, material, body_verts, lin.contacts)
    move = float(step.norm(dim=-1).max()) if step.numel() else 0.0
    if not move <= MAX_PREDICTED_MOVE:  # also NaN
        return x0, 0.0
    return x0 + step, move


def _held_by_friction(step, setup: DrapeSetup, material, body_verts, contacts: Contacts | None):
    """``step`` (Vs, 3) [m] with the tangential part of the contact vertices' moves removed when the cloth
    has friction: the energy has none, so its response slides the cloth over the body where static friction
    holds it (measured on the demo dress: the drape then landed 0.2-0.5 mm instead of 0.5-0.8 mm from a
    200-frame drape of the same step in the late iterations)."""
    if contacts is None or body_verts is None or not float(material.friction) > 0:
        return step
    _, normal = contact_frames(body_verts.detach().to(step.dtype), setup.body_faces, contacts)
    step = step.clone()
    # a vertex with two contacts (a valley) keeps the part of its move along both normals in turn
    for idx in [None] if contacts.layers is None else contacts.layers:
        vert, n = (contacts.vert, normal) if idx is None else (contacts.vert[idx], normal[idx])
        step[vert] = (step[vert] * n).sum(-1, keepdim=True) * n
    return step
