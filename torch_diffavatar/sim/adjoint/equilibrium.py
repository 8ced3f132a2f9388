"""The equilibrium adjoint: implicit differentiation of the draped rest state (one sparse solve).

The drape ends at quasi-equilibrium, so its result x* minimises the drape energy ``U(x; θ)`` of
`sim/energy.py` (stretch + bend + gravity + stitches + attachments + the frozen active contacts) over the
free vertices: ``∇ₓU(x*; θ) = 0``. Forward: the XPBD drape (`drape_to_equilibrium`), then the active
contact set (vertices within ``contact_tol`` of the body's surface offset), then a projected-Newton polish
(per-element Hessians projected to PSD, sparse solve, backtracking line search) to a tight force
residual, with primal active-set updates (release contacts that pull, add vertices that penetrate).
Backward: ``H λ = ∂φ/∂x`` with the exact sparse Hessian H = ∇²ₓU (free dofs), then
``dφ/dθ = −λᵀ ∂(∇ₓU)/∂θ`` by one double-backward through ∇ₓU with λ detached. H is built from
closed-form float64 element Hessians (`energy.hessian_blocks`, C++) scattered through the model's cached
CSR pattern (`energy.hessian_pattern`), and the fit's projected H is solved by the block sparse Cholesky
of `linsolve` whose ordering and symbolic analysis are computed once per model.

Limitations: the result is the minimiser of U, which the XPBD drape approximates (finite iterations,
friction, damping); friction is not in U, so a frictionless minimiser must exist (pinned or attached
cloth, or cloth resting in a stable position); the contact set is frozen (its changes are not
differentiated); a singular or strongly indefinite H is reported (warning or `SimulationError`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torch_diffavatar.sim import collision
from torch_diffavatar.sim.adjoint.common import DrapeSetup, Gradients, contacts_subset, material_with
from torch_diffavatar.sim.adjoint.linearization import (
    Linearization,
    adjoint_matrix,
    energy_gradient,
    free_dofs,
    predicted_start,
)
from torch_diffavatar.sim.adjoint.linsolve import SOLVE_METHODS, check_solve, solve_symmetric
from torch_diffavatar.sim.collision import Contacts
from torch_diffavatar.sim.energy import EnergyParams, drape_energy, hessian_blocks, hessian_pattern
from torch_diffavatar.sim.forward_drape import drape_to_equilibrium
from torch_diffavatar.sim.state import ClothState

HESSIANS = ("exact", "projected")


@dataclass(frozen=True)
class EquilibriumOptions:
    """Options of the equilibrium adjoint.

    Attributes:
        newton_iterations: Newton steps at most per active-set round.
        newton_tol: stop when the largest free-dof force |∇ₓU| is below this fraction of the largest
            vertex weight m_i |g| (float32 models use at least 1e-4).
        active_set_rounds: active-set updates at most.
        contact_stiffness: stiffness of the active-contact quadratic [N/m].
        contact_tol: a vertex starts active when its distance to the body is below thickness + this [m].
        contact_release: release an active contact when its quadratic pulls the vertex towards the body
            with more than this fraction of the vertex's weight m_i |g| (s − thickness >
            contact_release · m_i |g| / contact_stiffness), and add a vertex that penetrates by as much.
            The tolerance is a force, not a length: a fixed 1e-7 m slack let a 1e4 N/m contact pull with
            1e-3 N, about a vertex weight at 3 cm spacing, and on the frictionless 0.03 m dress 11 such
            adhesive contacts held cloth that XPBD's fixed point lifts 10–190 µm off (the body-gradient
            cosine to XPBD's N → ∞ limit was 0.985 with them, 0.9994 without; see bench_grad.py) [-].
        solve_method: adjoint solve method (`linsolve.SOLVE_METHODS`); newton_solve_method: the polish's.
        solve_tol: relative residual the adjoint solve aims at; a solve whose backward error exceeds it
            (or the gradient dtype's epsilon) warns, a relative residual beyond 1e-3 raises
            (`linsolve.check_solve`).
        hessian: the adjoint system's matrix. ``"exact"``: ∇²ₓU, the exact implicit gradient at a
            converged minimiser (what the gradchecks test). ``"projected"``: every element Hessian
            projected to PSD plus ``regularization`` × its largest diagonal entry on the diagonal — an
            approximation (Gauss–Newton-like) that stays solvable where the exact H is indefinite or
            singular: drapes stopped by a speed test rather than polished to a minimiser, compressed
            cloth, frictionless sliding modes. The fit uses it.
        regularization: see ``hessian`` (relative to the largest diagonal entry) [-].
        use_extension: use the C++ solve op when built.
        keep_linearization: when the solve was a Cholesky factorisation, leave its factor and inputs in
            the drape's ``stats["linearization"]`` (`linearization.Linearization`) for the next drape's
            warm start; False frees the factor with the backward.
    """

    newton_iterations: int = 30
    newton_tol: float = 1e-9
    active_set_rounds: int = 5
    contact_stiffness: float = 1e4
    contact_tol: float = 2e-4
    contact_release: float = 1e-3
    solve_method: str = "auto"
    newton_solve_method: str = "direct"
    solve_tol: float = 1e-8
    hessian: str = "exact"
    regularization: float = 1e-6
    use_extension: bool = True
    keep_linearization: bool = True

    def __post_init__(self):
        for name in ("solve_method", "newton_solve_method"):
            if getattr(self, name) not in SOLVE_METHODS:
                raise ValueError(f"EquilibriumOptions.{name} must be one of {SOLVE_METHODS}")
        if self.hessian not in HESSIANS:
            raise ValueError(f"EquilibriumOptions.hessian must be one of {HESSIANS}, got {self.hessian!r}")
        if not self.contact_release >= 0:
            raise ValueError(f"EquilibriumOptions.contact_release must be >= 0, got {self.contact_release}")
        if not self.regularization >= 0:
            raise ValueError(f"EquilibriumOptions.regularization must be >= 0, got {self.regularization}")


def _params(setup: DrapeSetup, opts: EquilibriumOptions) -> EnergyParams:
    x = setup.config.xpbd
    return EnergyParams(x.gravity, x.stitch_compliance, x.attach_compliance, opts.contact_stiffness)


def newton_polish(setup, rest, material, params, body_verts, contacts, x, opts, stats):
    """Projected Newton on U over the free dofs from ``x``; returns (x, iterations, force residual)."""
    model = setup.model
    free_dof, _, nfree = free_dofs(rest, model)
    weight = float((rest.vert_mass.detach() * x.new_tensor(params.gravity).norm()).max())
    tol = max(opts.newton_tol, 1e-4 if x.dtype == torch.float32 else 0.0) * weight
    energy = lambda y: drape_energy(  # noqa: E731
        y,
        model,
        rest,
        material,
        params,
        body_verts=body_verts,
        body_faces=setup.body_faces,
        contacts=contacts,
    )
    it, gmax = 0, float("inf")
    # exact Newton while H is positive definite, else projected; once the exact H has been indefinite
    # the polish stays projected (far from the minimiser the exact attempt only costs a Hessian: on the
    # 2k-vertex dress it failed in every iteration and doubled the polish time)
    tries = (False, True)
    for it in range(opts.newton_iterations + 1):  # noqa: B007
        u0, g = energy_gradient(x, setup, rest, material, params, body_verts, contacts)
        gf = g.reshape(-1)[free_dof]
        gmax = float(gf.abs().max()) if nfree else 0.0
        if gmax <= tol or it == opts.newton_iterations:
            break
        d = None
        pattern = hessian_pattern(model, free_dof[0::3])
        for project in tries:
            blocks = hessian_blocks(
                x, model, rest, material, params, body_verts=body_verts, body_faces=setup.body_faces,
                contacts=contacts, project=project, use_extension=opts.use_extension,
            )  # fmt: skip
            val = pattern.assemble(blocks, 1e-10 * blocks.max_diagonal()).to(x.dtype)
            method = "cg" if not project else opts.newton_solve_method
            # the exact-H CG attempt is capped: when it stalls, the projected Newton step is cheaper
            d, info = solve_symmetric(
                pattern.crow, pattern.col, val, -gf, method=method, tol=1e-10, max_iter=2000,
                use_extension=opts.use_extension, cache=pattern.solver_cache,
            )  # fmt: skip
            if not info.indefinite and info.residual < 1e-6:
                break
            tries = (True,)
        slope = float((gf * d).sum())
        if slope >= 0:  # not a descent direction (solve failed): steepest descent
            d, slope = -gf, -float((gf * gf).sum())
        step = torch.zeros_like(g).reshape(-1)
        t, accepted = 1.0, False
        with torch.no_grad():
            while t > 1e-8:
                step[free_dof] = t * d
                x_new = x + step.reshape(-1, 3)
                u1 = float(energy(x_new))
                if u1 <= float(u0) + 1e-4 * t * slope + 1e-13 * abs(float(u0)):
                    accepted = True
                    break
                t *= 0.5
        if not accepted:
            break
        x = x_new
    return x, it, gmax


def _signed(x, setup, body_verts, contacts):
    return collision.signed_distance_along_normal(x, body_verts, setup.body_faces, contacts)


def initial_contacts(x, setup, material, body_verts, opts) -> Contacts | None:
    """Vertices within ``thickness + contact_tol`` of their closest body triangle's plane."""
    if body_verts is None:
        return None
    thick = float(material.thickness)
    c = _detect(x, setup, material, body_verts, opts)
    if c.count == 0:
        return None
    s = _signed(x, setup, body_verts, c)
    c = contacts_subset(c, s < thick + opts.contact_tol)
    return c if c.count else None


def _detect(x, setup, material, body_verts, opts) -> Contacts:
    """The contacts within the XPBD drape's band, valley and floor contacts as the drape has them."""
    xpbd = setup.config.xpbd
    band = float(material.thickness) + xpbd.collision_band
    return collision.detect_contacts(
        x, body_verts, setup.body_faces, band, use_extension=opts.use_extension,
        valley=xpbd.valley_radius(material.thickness),
        floor=xpbd.floor_contacts(setup.body_faces.shape[0], material.thickness),
    )  # fmt: skip


def _not_held(cand: Contacts, contacts: Contacts, face_count: int) -> torch.Tensor:
    """(C_cand,) bool: candidates the active set does not have: a vertex's first contact when the vertex
    has none, a valley or floor contact (a vertex's second or third) when its (vertex, triangle) pair is not
    held."""
    pair = cand.vert * face_count + cand.tri
    held_pair = torch.isin(pair, contacts.vert * face_count + contacts.tri)
    first = torch.ones_like(cand.vert, dtype=torch.bool)
    if cand.layers is not None:
        first[torch.cat(cand.layers[1:])] = False
    return torch.where(first, ~torch.isin(cand.vert, contacts.vert), ~held_pair)


def _contact_slack(rest, setup, opts, vert):
    """(C,) the length s − thickness at which vertex ``vert``'s contact force is ``contact_release`` × its
    weight [m] (at least 50 ulp: the signed distance's rounding)."""
    g = float(torch.tensor(setup.config.xpbd.gravity, dtype=torch.float64).norm())
    weight = rest.vert_mass.detach()[vert] * g
    eps = 50 * torch.finfo(weight.dtype).eps
    return (opts.contact_release * weight / opts.contact_stiffness).clamp_min(eps)


def _update_active_set(x, setup, rest, material, body_verts, contacts, opts):
    """Release contacts that pull (s > thickness + slack), add penetrating vertices (s < thickness −
    slack); the slack is `_contact_slack`.

    Returns:
        (contacts, changed).
    """
    thick = float(material.thickness)
    changed = False
    if contacts is not None:
        s = _signed(x, setup, body_verts, contacts)
        keep = s <= thick + _contact_slack(rest, setup, opts, contacts.vert)
        if not bool(keep.all()):
            changed = True
            contacts = contacts_subset(contacts, keep)
    cand = _detect(x, setup, material, body_verts, opts)
    if cand.count:
        s = _signed(x, setup, body_verts, cand)
        new = s < thick - _contact_slack(rest, setup, opts, cand.vert)
        if contacts is not None and contacts.count:
            new &= _not_held(cand, contacts, setup.body_faces.shape[0])
        if bool(new.any()):
            changed = True
            add = contacts_subset(cand, new)
            if contacts is None or contacts.count == 0:
                contacts = add
            else:
                contacts = Contacts(
                    torch.cat((contacts.vert, add.vert)),
                    torch.cat((contacts.tri, add.tri)),
                    torch.cat((contacts.bary, add.bary)),
                )
    if contacts is not None and contacts.count == 0:
        contacts = None
    return contacts, changed


def equilibrium_forward(
    setup: DrapeSetup, rest_uv, body_verts, attach_height, material_values
) -> torch.Tensor:
    """XPBD drape, active set, Newton polish. Saves x* and the contact set in ``setup.saved``."""
    opts: EquilibriumOptions = setup.options
    model = setup.model
    material = material_with(setup.material, setup.material_names, material_values)
    rest = model.rest_data(rest_uv, material, attach_height)
    params = _params(setup, opts)
    x_start, predicted_move = predicted_start(setup, rest, material, params, body_verts, opts)
    res = drape_to_equilibrium(
        model,
        rest_uv,
        body_verts=body_verts,
        body_faces=setup.body_faces,
        material=material,
        state=ClothState(x_start, setup.v0),
        config=setup.config,
        attach_height=attach_height,
    )
    x = res.x
    contacts = initial_contacts(x, setup, material, body_verts, opts)
    total_it, gmax, rounds = 0, float("inf"), 0
    for rounds in range(1, opts.active_set_rounds + 1):  # noqa: B007
        x, it, gmax = newton_polish(setup, rest, material, params, body_verts, contacts, x, opts, setup.stats)
        total_it += it
        if body_verts is None:
            break
        contacts, changed = _update_active_set(x, setup, rest, material, body_verts, contacts, opts)
        if not changed:
            break
    setup.saved.update(x=x, contacts=contacts)
    setup.record(
        xpbd_steps=res.steps,
        xpbd_converged=res.converged,
        xpbd_max_speed=res.max_speed,
        predicted_move=predicted_move,
        polish_displacement=float((x - res.x).norm(dim=-1).max()),
        newton_iterations=total_it,
        newton_force_residual=gmax,
        active_set_rounds=rounds,
        active_contacts=0 if contacts is None else contacts.count,
    )
    return x


def equilibrium_backward(
    setup: DrapeSetup, rest_uv, body_verts, attach_height, material_values, grad_x, needs, grad_frames=None
) -> Gradients:
    """``−λᵀ ∂(∇ₓU)/∂θ`` with ``H λ = grad_x`` (free dofs)."""
    opts: EquilibriumOptions = setup.options
    model = setup.model
    x, contacts = setup.saved["x"], setup.saved["contacts"]
    need_uv, need_body, need_attach, need_mat = needs
    material = material_with(setup.material, setup.material_names, material_values)
    params = _params(setup, opts)
    rest = model.rest_data(rest_uv.detach(), material, attach_height)
    free_dof, _, nfree = free_dofs(rest, model)
    pattern, val = adjoint_matrix(x, setup, rest, material, params, body_verts, contacts, opts)
    # The solve runs in float64 whatever the model's dtype: the cloth's stiffness spread makes H too
    # ill-conditioned for a float32 factorisation (measured: relative residual ~5e-4 on the dress).
    b = grad_x.reshape(-1)[free_dof].to(torch.float64)
    lam_free, info = solve_symmetric(
        pattern.crow, pattern.col, val, b, method=opts.solve_method, tol=opts.solve_tol,
        use_extension=opts.use_extension, cache=pattern.solver_cache,
    )  # fmt: skip
    lam_free = lam_free.to(x.dtype)
    if info.factor is not None and opts.keep_linearization:  # the next drape's start predicts with it
        detached = tuple(v.detach() for v in material_values)
        body = None if body_verts is None else body_verts.detach()
        linearization = Linearization(
            x, contacts, rest_uv.detach(), body, attach_height.detach(), setup.material_names, detached,
            info.factor,
        )  # fmt: skip
        setup.record(linearization=linearization)
    setup.record(
        adjoint_solve_method=info.method,
        adjoint_solve_iterations=info.iterations,
        adjoint_solve_residual=info.residual,
        adjoint_solve_backward_error=info.backward_error,
        adjoint_hessian_indefinite=info.indefinite,
        adjoint_dofs=nfree,
    )
    check_solve(info, opts.solve_tol, "equilibrium adjoint", x.dtype)
    lam = x.new_zeros(3 * model.vert_count)
    lam[free_dof] = lam_free
    lam = lam.reshape(-1, 3)
    out = Gradients(material=tuple(None for _ in need_mat))
    with torch.enable_grad():
        uv_l = rest_uv.detach().requires_grad_(need_uv)
        mats = tuple(m.detach().requires_grad_(n) for m, n in zip(material_values, need_mat))
        body_l = body_verts.detach().requires_grad_(need_body) if body_verts is not None else None
        attach_l = attach_height.detach().requires_grad_(need_attach)
        mat_l = material_with(setup.material, setup.material_names, mats)
        rest_l = model.rest_data(uv_l, mat_l, attach_l)
        xl = x.detach().requires_grad_(True)
        u = drape_energy(
            xl,
            model,
            rest_l,
            mat_l,
            params,
            body_verts=body_l,
            body_faces=setup.body_faces,
            contacts=contacts,
        )
        (g,) = torch.autograd.grad(u, xl, create_graph=True)
        wrt = (
            ([uv_l] if need_uv else [])
            + ([body_l] if need_body and body_l is not None else [])
            + ([attach_l] if need_attach else [])
            + [m for m, n in zip(mats, need_mat) if n]
        )
        if not wrt:
            return out
        grads = torch.autograd.grad((g * lam).sum(), wrt, allow_unused=True)
    grads = [torch.zeros_like(w) if gr is None else -gr for gr, w in zip(grads, wrt)]
    if need_uv:
        out.rest_uv = grads.pop(0)
    if need_body and body_l is not None:
        out.body_verts = grads.pop(0)
    if need_attach:
        out.attach_height = grads.pop(0)
    out.material = tuple(grads.pop(0) if n else None for n in need_mat)
    return out
