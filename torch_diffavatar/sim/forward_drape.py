"""The forward-only drapes (no gradients; `sim.differentiable.drape` is the differentiable one): drape to
quasi-equilibrium, warm-started or from the pattern's placement, and sew-then-drape.

`drape_to_equilibrium` steps a `ClothModel` until the largest vertex speed stays under a tolerance
(paper §3.2: the drapes end at quasi-equilibrium); pass ``state=`` (e.g. a previous `DrapeResult.state`)
to warm-start from an earlier equilibrium. `sew_and_drape` runs the two phases that work for GarmentCode
patterns whose panels start apart (notes/draping-lessons.md): phase 1 "sew" on the unmerged panel-vertex
mesh with zero-length stitches ramped from soft to stiff, no gravity and strong damping, until the largest
stitch gap is under ``sew_gap_tol``; phase 2 "drape" on the seam-merged mesh (sim vertex = mean of its
panel vertices) with gravity until quasi-equilibrium.

A posed body the placement cannot dress (arms held low leave no room between arm and torso) is dressed
from its A-pose instead: `sew_and_drape`'s ``body_path`` sews on the first body of a path and carries the
sewn cloth along it to the pose (`follow_body`); its ``fallback`` (a `PoseRoute`) does so only when sewing
on the pose itself fails.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import torch

from torch_diffavatar.errors import SimulationError
from torch_diffavatar.geometry import green_strain
from torch_diffavatar.pattern.garment_mesh import GarmentMesh
from torch_diffavatar.sim import collision, floor
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.model import ClothModel, ClothModelBuilder
from torch_diffavatar.sim.solver import XPBDConfig, XPBDSolver
from torch_diffavatar.sim.state import ClothState

# Strain limit of the sewing phase. When the finishing snap closes the last open stitches of a shoulder
# tip, where four panels meet at 6 mm pattern edges, the tip's small triangles pass the solver's default
# (3) for a frame or two and then relax: a long-sleeve shirt on a tall heavy body (make-scan --seed 5,
# weight .8, height .7, gender .8, 2 cm) reached E = 3.36 and sewed to E = 1.9, converged drape 1.57.
# Real blow-ups also trip the speed limit or go non-finite. The fit's drapes use the same limit
# (`fit.FIT_MAX_STRAIN`).
SEW_MAX_STRAIN = 100.0


@dataclass(frozen=True)
class DrapeConfig:
    """Options of a drape (and of the sewing phase of `sew_and_drape`).

    Attributes:
        xpbd: stepping options of the drape.
        sew_xpbd: stepping options of the sewing phase (no gravity: fewer substeps suffice). Its strain
            limit is `SEW_MAX_STRAIN`, not the solver's default 3 (see there).
        dt: frame time [s].
        max_steps: frames before giving up (the result then has ``converged=False``).
        min_steps: frames always run.
        speed_tol: quasi-equilibrium when the largest vertex speed is below this [m/s] ...
        settle_steps: ... for this many consecutive frames.
        settle_outliers: ... but for at most this fraction of the vertices [-] (0: every vertex). A few
            vertices in contact can rock back and forth from frame to frame for good (measured on a fitted
            dress: 13-17 of 1,992 vertices at the side of the chest, 0.2-0.9 mm each way, 2-12 cm/s) while
            the rest of the cloth is at rest; with 0 such a drape never settles.
        sew_max_steps: frames of the sewing phase at most.
        sew_ramp_steps: frames over which the stitch stiffness ramps (geometrically) from
            ``sew_stiffness_start`` to ``sew_stiffness_end`` [N/m].
        sew_gap_tol: sewing stops once the largest stitch gap is below this [m] (after the ramp).
        sew_finish_snap: after the ramp, stitch gaps under this [m] close without the bounded pull of
            ``sew_xpbd.stitch_max_speed`` (its ``stitch_snap`` is raised to this). The bound keeps wide-open
            seams from yanking vertices out of their triangles, but once the seams are nearly closed it
            let the cloth's own elastic pull win: the longsleeve's shoulder-tip junction (four panels) sat
            at a 1 cm gap indefinitely, and so did the trousers' waist corners.
        sew_stall_steps, sew_stall_snap_max: after the ramp, when the largest gap is still above the snap
            distance and has not shrunk by 1 % for ``sew_stall_steps`` frames, the snap distance grows to
            1.25 times that gap (at most ``sew_stall_snap_max`` [m]). A single seam vertex pair held open
            just beyond the snap distance by the elastic pull of a pleat (a longsleeve's elbow on a short
            arm stayed 17 mm open for 300 frames with a 15 mm snap; a T-shirt's underarm on a slim body,
            31 mm) then closes instead of failing. The bound keeps a seam laid across the body failing
            (and a `PoseRoute` fallback then tried): at 6 cm, long sleeves on arms lowered 0.3-0.4 rad from
            the A-pose were snapped shut crumpled at the shoulder.
        sew_gravity_scale: gravity factor while sewing.
        sew_velocity_scale: velocity factor per frame while sewing (strong damping).
        sew_friction_scale: friction factor while sewing (0: seams pulled over the body slide freely).
        sew_gap_max: `sew_and_drape` raises `SimulationError` when a stitch gap is still larger than
            this [m] after sewing (merging it would tear the mesh).
        drape_velocity_scale: velocity factor per frame while draping (mild artificial damping).
        pose_frames: frames over which `sew_and_drape` moves the body along its ``body_path`` [-].
        pose_velocity_scale: velocity factor per frame while the body moves along a path (`follow_body`):
            strong damping, as while sewing, for the move is a way to the pose, not a motion to simulate.
            At the drape's 0.97, cloth squeezed out from between a lowering arm and the torso flew on
            and the drape then tore around the arm (Green strain 13, a long sleeve, arms 0.4 rad low).
        floor: a floor at the body's soles (its lowest vertex) that the cloth rests on (`sim.floor`): the
            body mesh gets two floor triangles (`floor_joined`: a vertex by a foot gets the floor as a second
            contact), and cloth placed below the floor is first folded up onto it. Off by default (no floor:
            cloth longer than the legs hangs through where the floor is; `make-scan` and the fit turn it on).
    """

    xpbd: XPBDConfig = field(default_factory=XPBDConfig)
    sew_xpbd: XPBDConfig = field(
        default_factory=lambda: XPBDConfig(substeps=10, iterations=2, max_strain=SEW_MAX_STRAIN)
    )
    dt: float = 1.0 / 60.0
    max_steps: int = 1000
    min_steps: int = 10
    speed_tol: float = 0.02
    settle_steps: int = 5
    settle_outliers: float = 0.0
    sew_max_steps: int = 300
    sew_ramp_steps: int = 100
    sew_stiffness_start: float = 5.0
    sew_stiffness_end: float = 1.0e5
    sew_gap_tol: float = 1.0e-3
    sew_finish_snap: float = 0.015
    sew_stall_steps: int = 20
    sew_stall_snap_max: float = 0.04
    sew_gravity_scale: float = 0.0
    sew_velocity_scale: float = 0.7
    sew_friction_scale: float = 0.0
    sew_gap_max: float = 0.01
    drape_velocity_scale: float = 0.97
    pose_frames: int = 60
    pose_velocity_scale: float = 0.7
    floor: bool = False

    def __post_init__(self):
        if not 0 <= self.settle_outliers < 1:
            raise ValueError(f"DrapeConfig.settle_outliers must be in [0, 1), got {self.settle_outliers}")


@dataclass
class DrapeResult:
    """Outcome of a drape.

    Attributes:
        x: (Vs, 3) final positions [m]; v: (Vs, 3) final velocities [m/s].
        steps: frames run; max_speed: largest vertex speed at the end [m/s];
        converged: the speed criterion was met; seconds: wall time [s];
        diagnostics: ``max_strain`` (largest |Green strain| component), ``contact_count``,
            ``penetrating_count`` (vertices behind the plane of their closest body triangle within 5 cm),
            and for `sew_and_drape` also ``max_stitch_gap_m``, ``sew_steps``, ``sew_seconds``.
        model: the model the result belongs to (the merged one for `sew_and_drape`).
    """

    x: torch.Tensor
    v: torch.Tensor
    steps: int
    max_speed: float
    converged: bool
    seconds: float
    diagnostics: dict = field(default_factory=dict)
    model: ClothModel | None = None

    @property
    def state(self) -> ClothState:
        """The final state, e.g. to warm-start the next drape."""
        return ClothState(self.x, self.v)


@dataclass(frozen=True)
class PoseRoute:
    """A second way onto a posed body, for `sew_and_drape`'s ``fallback``: the garment placed on the
    body in another pose (the A-pose, which templates are made for), sewn there, and carried along the
    body's path to its own pose. Built by `torch_diffavatar.sim.placement.a_pose_route`.

    Attributes:
        vert_pos: (V, 3) [m] the garment's placement on ``body_path[0]``.
        body_path: (K, Vb, 3) [m] the body from that pose toward its own (`sew_and_drape`'s ``body_path``).
    """

    vert_pos: torch.Tensor
    body_path: torch.Tensor


def _check_body(body_verts, body_faces, model: ClothModel):
    if (body_verts is None) != (body_faces is None):
        raise ValueError("pass both body_verts and body_faces, or neither")
    if body_verts is None:
        return None, None
    if body_verts.ndim != 2 or body_verts.shape[1] != 3:
        raise ValueError(f"body_verts must be (Vb, 3), got {tuple(body_verts.shape)}")
    if body_faces.ndim != 2 or body_faces.shape[1] != 3:
        raise ValueError(f"body_faces must be (Fb, 3), got {tuple(body_faces.shape)}")
    return body_verts.to(device=model.device, dtype=model.dtype), body_faces.to(model.device, torch.int64)


def collider(body_verts, body_faces, config: DrapeConfig, height: float | None = None):
    """What the cloth collides with, and the options to step against it: the body (..., Vb, 3) [m] (one
    pose or several), and with ``config.floor`` the floor at ``height`` [m] (default: its soles) joined to it
    (`sim.floor.with_floor`, `floor_joined`). Returns (verts, faces, config)."""
    if body_verts is None or not config.floor:
        return body_verts, body_faces, config
    return *floor.with_floor(body_verts, body_faces, height), floor_joined(config)


def floor_joined(config: DrapeConfig) -> DrapeConfig:
    """``config`` for a body mesh that has the floor joined already (`sim.floor.with_floor`): ``floor`` off
    (not joined again), the steps told which faces are the floor (`XPBDConfig.floor_faces`)."""
    return replace(
        config,
        floor=False,
        xpbd=replace(config.xpbd, floor_faces=floor.FLOOR_FACES),
        sew_xpbd=replace(config.sew_xpbd, floor_faces=floor.FLOOR_FACES),
    )


def start_positions(model: ClothModel, body_verts, config: DrapeConfig, material=None) -> torch.Tensor:
    """(Vs, 3) [m] where a drape without a start state begins: the placement, and with ``config.floor`` what
    lies below the floor (at the soles of ``body_verts``) folded up onto it."""
    x = model.vert_init_pos
    if body_verts is None or not config.floor:
        return x
    thickness = float((model.material if material is None else material).thickness)
    return floor.fold_above_floor(x, floor.sole_height(body_verts), thickness)


def penetration_diagnostics(x, body_verts, body_faces, band: float = 0.05) -> dict:
    """``contact_count`` (vertices within ``band`` of the body) and ``penetrating_count`` (of those,
    vertices behind the plane of their closest body triangle)."""
    contacts = collision.detect_contacts(x, body_verts, body_faces, band)
    if contacts.count == 0:
        return {"contact_count": 0, "penetrating_count": 0}
    s = collision.signed_distance_along_normal(x, body_verts, body_faces, contacts)
    return {"contact_count": contacts.count, "penetrating_count": int((s < 0).sum())}


def drape_to_equilibrium(
    model: ClothModel,
    rest_uv: torch.Tensor,
    *,
    body_verts: torch.Tensor | None = None,
    body_faces: torch.Tensor | None = None,
    material: ClothMaterial | None = None,
    state: ClothState | None = None,
    config: DrapeConfig | None = None,
    attach_height: torch.Tensor | None = None,
) -> DrapeResult:
    """Step until quasi-equilibrium (vertex speeds < ``speed_tol`` for ``settle_steps`` frames, all but
    ``settle_outliers`` of them).

    Args:
        model: the cloth model.
        rest_uv: (V, 2) panel-vertex rest coordinates [m].
        body_verts: (Vb, 3) body vertices [m]; body_faces: (Fb, 3) int64 (both or neither).
        material: overrides ``model.material``.
        state: start state (warm start, e.g. ``previous_result.state``); default: the placement at rest.
        config: drape options.
        attach_height: (A,) target heights of the attached vertices [m] (default ``model.attach_height``).

    Returns:
        a `DrapeResult` (``converged`` False when ``max_steps`` ran out).

    Raises:
        SimulationError: the simulation blew up.
    """
    config = DrapeConfig() if config is None else config
    body_verts, body_faces = _check_body(body_verts, body_faces, model)
    placed = model.initial_state(start_positions(model, body_verts, config, material))
    body_verts, body_faces, config = collider(body_verts, body_faces, config)
    t0 = time.perf_counter()
    rest = model.rest_data(rest_uv, material, attach_height)
    solver = XPBDSolver(model, config.xpbd)
    state = placed if state is None else state
    if state.x.shape != (model.vert_count, 3):
        raise ValueError(f"state.x must be ({model.vert_count}, 3), got {tuple(state.x.shape)}")
    state = state.to(device=model.device, dtype=model.dtype)
    settled, steps, speed = 0, 0, math.inf
    allowed = int(config.settle_outliers * model.vert_count)
    while steps < config.max_steps:
        state = solver.step(
            state,
            rest,
            config.dt,
            body_verts=body_verts,
            body_faces=body_faces,
            velocity_scale=config.drape_velocity_scale,
        )
        steps += 1
        speeds = state.v.norm(dim=-1)
        speed = float(speeds.max())
        calm = speed < config.speed_tol or int((speeds >= config.speed_tol).sum()) <= allowed
        settled = settled + 1 if calm else 0
        if steps >= config.min_steps and settled >= config.settle_steps:
            break
    return _result(
        model, rest, state, steps, speed, settled >= config.settle_steps, t0, body_verts, body_faces
    )


def follow_body(
    model: ClothModel,
    rest_uv: torch.Tensor,
    state: ClothState,
    bodies: torch.Tensor,
    body_faces: torch.Tensor,
    *,
    frames: int,
    material: ClothMaterial | None = None,
    config: DrapeConfig | None = None,
) -> DrapeResult:
    """Step the cloth while the body moves through keyframes, linearly between them (gravity on).

    Brings a garment sewn on one pose of a body to another: the body starts at ``bodies[0]`` and ends at
    ``bodies[-1]`` after ``frames`` frames, each frame's substeps seeing the body interpolated within the
    frame (`XPBDSolver.step`'s ``body_verts_end``), so the cloth is carried, not tunnelled through.

    Args:
        model: the cloth model; rest_uv: (V, 2) rest coordinates [m]; state: the start state.
        bodies: (K, Vb, 3) body keyframes [m], K >= 2; body_faces: (Fb, 3) int64.
        frames: frames of the move (>= 1), spread evenly over the K − 1 segments.
        material: overrides ``model.material``; config: ``xpbd``, ``dt`` and ``pose_velocity_scale``.

    Returns:
        a `DrapeResult` (``converged`` is whether the cloth was below ``speed_tol`` at the end).

    Raises:
        SimulationError: the simulation blew up.
    """
    config = DrapeConfig() if config is None else config
    if bodies.ndim != 3 or bodies.shape[0] < 2 or bodies.shape[2] != 3:
        raise ValueError(f"bodies must be (K >= 2, Vb, 3), got {tuple(bodies.shape)}")
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    bodies = bodies.to(device=model.device, dtype=model.dtype)
    _, body_faces = _check_body(bodies[0], body_faces, model)
    # the floor under the first pose's soles, in every keyframe
    bodies, body_faces, config = collider(bodies, body_faces, config, floor.sole_height(bodies[0]))
    t0 = time.perf_counter()
    rest = model.rest_data(rest_uv, material)
    solver = XPBDSolver(model, config.xpbd)
    state = state.to(device=model.device, dtype=model.dtype)
    segments = bodies.shape[0] - 1

    def body_at(frame: int) -> torch.Tensor:
        u = frame * segments / frames
        k = min(int(u), segments - 1)
        return torch.lerp(bodies[k], bodies[k + 1], u - k)

    start = body_at(0)
    for f in range(frames):
        end = body_at(f + 1)
        state = solver.step(
            state,
            rest,
            config.dt,
            body_verts=start,
            body_faces=body_faces,
            body_verts_end=end,
            velocity_scale=config.pose_velocity_scale,
        )
        start = end
    speed = float(state.v.norm(dim=-1).max())
    return _result(model, rest, state, frames, speed, speed < config.speed_tol, t0, bodies[-1], body_faces)


def _result(model, rest, state, steps, speed, converged, t0, body_verts, body_faces, **extra) -> DrapeResult:
    """The `DrapeResult` of a run that started at ``t0`` (perf_counter): ``max_strain``, the body's
    penetration diagnostics when there is a body, and ``extra`` diagnostics."""
    diagnostics = {
        "max_strain": float(green_strain(state.x, model.tri_vertices, rest.tri_rest_inv).abs().max()),
        **extra,
    }
    if body_verts is not None:
        diagnostics.update(penetration_diagnostics(state.x, body_verts, body_faces))
    return DrapeResult(
        x=state.x,
        v=state.v,
        steps=steps,
        max_speed=speed,
        converged=converged,
        seconds=time.perf_counter() - t0,
        diagnostics=diagnostics,
        model=model,
    )


def max_stitch_gap(model: ClothModel, x: torch.Tensor) -> float:
    """Largest distance [m] between stitched vertices of ``model`` (0 without open stitches)."""
    if model.stitch_vertices.shape[0] == 0:
        return 0.0
    pairs = model.stitch_vertices
    return float((x[pairs[:, 0]] - x[pairs[:, 1]]).norm(dim=-1).max())


def sew(
    model: ClothModel,
    rest_uv: torch.Tensor,
    *,
    body_verts: torch.Tensor | None = None,
    body_faces: torch.Tensor | None = None,
    material: ClothMaterial | None = None,
    config: DrapeConfig | None = None,
) -> DrapeResult:
    """Phase 1: close the open stitches of an unmerged model (``merge_seams=False``).

    The stitch stiffness ramps geometrically from ``sew_stiffness_start`` to ``sew_stiffness_end`` over
    ``sew_ramp_steps`` frames; sewing stops when the ramp is done and the largest gap is under
    ``sew_gap_tol`` (``converged``), or after ``sew_max_steps``. After the ramp, gaps under
    ``sew_finish_snap`` close without the bounded pull, and that snap distance grows when the largest gap
    stalls above it (``sew_stall_steps``, ``sew_stall_snap_max``). ``diagnostics["max_stitch_gap_m"]``
    reports the final gap and ``diagnostics["sew_snap_m"]`` the final snap distance [m].
    """
    config = DrapeConfig() if config is None else config
    body_verts, body_faces = _check_body(body_verts, body_faces, model)
    state = model.initial_state(start_positions(model, body_verts, config, material))
    body_verts, body_faces, config = collider(body_verts, body_faces, config)
    t0 = time.perf_counter()
    rest = model.rest_data(rest_uv, material)
    solver = XPBDSolver(model, config.sew_xpbd)
    snap = max(config.sew_xpbd.stitch_snap, config.sew_finish_snap)
    finisher = XPBDSolver(model, replace(config.sew_xpbd, stitch_snap=snap))
    gap = max_stitch_gap(model, state.x)
    steps = 0
    k0, k1 = config.sew_stiffness_start, config.sew_stiffness_end
    ref, stalled = math.inf, 0  # gap when progress was last made, frames since (1 % below ref)
    while steps < config.sew_max_steps:
        frac = min(1.0, steps / max(1, config.sew_ramp_steps))
        stiffness = k0 * (k1 / k0) ** frac
        if frac >= 1.0:
            if gap < 0.99 * ref:
                ref, stalled = gap, 0
            else:
                stalled += 1
            if stalled >= config.sew_stall_steps and snap < gap and snap < config.sew_stall_snap_max:
                snap = min(1.25 * gap, config.sew_stall_snap_max)
                finisher = XPBDSolver(model, replace(config.sew_xpbd, stitch_snap=snap))
                ref, stalled = gap, 0
        state = (finisher if frac >= 1.0 else solver).step(
            state,
            rest,
            config.dt,
            body_verts=body_verts,
            body_faces=body_faces,
            gravity_scale=config.sew_gravity_scale,
            stitch_compliance=1.0 / stiffness,
            velocity_scale=config.sew_velocity_scale,
            friction_scale=config.sew_friction_scale,
        )
        steps += 1
        gap = max_stitch_gap(model, state.x)
        if frac >= 1.0 and gap < config.sew_gap_tol:
            break
    speed = float(state.v.norm(dim=-1).max())
    converged = gap < config.sew_gap_tol
    return _result(
        model, rest, state, steps, speed, converged, t0, None, None, max_stitch_gap_m=gap, sew_snap_m=snap
    )


def sew_and_drape(
    garment: GarmentMesh,
    *,
    rest_uv: torch.Tensor | None = None,
    body_verts: torch.Tensor | None = None,
    body_faces: torch.Tensor | None = None,
    body_path: torch.Tensor | None = None,
    fallback: PoseRoute | None = None,
    material: ClothMaterial | None = None,
    config: DrapeConfig | None = None,
    device=None,
    dtype: torch.dtype = torch.float32,
) -> DrapeResult:
    """Sew the garment's open seams (phase 1), then drape the seam-merged garment (phase 2).

    Args:
        garment: meshed and placed pattern (panels apart, ``stitch_pairs`` open).
        rest_uv: (V, 2) rest coordinates [m] (default ``garment.vert_uv``).
        body_verts, body_faces: the body (both or neither).
        body_path: (K, Vb, 3) [m], K >= 1: the body in other poses, from the one the garment was placed
            on (``body_path[0]``) toward ``body_verts``. The garment is then sewn on ``body_path[0]``, the
            body moves through the rest of the path to ``body_verts`` over ``config.pose_frames`` frames
            with the sewn cloth on it (`follow_body`), and the drape settles on ``body_verts``. For poses
            the placement cannot dress directly, such as arms lowered against the torso: sew in the
            A-pose, then pose the body (`BodyModel.pose_path`).
        fallback: when sewing or draping on ``body_verts`` (along ``body_path``, if given) fails, dress
            the body this way instead (`PoseRoute`); ``diagnostics["fallback_after"]`` then holds the
            first attempt's error.
        material: cloth material (default `medium_cotton`).
        config: drape options.

    Returns:
        the phase-2 `DrapeResult` on the merged model (``result.model``), whose diagnostics also hold
        ``max_stitch_gap_m``, ``sew_steps``, ``sew_seconds``, ``sew_converged`` and ``sew_snap_m`` from
        phase 1, ``floor`` (``config.floor``) (and ``pose_frames``, with a ``body_path``).

    Raises:
        SimulationError: a phase blew up or the seams did not close (the message says which; with a
            ``fallback``, the message holds both attempts' errors).
    """
    if fallback is not None and (body_verts is None or fallback.vert_pos.shape != garment.vert_pos.shape):
        raise ValueError("a fallback needs body_verts and a vert_pos of the garment's (V, 3)")
    kwargs = dict(rest_uv=rest_uv, body_verts=body_verts, body_faces=body_faces, material=material)
    kwargs.update(config=config, device=device, dtype=dtype)
    t0 = time.perf_counter()
    try:
        return _sew_and_drape(garment, body_path=body_path, **kwargs)
    except SimulationError as exc:
        if fallback is None:
            raise
        first = str(exc)
    try:
        result = _sew_and_drape(
            replace(garment, vert_pos=fallback.vert_pos), body_path=fallback.body_path, **kwargs
        )
    except SimulationError as exc:
        raise SimulationError(f"{first}; and from the A-pose along the body's path: {exc}") from exc
    result.diagnostics["fallback_after"] = first
    result.seconds = time.perf_counter() - t0
    return result


def _sew_and_drape(
    garment: GarmentMesh,
    *,
    rest_uv: torch.Tensor | None,
    body_verts: torch.Tensor | None,
    body_faces: torch.Tensor | None,
    body_path: torch.Tensor | None,
    material: ClothMaterial | None,
    config: DrapeConfig | None,
    device,
    dtype: torch.dtype,
) -> DrapeResult:
    """`sew_and_drape` without its fallback."""
    config = DrapeConfig() if config is None else config
    rest_uv = garment.vert_uv if rest_uv is None else rest_uv
    sew_body = body_verts
    if body_path is not None:
        if body_verts is None or body_path.ndim != 3 or body_path.shape[1:] != body_verts.shape:
            raise ValueError("body_path must be (K, Vb, 3) of the body_verts' Vb, with body_verts given")
        sew_body = body_path[0]
    sew_model = ClothModelBuilder(material).add_garment(garment, merge_seams=False).finalize(device, dtype)
    drape_model = ClothModelBuilder(material).add_garment(garment, merge_seams=True).finalize(device, dtype)
    rest_uv = rest_uv.to(device=sew_model.device, dtype=dtype)
    try:
        sewn = sew(sew_model, rest_uv, body_verts=sew_body, body_faces=body_faces, config=config)
    except SimulationError as exc:
        raise SimulationError(f"sewing phase: {exc}") from exc
    gap = sewn.diagnostics["max_stitch_gap_m"]
    if gap > config.sew_gap_max:
        pairs = sew_model.stitch_vertices
        worst = int((sewn.x[pairs[:, 0]] - sewn.x[pairs[:, 1]]).norm(dim=-1).argmax())
        a, b = (int(v) for v in pairs[worst])
        names = garment.panel_names
        panels = (names[int(garment.vert_panel[a])], names[int(garment.vert_panel[b])])
        raise SimulationError(
            f"sewing phase: seams did not close after {sewn.steps} frames (max stitch gap {gap * 1e3:.1f} mm "
            f"> sew_gap_max {config.sew_gap_max * 1e3:.1f} mm, between panels {panels[0]!r} and "
            f"{panels[1]!r} at {[round(float(c), 3) for c in sewn.x[a]]}); the placement probably lays "
            "that seam across the body"
        )
    state = drape_model.initial_state(drape_model.sim_positions(sewn.x))
    moved = None
    if body_path is not None:
        bodies = torch.cat([body_path, body_verts[None].to(body_path)])
        try:
            moved = follow_body(
                drape_model, rest_uv, state, bodies, body_faces, frames=config.pose_frames, config=config
            )
        except SimulationError as exc:
            raise SimulationError(f"posing phase: {exc}") from exc
        state = moved.state
    try:
        result = drape_to_equilibrium(
            drape_model,
            rest_uv,
            body_verts=body_verts,
            body_faces=body_faces,
            state=state,
            config=config,
        )
    except SimulationError as exc:
        raise SimulationError(f"drape phase: {exc}") from exc
    result.diagnostics.update(
        max_stitch_gap_m=sewn.diagnostics["max_stitch_gap_m"],
        sew_steps=sewn.steps,
        sew_seconds=sewn.seconds,
        sew_converged=sewn.converged,
        sew_snap_m=sewn.diagnostics["sew_snap_m"],
        floor=config.floor,
    )
    result.seconds += sewn.seconds
    if moved is not None:
        result.diagnostics["pose_frames"] = moved.steps
        result.seconds += moved.seconds
    return result
