"""The differentiable drape: `drape()` and the `_Drape` autograd.Function (paper §3.3, eqs. 3–5).

``x = drape(rest_uv, garment, body_verts, material, body_faces=..., adjoint="equilibrium")`` runs the XPBD
drape under ``no_grad`` and returns the final (Vs, 3) positions; ``x.backward(...)`` (or any loss of x)
reaches ``rest_uv`` (the 2D pattern), ``body_verts`` (through the body contacts), ``attach_height`` (the
waist attachments' target heights, when given) and every material tensor that requires grad
(``bend_stiffness``, ``k_uu``, ``k_vv``, ``k_uv``, ``poisson``, ``areal_density``; e.g.
``ClothMaterial(bend_stiffness=log_kb.exp())``). Two adjoints, chosen by name:

* ``"trajectory"`` — DiffXPBD (`sim/adjoint/trajectory.py`): reverse-mode through every frame of the
  discrete drape from checkpoints; exact for the discrete trajectory; cost grows with the frames.
* ``"equilibrium"`` — implicit differentiation of the Newton-polished equilibrium
  (`sim/adjoint/equilibrium.py`): one sparse solve ``H λ = ∂φ/∂x`` per backward.

Example::

    log_kb = torch.tensor(-12.0, requires_grad=True)
    mat = ClothMaterial(bend_stiffness=log_kb.exp())
    x = drape(rest_uv, model, body_verts, mat, body_faces=faces, adjoint="equilibrium")
    loss = chamfer(x, scan); loss.backward()     # rest_uv.grad, body_verts.grad, log_kb.grad
"""

from __future__ import annotations

import time

import torch
from torch.autograd.function import once_differentiable

from torch_diffavatar.pattern.garment_mesh import GarmentMesh
from torch_diffavatar.sim.adjoint import ADJOINTS
from torch_diffavatar.sim.adjoint.common import DrapeSetup, material_tensor_fields, material_with
from torch_diffavatar.sim.forward_drape import DrapeConfig, collider, start_positions
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.model import ClothModel, ClothModelBuilder
from torch_diffavatar.sim.state import ClothState

__all__ = ["ADJOINTS", "drape"]


class _Drape(torch.autograd.Function):
    """XPBD drape with an adjoint backward. Inputs: setup (on ctx), rest_uv, body_verts, attach_height,
    *material tensors."""

    @staticmethod
    def forward(ctx, setup: DrapeSetup, rest_uv, body_verts, attach_height, *material_values):
        t0 = time.perf_counter()
        adjoint = ADJOINTS[setup.saved["adjoint"]]
        with torch.no_grad():
            # a new tensor: the adjoint keeps its own x in ``setup.saved``, and an output kept on ctx would
            # make a reference cycle through the graph that Python's collector cannot see (a drape's whole
            # setup, its linearization's factor too, was kept alive by every fit iteration)
            x = adjoint.forward(setup, rest_uv, body_verts, attach_height, material_values).clone()
        ro = setup.saved.get("rollout")
        frames = ro.frames if ro is not None and ro.frames is not None else x.new_zeros(0, *x.shape)
        ctx.setup = setup
        ctx.save_for_backward(rest_uv, body_verts, attach_height, *material_values)
        if frames.shape[0] == 0:
            ctx.mark_non_differentiable(frames)
        setup.record(forward_seconds=time.perf_counter() - t0)
        return x, frames

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_x, grad_frames):
        t0 = time.perf_counter()
        setup: DrapeSetup = ctx.setup
        rest_uv, body_verts, attach_height, *material_values = ctx.saved_tensors
        needs = ctx.needs_input_grad
        need_uv = needs[1]
        need_body = body_verts is not None and needs[2]
        need_attach = needs[3]
        need_mat = tuple(needs[4:])
        if not (need_uv or need_body or need_attach or any(need_mat)):
            return (None,) * len(needs)
        if grad_frames is not None and grad_frames.numel() == 0:
            grad_frames = None
        g = ADJOINTS[setup.saved["adjoint"]].backward(
            setup,
            rest_uv,
            body_verts,
            attach_height,
            tuple(material_values),
            grad_x,
            (need_uv, need_body, need_attach, need_mat),
            grad_frames,
        )
        setup.record(backward_seconds=time.perf_counter() - t0)
        return (
            None,
            g.rest_uv if need_uv else None,
            g.body_verts if need_body else None,
            g.attach_height if need_attach else None,
            *g.material,
        )


def _check_inputs(model: ClothModel, rest_uv, body_verts, body_faces):
    if not isinstance(rest_uv, torch.Tensor) or not rest_uv.is_floating_point():
        raise ValueError("rest_uv must be a floating-point tensor (V, 2) [m]")
    if rest_uv.shape != (model.panel_vert_count, 2):
        raise ValueError(f"rest_uv must have shape ({model.panel_vert_count}, 2), got {tuple(rest_uv.shape)}")
    if model.device.type != "cpu":
        raise ValueError(
            f"the ClothModel is on {model.device}, but the simulator runs on the CPU: finalize the model "
            "on the CPU and pass rest_uv and body_verts on any device (results come back on theirs)"
        )
    if rest_uv.dtype != model.dtype:
        raise ValueError(
            f"rest_uv is {rest_uv.dtype} but the model is {model.dtype}; finalize it with that dtype"
        )
    if (body_verts is None) != (body_faces is None):
        raise ValueError("pass both body_verts and body_faces, or neither")
    if body_verts is not None:
        if body_verts.ndim != 2 or body_verts.shape[1] != 3:
            raise ValueError(f"body_verts must be (Vb, 3), got {tuple(body_verts.shape)}")
        if body_verts.dtype != model.dtype or body_verts.device != rest_uv.device:
            raise ValueError(
                f"body_verts must be {model.dtype} on {rest_uv.device} (as rest_uv), got {body_verts.dtype} "
                f"on {body_verts.device}"
            )
        if body_faces.ndim != 2 or body_faces.shape[1] != 3 or body_faces.dtype != torch.int64:
            raise ValueError(
                f"body_faces must be (Fb, 3) int64, got {tuple(body_faces.shape)} {body_faces.dtype}"
            )


def _attach_height(model: ClothModel, attach_height) -> torch.Tensor:
    """``attach_height`` checked and on the CPU (differentiably), or the model's."""
    if attach_height is None:
        return model.attach_height
    expected = tuple(model.attach_height.shape)
    if not isinstance(attach_height, torch.Tensor) or tuple(attach_height.shape) != expected:
        got = tuple(attach_height.shape) if isinstance(attach_height, torch.Tensor) else type(attach_height)
        raise ValueError(
            f"attach_height must be a tensor of shape {expected} (one per attached vertex), got {got}"
        )
    if attach_height.dtype != model.dtype:
        raise ValueError(f"attach_height is {attach_height.dtype} but the model is {model.dtype}")
    return attach_height.cpu()


def _drape_batch(rest_uv, garment, body_verts, material, *, state, stats, **kwargs):
    """`drape` of a batch: rest_uv (B, V, 2), body_verts None, (Vb, 3) or (B, Vb, 3), state None or x/v
    of (Vs, 3) or (B, Vs, 3) -> (B, Vs, 3). One drape per element, on the same (CPU) model."""
    b = rest_uv.shape[0]
    if getattr(kwargs.get("options"), "return_trajectory", False):
        raise ValueError("return_trajectory is for one drape; drape batch elements one by one for frames")
    if body_verts is not None and body_verts.ndim == 3 and body_verts.shape[0] != b:
        raise ValueError(f"body_verts has batch {body_verts.shape[0]} but rest_uv has batch {b}")
    if isinstance(garment, GarmentMesh):  # one model for every element
        garment = ClothModelBuilder(material).add_garment(garment).finalize("cpu", rest_uv.dtype)
    element_stats = []
    out = []
    for k in range(b):
        body_k = body_verts[k] if body_verts is not None and body_verts.ndim == 3 else body_verts
        state_k = state
        if state is not None and state.x.ndim == 3:
            state_k = ClothState(state.x[k], state.v[k])
        element_stats.append({} if stats is not None else None)
        out.append(
            drape(rest_uv[k], garment, body_k, material, state=state_k, stats=element_stats[-1], **kwargs)
        )
    if stats is not None:
        stats["batch"] = element_stats
    return torch.stack(out)


def _drape_setup(rest_uv, garment, body_verts, material, body_faces, state, config, adjoint, options, stats):
    """Check `drape`'s inputs and build its `DrapeSetup` (on the CPU model), its material tensors and
    what the cloth collides with (the body, with ``config.floor`` the floor appended: (Vb [+ 4], 3))."""
    if adjoint not in ADJOINTS:
        raise ValueError(f"unknown adjoint {adjoint!r}; valid: {sorted(ADJOINTS)}")
    spec = ADJOINTS[adjoint]
    options = spec.options() if options is None else options
    if not isinstance(options, spec.options):
        raise ValueError(f"adjoint {adjoint!r} takes {spec.options.__name__}, got {type(options).__name__}")
    if isinstance(garment, GarmentMesh):
        model = ClothModelBuilder(material).add_garment(garment).finalize("cpu", rest_uv.dtype)
    elif isinstance(garment, ClothModel):
        model = garment
    else:
        raise ValueError(f"garment must be a ClothModel or a GarmentMesh, got {type(garment).__name__}")
    _check_inputs(model, rest_uv, body_verts, body_faces)
    material = model.material if material is None else material
    names, values = material_tensor_fields(material)
    values = tuple(v.to(dtype=model.dtype, device=model.device) for v in values)
    config = DrapeConfig() if config is None else config
    if state is None:
        x0 = start_positions(model, body_verts, config, material)
        v0 = torch.zeros_like(x0)
    else:
        if state.x.shape != (model.vert_count, 3):
            raise ValueError(f"state.x must be ({model.vert_count}, 3), got {tuple(state.x.shape)}")
        x0, v0 = state.x.detach().to(model.vert_init_pos), state.v.detach().to(model.vert_init_pos)
    setup = DrapeSetup(
        model=model,
        material=material_with(material, names, tuple(v.detach() for v in values)),
        material_names=names,
        body_faces=None if body_faces is None else body_faces.to(model.device),
        config=config,  # with the floor, replaced below by `collider`'s
        x0=x0,
        v0=v0,
        options=options,
        stats=stats,
        linearization=None if state is None else state.linearization,
    )
    setup.saved["adjoint"] = adjoint
    # the floor joins the body once, here: the adjoints' own drapes then see it as body triangles
    body_verts, setup.body_faces, setup.config = collider(body_verts, setup.body_faces, config)
    return setup, values, body_verts


def drape(
    rest_uv: torch.Tensor,
    garment: ClothModel | GarmentMesh,
    body_verts: torch.Tensor | None = None,
    material: ClothMaterial | None = None,
    *,
    body_faces: torch.Tensor | None = None,
    state: ClothState | None = None,
    config: DrapeConfig | None = None,
    adjoint: str = "equilibrium",
    options=None,
    stats: dict | None = None,
    attach_height: torch.Tensor | None = None,
):
    """Differentiable drape of a garment on a body.

    The simulation and its adjoint run on the CPU, where they are verified (float64 gradchecks); inputs on
    another device are copied there and the positions come back, with their gradients, on the input's
    device (on CUDA the equilibrium adjoint was measured wrong, the trajectory adjoint right but ~40x
    slower than the C++ CPU op at 4k vertices).

    Args:
        rest_uv: (V, 2) panel-vertex rest coordinates [m] (differentiable), or a batch (B, V, 2).
        garment: a `ClothModel` (seam-merged drape model on the CPU; reuse it across a fit) or a
            `GarmentMesh` (a merged model is built with ``material`` and ``rest_uv``'s dtype).
        body_verts: (Vb, 3) body vertices [m] (differentiable), or None for no body; with a batch of
            rest shapes, (Vb, 3) for one body under all or (B, Vb, 3).
        material: cloth material (default ``model.material``); its 0-dim tensor fields that require grad
            get gradients (see `adjoint.common.DIFFERENTIABLE_MATERIAL_FIELDS`).
        body_faces: (Fb, 3) int64 body triangles (outward normals), with ``body_verts``.
        state: start state (warm start, e.g. a previous drape's positions); default the placement at rest.
            With a batch, its x and v may be (B, Vs, 3). Equilibrium adjoint: a state at the end of an
            earlier drape that carries that drape's ``stats["linearization"]`` (its backward's) starts
            from the predicted equilibrium (`sim.adjoint.linearization`).
        config: drape options (step count, tolerances, XPBD settings). For gradchecks use a fixed step
            count (``min_steps == max_steps``) with the trajectory adjoint.
        adjoint: ``"trajectory"`` or ``"equilibrium"`` (keys of `ADJOINTS`).
        options: the adjoint's options (`TrajectoryOptions` / `EquilibriumOptions`; default: theirs).
        stats: a dict that the forward and backward fill with diagnostics (steps, Newton residual,
            solve residual, timings, the predicted move); with a batch, ``stats["batch"]`` holds one such
            dict per element. The equilibrium backward also leaves its ``linearization`` there (when its
            solve was a Cholesky factorisation), for the next drape's ``state``.
        attach_height: (A,) target heights y [m] of the model's attached vertices (the waist of a skirt or
            trousers; differentiable), default ``model.attach_height`` (their placement height). One
            vector for every element of a batch.

    Returns:
        x: (Vs, 3) draped positions [m] (a batch: (B, Vs, 3)); with ``TrajectoryOptions(return_trajectory=
        True)`` the tuple (x, frames (T+1, Vs, 3)), every frame differentiable.

    Raises:
        ValueError: bad shapes/dtypes, unknown adjoint name, options of the wrong type.
        SimulationError: the drape blew up, or the equilibrium adjoint's solve failed.
    """
    if isinstance(rest_uv, torch.Tensor) and rest_uv.ndim == 3:
        return _drape_batch(
            rest_uv,
            garment,
            body_verts,
            material,
            body_faces=body_faces,
            state=state,
            config=config,
            adjoint=adjoint,
            options=options,
            stats=stats,
            attach_height=attach_height,
        )
    setup, values, body_verts = _drape_setup(
        rest_uv, garment, body_verts, material, body_faces, state, config, adjoint, options, stats
    )
    device = rest_uv.device
    # to the simulator's device; `Tensor.cpu` is differentiable, so gradients flow back to ``device``
    rest_uv = rest_uv.cpu()
    body_verts = None if body_verts is None else body_verts.cpu()
    attach_height = _attach_height(setup.model, attach_height)
    x, frames = _Drape.apply(setup, rest_uv, body_verts, attach_height, *values)
    if getattr(setup.options, "return_trajectory", False):
        return x.to(device), frames.to(device)
    return x.to(device)
