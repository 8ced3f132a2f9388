"""The trajectory adjoint (DiffXPBD, paper §3.3 and appendix A, eqs. 9–12; appendix B, eqs. 13–19).

Forward: the XPBD drape of `XPBDSolver.step`, frame by frame under ``no_grad``, keeping a checkpoint of the
state (x, v) every ``checkpoint_every`` frames and the contact set (cloth vertex, body triangle,
barycentrics) of EVERY frame — the contact set is frozen from the forward pass.

Backward: reverse-mode through the discrete steps. Segment by segment, from the last to the first, the
frame states are recomputed from their checkpoint, then the frames are replayed one at a time (last
first) under ``torch.enable_grad()`` with `replay.ReplayPlan.frame` — the same step maths as the C++
forward in few, batched torch ops per colour (`replay_frame`, the reference kernels, for the Jacobi
scheme) — and the vector–Jacobian products come from `torch.autograd.grad` (torchdiffeq's adjoint
pattern). This IS the adjoint recursion of eqs. 9–12 evaluated by the chain rule: the adjoint state
(x̂_n, v̂_n) of a frame boundary is the VJP of the frame map with (x̂_{n+1}, v̂_{n+1}); ∂Δx/∂x̄ (rest
shape, eqs. 13–19) is the VJP through ``tri_rest_inv``, the rest areas (compliances, masses) and the
bending weights; ∂Δx/∂λ_b through the bending compliance; ∂Δx/∂x_body through the contact projection
(contact point and face normal recomputed from the body vertices, paper eq. 6) and friction. The
gradient is exact for the discrete trajectory up to the rounding difference between the C++ kernels of
the forward and the replay (~1e-14 m in float64; the backward records the largest deviation it saw).

Cost: about three forward frames of the replay per frame (its no-grad recompute, its recorded forward,
its backward): 1,280 colour passes per frame at the default 40 substeps on a 32-colour dress, Python-op
bound (measured in scripts/bench_grad.py). Memory: the checkpoints, one segment's states and one
frame's graph.
Limitations: the Gauss–Seidel order, contact set and friction regime (static/kinetic) are those of the
forward; the step count is fixed by the forward (speed criterion), so the derivative of "when the drape
stops" is ignored.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from torch_diffavatar.sim import reference
from torch_diffavatar.sim.adjoint.common import DrapeSetup, Gradients, material_with
from torch_diffavatar.sim.adjoint.replay import ReplayPlan
from torch_diffavatar.sim.constraints import RestData
from torch_diffavatar.sim.contacts import Contacts
from torch_diffavatar.sim.model import ClothModel
from torch_diffavatar.sim.solver import XPBDConfig, XPBDSolver, substep_inputs
from torch_diffavatar.sim.state import ClothState


@dataclass(frozen=True)
class TrajectoryOptions:
    """Options of the trajectory adjoint.

    Attributes:
        checkpoint_every: frames between stored states; the backward keeps one segment's graph at a time
            (memory ∝ frames / checkpoint_every + checkpoint_every).
        return_trajectory: also return every frame's positions (T+1, Vs, 3) (differentiable).
    """

    checkpoint_every: int = 8
    return_trajectory: bool = False

    def __post_init__(self):
        if self.checkpoint_every < 1:
            raise ValueError(f"checkpoint_every must be >= 1, got {self.checkpoint_every}")


_REST_LEAVES = ("tri_rest_inv", "tri_compliance", "edge_compliance", "vert_inv_mass", "attach_height")


def replay_frame(
    model: ClothModel,
    xpbd: XPBDConfig,
    x: torch.Tensor,
    v: torch.Tensor,
    rest: RestData,
    dt: float,
    *,
    contacts: Contacts | None = None,
    body_verts: torch.Tensor | None = None,
    body_faces: torch.Tensor | None = None,
    velocity_scale: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """One frame of `XPBDSolver.advance`, differentiable (autograd) in x, v, rest data and body vertices.

    The solver's frame (drape phase: gravity on, ``config.stitch_compliance``): its arguments from
    `solver.substep_inputs`, its maths `reference.xpbd_substeps` with the reference kernels, and the
    contact set given instead of detected.

    Args:
        x, v: (Vs, 3) state at the frame start [m], [m/s].
        rest: rest data (its tensors may require grad); dt: frame time [s].
        contacts: the frame's contact set (from the forward) or None.
        body_verts: (Vb, 3) [m]; body_faces: (Fb, 3) int64 (needed when ``contacts`` is given).
        velocity_scale: factor on v at the end of the frame.

    Returns:
        (x, v) at the frame end, (Vs, 3) each.
    """
    inputs = substep_inputs(
        model, rest, xpbd, dt, contacts=contacts, body_verts=body_verts, body_faces=body_faces
    )
    x, v = reference.xpbd_substeps(x, v, inputs)
    return x, (v * velocity_scale if velocity_scale != 1.0 else v)


@dataclass
class Rollout:
    """What the forward keeps for the backward.

    Attributes:
        steps: frames run; checkpoints: {frame: (x, v)} every ``checkpoint_every`` frames (and frame 0);
        contacts: per frame, its contact set or None; frames: (T+1, Vs, 3) all positions when requested;
        x, v: (Vs, 3) final state; max_speed [m/s]; converged: the speed criterion was met.
    """

    steps: int
    checkpoints: dict
    contacts: list
    frames: torch.Tensor | None
    x: torch.Tensor
    v: torch.Tensor
    max_speed: float
    converged: bool


def rollout(
    setup: DrapeSetup, rest: RestData, body_verts: torch.Tensor | None, options: TrajectoryOptions
) -> Rollout:
    """The XPBD drape of `drape_to_equilibrium` (same stopping rule), keeping checkpoints and contacts."""
    model, cfg = setup.model, setup.config
    solver = XPBDSolver(model, cfg.xpbd)
    state = ClothState(setup.x0, setup.v0)
    checkpoints = {0: (state.x, state.v)}
    contacts_per_frame = []
    frames = [state.x] if options.return_trajectory else None
    settled, steps, speed = 0, 0, math.inf
    with torch.no_grad():
        while steps < cfg.max_steps:
            result = solver.advance(
                state,
                rest,
                cfg.dt,
                body_verts=body_verts,
                body_faces=setup.body_faces,
                velocity_scale=cfg.drape_velocity_scale,
            )
            state = result.state
            # the replay projects against exactly the contacts this step detected and used
            contacts_per_frame.append(result.contacts)
            steps += 1
            if steps % options.checkpoint_every == 0:
                checkpoints[steps] = (state.x, state.v)
            if frames is not None:
                frames.append(state.x)
            speed = float(state.v.norm(dim=-1).max())
            settled = settled + 1 if speed < cfg.speed_tol else 0
            if steps >= cfg.min_steps and settled >= cfg.settle_steps:
                break
    return Rollout(
        steps=steps,
        checkpoints=checkpoints,
        contacts=contacts_per_frame,
        frames=torch.stack(frames) if frames is not None else None,
        x=state.x,
        v=state.v,
        max_speed=speed,
        converged=settled >= cfg.settle_steps,
    )


def trajectory_forward(setup: DrapeSetup, rest_uv, body_verts, attach_height, material_values):
    """XPBD rollout with checkpoints; returns the final positions (Vs, 3) (frames in ``setup.saved``)."""
    material = material_with(setup.material, setup.material_names, material_values)
    rest = setup.model.rest_data(rest_uv, material, attach_height)
    ro = rollout(setup, rest, body_verts, setup.options)
    setup.saved["rollout"] = ro
    setup.record(
        xpbd_steps=ro.steps,
        xpbd_converged=ro.converged,
        xpbd_max_speed=ro.max_speed,
        checkpoints=len(ro.checkpoints),
        max_contacts=max((c.count for c in ro.contacts if c is not None), default=0),
    )
    return ro.x


def trajectory_backward(
    setup: DrapeSetup,
    rest_uv: torch.Tensor,
    body_verts: torch.Tensor | None,
    attach_height: torch.Tensor,
    material_values: tuple[torch.Tensor, ...],
    grad_x: torch.Tensor,
    needs: tuple[bool, bool, bool, tuple[bool, ...]],
    grad_frames: torch.Tensor | None = None,
) -> Gradients:
    """Vector–Jacobian product of the drape with ``grad_x`` (Vs, 3) (and ``grad_frames`` (T+1, Vs, 3)).

    Segment by segment from the last: the frame states of a segment are recomputed from its checkpoint
    (no grad), then its frames are replayed one at a time, last first, each with its own small graph
    (`ReplayPlan.frame`, or `replay_frame` for the Jacobi scheme), and the adjoint state is pulled through
    it with `torch.autograd.grad`. The gradients of the rest data (``_REST_LEAVES``) and of the body are
    accumulated over the frames and mapped to ``rest_uv`` and the material once at the end.

    Args:
        setup: forward data; ``setup.saved["rollout"]`` is the `Rollout`.
        rest_uv: (V, 2) [m]; body_verts: (Vb, 3) [m] or None; attach_height: (A,) [m];
            material_values: differentiable material tensors (names in ``setup.material_names``).
        needs: whether rest_uv, body_verts, attach_height and each material tensor need a gradient.

    Records in ``setup.stats``: ``replay_max_deviation_m``, the largest difference between a replayed
    segment end and the forward's state there (rounding of the C++ forward vs the replay; a larger value
    means the replay does not reproduce the forward and the gradient is not that of the forward).
    """
    leaves = _ReplayLeaves.build(setup, rest_uv, body_verts, attach_height, material_values, needs)
    acc, deviation = _reverse_sweep(setup, leaves, grad_x, grad_frames)
    setup.record(replay_max_deviation_m=deviation)
    return leaves.gradients(acc)


@dataclass
class _ReplayLeaves:
    """The backward's leaves: the rest data as detached leaves (``_REST_LEAVES``) of the graph
    ``rest_uv``, attachment heights, material → rest data, and the body vertices.

    Attributes:
        needs: as `trajectory_backward`; uv, attach, materials: leaves of ``rest_uv``, the attachment
            heights and the material tensors;
        rest_graph: `RestData` computed from them (with grad); rest: the replay's `RestData`, its
        ``_REST_LEAVES`` detached leaves; body: (Vb, 3) leaf or None; inputs: the tensors whose gradients
        the sweep accumulates (the rest leaves when needed, then the body when needed).
    """

    needs: tuple
    uv: torch.Tensor
    attach: torch.Tensor
    materials: tuple[torch.Tensor, ...]
    rest_graph: RestData
    rest: RestData
    body: torch.Tensor | None
    inputs: list[torch.Tensor]

    @staticmethod
    def build(setup: DrapeSetup, rest_uv, body_verts, attach_height, material_values, needs) -> _ReplayLeaves:
        need_uv, need_body, need_attach, need_mat = needs
        need_rest = need_uv or need_attach or any(need_mat)
        with torch.enable_grad():
            uv_leaf = rest_uv.detach().requires_grad_(need_uv)
            attach_leaf = attach_height.detach().requires_grad_(need_attach)
            mat_leaves = tuple(m.detach().requires_grad_(n) for m, n in zip(material_values, need_mat))
            material = material_with(setup.material, setup.material_names, mat_leaves)
            rest_graph = setup.model.rest_data(uv_leaf, material, attach_leaf)
        leaves = {name: getattr(rest_graph, name).detach().requires_grad_(need_rest) for name in _REST_LEAVES}
        rest = dataclasses.replace(rest_graph, material=_floats(material), **leaves)
        body = body_verts.detach().requires_grad_(need_body) if body_verts is not None else None
        inputs = [leaves[n] for n in _REST_LEAVES] if need_rest else []
        if need_body and body is not None:
            inputs.append(body)
        return _ReplayLeaves(needs, uv_leaf, attach_leaf, mat_leaves, rest_graph, rest, body, inputs)

    def gradients(self, acc: list[torch.Tensor]) -> Gradients:
        """`Gradients` from the accumulated gradients ``acc`` of ``inputs``: the body's as they are, the
        rest data's pulled back to ``rest_uv``, the attachment heights and the material through
        ``rest_graph``."""
        need_uv, need_body, need_attach, need_mat = self.needs
        out = Gradients(body_verts=None, material=tuple(None for _ in need_mat))
        if need_body and self.body is not None:
            out.body_verts = acc[-1]
        if not (need_uv or need_attach or any(need_mat)):
            return out
        wrt = (
            ([self.uv] if need_uv else [])
            + ([self.attach] if need_attach else [])
            + [m for m, n in zip(self.materials, need_mat) if n]
        )
        pairs = [
            (getattr(self.rest_graph, name), acc[i])
            for i, name in enumerate(_REST_LEAVES)
            if getattr(self.rest_graph, name).requires_grad
        ]
        with torch.enable_grad():
            grads = torch.autograd.grad([p[0] for p in pairs], wrt, [p[1] for p in pairs], allow_unused=True)
        grads = [_zero_if_none(gr, t) for gr, t in zip(grads, wrt)]
        if need_uv:
            out.rest_uv = grads.pop(0)
        if need_attach:
            out.attach_height = grads.pop(0)
        out.material = tuple(grads.pop(0) if n else None for n in need_mat)
        return out


def _reverse_sweep(setup: DrapeSetup, leaves: _ReplayLeaves, grad_x, grad_frames):
    """The adjoint state pulled back through every frame, last first, segment by segment.

    Returns:
        (acc, deviation): the summed gradients of ``leaves.inputs``, and the largest difference [m]
        between a replayed segment end and the forward's state there.
    """
    ro: Rollout = setup.saved["rollout"]
    model, cfg = setup.model, setup.config
    plan = (
        ReplayPlan(model, cfg.xpbd, leaves.rest.vert_inv_mass) if cfg.xpbd.scheme == "gauss_seidel" else None
    )

    def frame(n, x, v):
        kw = dict(
            contacts=ro.contacts[n],
            body_verts=leaves.body,
            body_faces=setup.body_faces,
            velocity_scale=cfg.drape_velocity_scale,
        )
        if plan is not None:
            return plan.frame(x, v, leaves.rest, cfg.dt, **kw)
        return replay_frame(model, cfg.xpbd, x, v, leaves.rest, cfg.dt, **kw)

    acc = [torch.zeros_like(t) for t in leaves.inputs]
    a_x, a_v = grad_x, torch.zeros_like(grad_x)
    if grad_frames is not None:
        a_x = a_x + grad_frames[ro.steps]
    deviation = 0.0
    starts = sorted(k for k in ro.checkpoints if k < ro.steps)
    for k in reversed(starts):
        end = min(ro.steps, k + _segment(starts, k))
        states = [ro.checkpoints[k]]
        with torch.no_grad():
            for n in range(k, end - 1):
                states.append(frame(n, *states[-1]))
        for n in reversed(range(k, end)):
            with torch.enable_grad():
                x = states[n - k][0].detach().requires_grad_(True)
                v = states[n - k][1].detach().requires_grad_(True)
                xe, ve = frame(n, x, v)
                if n == end - 1:
                    target = ro.checkpoints[end][0] if end in ro.checkpoints else ro.x
                    deviation = max(deviation, float((xe.detach() - target.detach()).abs().max()))
                grads = torch.autograd.grad((xe, ve), [x, v, *leaves.inputs], (a_x, a_v), allow_unused=True)
            a_x, a_v = _zero_if_none(grads[0], x), _zero_if_none(grads[1], v)
            if grad_frames is not None:
                a_x = a_x + grad_frames[n]
            for a, gr in zip(acc, grads[2:]):
                if gr is not None:
                    a += gr
    return acc, deviation


def _segment(starts: list[int], k: int) -> int:
    later = [s for s in starts if s > k]
    return (later[0] - k) if later else 1 << 62


def _floats(material):
    """The material with every tensor field detached (the replay reads damping/friction/thickness)."""
    values = {
        f.name: getattr(material, f.name).detach()
        for f in dataclasses.fields(material)
        if isinstance(getattr(material, f.name), torch.Tensor)
    }
    return dataclasses.replace(material, **values) if values else material


def _zero_if_none(g, like):
    return torch.zeros_like(like) if g is None else g
