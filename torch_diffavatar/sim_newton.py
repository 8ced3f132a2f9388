"""A second cloth physics: settle a sewn garment with NVIDIA Newton's VBD solver (Newton 1.8.0, Warp 1.19.0).

`diffavatar make-scan --simulator newton` uses it so that a synthetic scan's truth is NOT made by the
simulator a fit inverts (which would hide model error). Newton and Warp are optional (the ``newton``
extra: ``pip install -e ".[newton]"``) and are imported only inside the functions that need them.

The Newton model is built on our sewn, seam-merged garment (`ClothModel` of `sew_and_drape`'s result):
particles at our drape, triangles = our triangles, and the REST shape from the pattern, per triangle:
a merged seam vertex has different (u, v) in its two panels, so each triangle's rest matrix and area
(Newton's ``tri_poses``, ``tri_areas``) are set from its own panel's 2D coordinates, the bending rest
angles are 0 (a flat pattern), and the particle masses are our lumped ``density × rest area / 3``.

Newton's energies (read in ``newton/_src/solvers/vbd/particle_vbd_kernels.py``) and ours (the conversion
lives in `sim.newton_units`, pure numpy, re-exported here; the asset export writes it as
``material_newton.json``, docs/ASSETS.md):

* Membrane. Newton's VBD triangle is the *stable Neo-Hookean* membrane of Smith et al. 2018 (not StVK):
  per rest area ``ψ = μ/2 (I_c − 2) + λ'/2 (J − α)²`` with ``I_c = tr FᵀF``, ``J = |f0 × f1|``,
  ``λ' = λ + μ``, ``α = 1 + μ/λ'``, where ``μ = tri_ke`` and ``λ = tri_ka`` [N/m] are 2D Lamé moduli.
  Expanded to second order in the Green strain E = ½(FᵀF − I) it is
  ``ψ ≈ (λ+2μ)/2 (E00² + E11²) + λ E00 E11 + 2μ E01²``.
  Ours (`ClothMaterial`, `sim/constraints.py`): ``ψ = ½ k_uu E00² + ½ k_vv E11² + ν√(k_uu k_vv) E00 E11
  + 2 k_uv E01²``. So Newton → ours is exact at small strain: ``k_uu = k_vv = λ + 2μ``, ``k_uv = μ``,
  ``ν = λ/(λ + 2μ)`` (`membrane_from_newton`). Newton's membrane is isotropic, ours orthotropic: ours →
  Newton (`membrane_to_newton`) keeps the shear ``μ = k_uv`` and the geometric mean of the axial
  stiffnesses ``λ + 2μ = √(k_uu k_vv)`` (λ clamped at 0) and drops ν; it inverts `membrane_from_newton`
  exactly (the round trip Newton → ours → Newton is the identity, and ours → Newton → ours is for an
  isotropic material of ours with ν = (k − 2k_uv)/k). ``keep="stretch"`` keeps our coupling and so our
  stretch instead (λ = ν√(k_uu k_vv), μ = (√(k_uu k_vv) − λ)/2): what the asset export writes, since
  Newton's drape of an orthotropic material of ours came out closer that way (docs/ASSETS.md); both agree
  on the isotropic materials `draw_material` makes. Large strains differ (Neo-Hookean vs StVK): that,
  the solver and the contact model are the "other physics".
* Bending. Newton's dihedral energy per interior edge is ``½ edge_ke · |ē| (θ − θ̄)²`` (``|ē|`` =
  ``edge_rest_length``, edge_ke in N); ours is ``½ k_b · w (θ − θ̄)²`` with ``w = 3|ē|²/(Ā1 + Ā2)``
  (`constraints.edge_bend_weight`). Newton takes one stiffness per edge, so with Newton's rest length set
  to ours the energies are equal for ``edge_ke = k_b w / |ē|`` (`bend_to_newton`); back,
  ``k_b = edge_ke |ē| / w`` (`bend_from_newton`, the mean over the edges).
* Mass: ``density`` [kg/m²] = our ``areal_density``. Contact: Newton's penalty contact (stiffness
  ``soft_contact_ke``, Coulomb friction ``soft_contact_mu`` = our ``friction``) at ``particle_radius`` =
  our ``thickness``, with the body and with a floor at the body's lowest point (as ours,
  `DrapeConfig.floor`). Gravity −9.81 m/s² along −Y.

Waist-held garments (our ``attach_vertices``: skirts, trousers) slid off the body on contact and friction
alone, and zero-length springs (or Newton's particle-body attachments) to fixed points did not hold them
in Newton 1.8's VBD either, so their waist vertices are pinned (kinematic) where our drape, lowered onto
the hips (`lower_onto_body`), has them: the waistband as long as its pattern makes it. Pinned on the body
surface instead (the closest point of each), the band took the body's girth at that height: the true
drapes' waistbands were 4.5-14.2 % shorter than their patterns', and the fits shrank the pattern's waist
to match, by up to 20 cm (docs/BENCHMARKS.md, "Newton's waistbands as long as their patterns").

Limitations: no self-collision (as ours); stiff cloth does not settle at the affordable substeps (see
`STRETCH_FACTOR_RANGE`); Warp's CPU kernels run on one core (a 2 cm dress settles in 5-14 minutes here at
`NewtonDrapeConfig`'s 120 iterations per step), and the first use compiles Warp's kernels (~30 s, cached
in ~/.cache/warp).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from torch_diffavatar.errors import InputError, SimulationError
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.newton_units import (  # noqa: F401  (the conversion, re-exported: pure numpy)
    NewtonCloth,
    NewtonMaterial,
    bend_from_newton,
    bend_to_newton,
    edge_geometry,
    material_from_newton,
    material_to_newton,
    membrane_conversion_loss,
    membrane_from_newton,
    membrane_to_newton,
    newton_cloth,
    newton_cloth_from_arrays,
    vertex_coloring,
)

NEWTON_INSTALL = 'pip install -e ".[newton]"'
# [m/s²] Newton's default gravity along -up (the model is built Y up)
GRAVITY = 9.81


def import_newton():
    """(warp, newton), Warp's banner silenced; `InputError` naming the install command when missing."""
    try:
        import warp as wp

        wp.config.log_level = wp.LOG_WARNING  # before newton initialises Warp
        import newton
    except ImportError as exc:
        raise InputError(
            f"--simulator newton needs NVIDIA Newton and Warp ({exc.name or exc} is missing): "
            f"install them with {NEWTON_INSTALL}"
        ) from exc
    return wp, newton


# [-] the random true material of a Newton scan, relative to our defaults (`draw_material`). The stretch is
# 2-10x SOFTER only: at 8.45x stiffer (μ = 8.4e3, λ = 1.3e5 N/m) VBD at 10 substeps x 5 iterations per
# frame did not settle a 2 cm dress in 400 frames (max speed 0.13 m/s, 57 vertices inside the body, edge
# strains as large as at 0.25x: the stiffness is not resolved), nor a 2 cm skirt at 3x (max 6.7 cm/s): the
# stiff side needs more substeps than a CPU scan affords. At 0.12x and 0.25x the dress settled (111-179
# frames), nothing inside the body.
STRETCH_FACTOR_RANGE = (2.0, 10.0)
BEND_FACTOR_RANGE = (0.3, 3.0)
FRICTION_RANGE = (0.2, 0.6)


def draw_material(rng: np.random.Generator, bend_stiffness: float, base: ClothMaterial | None = None):
    """A random true material in our units, with an exact Newton counterpart (isotropic membrane).

    The stretch (Newton's μ and λ + 2μ, i.e. our k_uv and √(k_uu k_vv)) is ``s`` × ``base``'s, softer:
    ``1/s`` log-uniform in `STRETCH_FACTOR_RANGE` (see there why not stiffer);
    the bending is ``bend_stiffness`` [N·m] × a log-uniform factor in `BEND_FACTOR_RANGE`; the friction
    uniform in `FRICTION_RANGE`. Density and thickness stay ``base``'s (default `ClothMaterial()`).

    Returns:
        (the `ClothMaterial`, ``{"stretch_factor": s, "bend_factor": b}``).
    """
    base = ClothMaterial() if base is None else base
    lo, hi = np.log(STRETCH_FACTOR_RANGE)
    s = float(np.exp(-rng.uniform(lo, hi)))
    b = float(np.exp(rng.uniform(*np.log(BEND_FACTOR_RANGE))))
    friction = float(rng.uniform(*FRICTION_RANGE))
    mu, lam = membrane_to_newton(
        s * float(base.k_uu), s * float(base.k_vv), s * float(base.k_uv)
    )  # on the isotropic subset, where both directions are exact
    material = ClothMaterial(
        areal_density=float(base.areal_density),
        **membrane_from_newton(mu, lam),
        bend_stiffness=b * bend_stiffness,
        friction=friction,
        thickness=float(base.thickness),
    )
    return material, {"stretch_factor": s, "bend_factor": b}


# ---------------------------------------------------------------------------------------------------
# the Newton drape
# ---------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class NewtonDrapeConfig:
    """How `newton_drape` steps Newton's VBD solver.

    Attributes:
        fps: frames per second [1/s]; substeps: VBD steps per frame.
        iterations: VBD iterations per step. Too few leave the drape resting where it is not at rest: each
            step's gravity pull is not undone by the iterations (the cloth's long, slow modes converge last),
            and the garment hangs stretched. The true dress of seed 0 (2 cm, the suite's scan) from our
            drape at 10 / 40 / 80 / 120 iterations, against 240 (continued from 120): its lowest point 50 /
            16 / 7.1 / 3.6 mm lower, 40 / 12 / 6.4 / 3.4 mm apart on average, its edges strained 1.79 /
            0.54 / 0.31 / 0.23 % (mean |·|; 240: 0.15 %, ours 0.21 %); at 240 it hangs 1-3 mm higher than
            ours. 120 rests in 30-62 frames (5-14 min on one core here; 10 took 30-174, 1-8 min). The
            truths made at 10 before (docs/BENCHMARKS.md, "Newton's drapes at rest in their iterations")
            hung 2-5 cm longer than their patterns do, and the fits lengthened the patterns to match.
        max_frames: frames at most; min_frames: frames always run.
        speed_tol: at rest when the MEAN vertex speed is below this [m/s] ...
        max_speed_tol: ... and the largest below this [m/s] ...
        settle_frames: ... for this many consecutive frames.
        velocity_scale: velocity factor per frame (artificial damping: it shortens the settle, not the
            resting shape). At 0.95 a few vertices kept jittering at 8-11 cm/s for 400 frames (2 cm skirt and
            T-shirt, 5 cm trousers: VBD's penalty contact); at 0.9 the trousers came to rest in 94 frames.
            At 5 iterations and 0.9, a 2 cm T-shirt 9x softer than ours (seed 103) still moved at 0.35 m/s
            after 400 frames, its free hem and sleeves 2-5 cm off the body, and its edges strained 2.1 % on
            average: twice the 1.0 % at 10 iterations (see ``iterations``). At 10 and 0.8 it came to rest
            (mean 4 mm/s, max 3 cm/s) by frame 75-150.
        contact_ke: body contact stiffness [N/m]; contact_kd: its damping [s].
        contact_gap: contact detection band beyond the particle radius [m] (detection once per frame).
        blow_up_speed: `SimulationError` when a vertex gets faster than this [m/s].
        seam_ke: stiffness of the zero-length seam springs of an unmerged cloth (`NewtonCloth.spring_pairs`)
            [N/m].
    """

    fps: float = 60.0
    substeps: int = 10
    iterations: int = 120
    max_frames: int = 400
    min_frames: int = 30
    speed_tol: float = 0.005
    max_speed_tol: float = 0.05
    settle_frames: int = 5
    velocity_scale: float = 0.8
    contact_ke: float = 1.0e4
    contact_kd: float = 1.0e-2
    contact_gap: float = 0.02
    blow_up_speed: float = 20.0
    seam_ke: float = 1.0e4

    def __post_init__(self):
        """ValueError naming the first setting out of its range (a drape with it would hang, never end, or
        blow up minutes in)."""
        counts = {"substeps": 1, "iterations": 1, "max_frames": 1, "min_frames": 0, "settle_frames": 1}
        for name, least in counts.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < least:
                raise ValueError(f"NewtonDrapeConfig.{name} must be an integer >= {least}, got {value!r}")
        if self.min_frames > self.max_frames:
            raise ValueError(f"NewtonDrapeConfig.min_frames {self.min_frames} > max_frames {self.max_frames}")
        positive = ("fps", "speed_tol", "max_speed_tol", "blow_up_speed")
        for name in positive + ("contact_ke", "contact_kd", "contact_gap", "seam_ke", "velocity_scale"):
            value = getattr(self, name)
            number = isinstance(value, int | float) and not isinstance(value, bool)
            if not number or not math.isfinite(value) or value < 0 or (name in positive and value == 0):
                least = "> 0" if name in positive else ">= 0"
                raise ValueError(f"NewtonDrapeConfig.{name} must be a finite number {least}, got {value!r}")
        if not 0.0 < self.velocity_scale <= 1.0:
            raise ValueError(f"NewtonDrapeConfig.velocity_scale must be in (0, 1], got {self.velocity_scale}")


@dataclass
class NewtonDrapeResult:
    """Outcome of `newton_drape`.

    Attributes:
        x: (Vs, 3) float64 final positions [m]; frames: frames run; seconds: wall time of the settle [s];
        mean_speed, max_speed: vertex speeds at the end [m/s]; converged: the speed criterion was met;
        penetrating_count: cloth vertices behind the plane of their closest body triangle (5 cm band).
    """

    x: torch.Tensor
    frames: int
    seconds: float
    mean_speed: float
    max_speed: float
    converged: bool
    penetrating_count: int

    def diagnostics(self) -> dict:
        """JSON-friendly figures (without ``x``)."""
        return {
            "frames": self.frames,
            "seconds": round(self.seconds, 2),
            "mean_speed_m_per_s": self.mean_speed,
            "max_speed_m_per_s": self.max_speed,
            "converged": self.converged,
            "penetrating_count": self.penetrating_count,
        }


def pattern_edge_strain(x: torch.Tensor, model, rest_uv: torch.Tensor) -> np.ndarray:
    """(3F,) strain ``|e| / |ē| − 1`` [-] of every triangle edge at positions ``x`` (Vs, 3) [m] against
    its rest length in its own panel (``rest_uv`` (V, 2) [m]; ``model``: the `ClothModel`)."""
    uv = rest_uv.double().cpu()[model.tri_panel_vertices.cpu()]  # (F, 3, 2)
    return tri_edge_strain(x, model.tri_vertices.cpu(), uv)


def tri_edge_strain(x: torch.Tensor, tri_vertices, tri_rest_uv) -> np.ndarray:
    """(3F,) strain ``|e| / |ē| − 1`` [-] of every edge of the triangles ``tri_vertices`` (F, 3) of ``x``
    (Vs, 3) [m] against the rest corners ``tri_rest_uv`` (F, 3, 2) [m] (edges 0-1, then 1-2, then 2-0)."""
    tri, ud = torch.as_tensor(tri_vertices), torch.as_tensor(tri_rest_uv).double()
    xd = x.double().cpu()
    out = []
    for a, b in ((0, 1), (1, 2), (2, 0)):
        length = (xd[tri[:, a]] - xd[tri[:, b]]).norm(dim=1)
        out.append(length / (ud[:, a] - ud[:, b]).norm(dim=1) - 1.0)
    return torch.cat(out).numpy()


def strain_summary(strain: np.ndarray) -> dict:
    """Mean, mean absolute, 99th percentile and max of (K,) edge strains [-]."""
    return {
        "mean": float(strain.mean()),
        "mean_abs": float(np.abs(strain).mean()),
        "p99": float(np.percentile(strain, 99)),
        "max": float(strain.max()),
    }


def lower_onto_body(
    x: torch.Tensor, drop: float, body_verts: torch.Tensor, body_faces: torch.Tensor, thickness
):
    """(Vs, 3) float64: ``x`` (Vs, 3) [m] moved down by ``drop`` [m] and kept above the floor (the body's
    lowest point plus ``thickness``: cloth below it is put on it), then every vertex that lands within
    ``thickness`` [m] of the body (or behind it) pushed out along its closest body triangle's normal. A
    waist-held garment then starts lower on the hips (and its waist is pinned there). Our drape without a
    floor (`DrapeConfig.floor` off) lets trouser legs hang through it: Newton's floor then met cloth 8 cm
    under it and blew up at the first frame (`make-scan pants --seed 305 --simulator newton --hem-up 0.1
    --hem-widen 0.15`)."""
    from torch_diffavatar.sim import collision

    xd = x.double().clone()
    floor = float(body_verts[:, 1].min()) + float(thickness)
    xd[:, 1] = (xd[:, 1] - drop).clamp(min=floor)
    bv, bf = body_verts.double(), body_faces
    for _ in range(3):  # a push along one face normal can land near another face: repeat
        contacts = collision.detect_contacts(xd, bv, bf, 0.05)
        if contacts.count == 0:
            break
        xd, _, _ = collision.project_contacts(
            xd, torch.ones(len(xd), dtype=xd.dtype), bv, bf, contacts, thickness
        )
    return xd


def newton_drape(
    model,
    rest_uv: torch.Tensor,
    x: torch.Tensor,
    body_verts: torch.Tensor,
    body_faces: torch.Tensor,
    material: NewtonMaterial,
    config: NewtonDrapeConfig | None = None,
    *,
    attach_vertices: torch.Tensor | None = None,
    attach_targets: np.ndarray | None = None,
) -> NewtonDrapeResult:
    """Settle the garment with Newton's VBD cloth until it rests (see the module docstring).

    Args:
        model: our seam-merged `ClothModel` (topology, edges, panel vertices): ``sew_and_drape(...).model``;
            or a `NewtonCloth` (then ``rest_uv`` is unused: an asset's exported arrays).
        rest_uv: (V, 2) panel-vertex rest coordinates [m].
        x: (Vs, 3) start positions [m] (e.g. our drape, at rest).
        body_verts: (Vb, 3) static body [m]; body_faces: (Fb, 3) int64.
        material: Newton's parameters (``edge_ke`` one per edge of ``model``).
        config: stepping options.
        attach_vertices: (A,) int64 simulated vertices held fixed at ``attach_targets`` (A, 3) [m]
            (a waistband where our lowered drape has it: `synthetic_scans`); default none.

    Raises:
        InputError: Newton is not installed. SimulationError: the settle blew up.
    """
    config = NewtonDrapeConfig() if config is None else config
    _, newton = import_newton()
    cloth = model if isinstance(model, NewtonCloth) else newton_cloth(model, rest_uv, material.density)
    if len(material.edge_ke) != cloth.edge_count:
        raise ValueError(
            f"material.edge_ke has {len(material.edge_ke)} values, the model {cloth.edge_count} edges"
        )
    attach = (
        None if attach_vertices is None or not len(attach_vertices) else (attach_vertices, attach_targets)
    )
    nmodel = _build_model(newton, cloth, x, body_verts, body_faces, material, config, attach)
    return _settle(newton, nmodel, body_verts, body_faces, config)


def _build_model(
    newton, cloth: NewtonCloth, x, body_verts, body_faces, material: NewtonMaterial, config, attach=None
):
    """Newton's finalized `Model` of the garment ``cloth`` (particles at ``x`` (Vs, 3) [m]) and the body;
    ``attach``: None or (vertices (A,), targets (A, 3) [m]): those particles are kinematic at the targets."""
    tri, uv = cloth.tri_vertices, cloth.tri_rest_uv
    dm = np.stack((uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]), axis=-1)  # (F, 2, 2) columns: rest edges
    area = 0.5 * np.abs(np.linalg.det(dm))
    edges = cloth.edge_indices

    builder = newton.ModelBuilder(up_axis=newton.Axis.Y)  # gravity -9.81 m/s² along -Y
    xs = x.double().cpu().numpy().copy()
    mass = cloth.vert_mass.copy()
    if attach is not None:  # kinematic (mass 0) waist particles, on the body surface
        held = np.asarray(attach[0].cpu() if isinstance(attach[0], torch.Tensor) else attach[0])
        xs[held] = np.asarray(attach[1])
        mass[held] = 0.0
    builder.add_particles(
        pos=[tuple(p) for p in xs],
        vel=[(0.0, 0.0, 0.0)] * len(xs),
        mass=mass.tolist(),
        radius=[material.particle_radius] * len(xs),
    )
    n_tri = len(tri)
    builder.add_triangles(
        tri[:, 0], tri[:, 1], tri[:, 2],
        tri_ke=[material.tri_ke] * n_tri, tri_ka=[material.tri_ka] * n_tri, tri_kd=[material.tri_kd] * n_tri,
    )  # fmt: skip
    if len(builder.tri_poses) != n_tri:
        raise SimulationError("Newton dropped degenerate triangles of the drape: cannot settle it")
    # the rest shape is the pattern's, per triangle (the builder took it from the 3D drape)
    builder.tri_poses[:] = np.linalg.inv(dm).tolist()
    builder.tri_areas[:] = area.tolist()
    builder.add_edges(
        edges[:, 0], edges[:, 1], edges[:, 2], edges[:, 3],
        rest=[0.0] * len(edges), edge_ke=material.edge_ke.tolist(), edge_kd=[material.edge_kd] * len(edges),
    )  # fmt: skip
    builder.edge_rest_length[-len(edges) :] = cloth.edge_rest_length.tolist()
    builder.add_shape_mesh(
        body=-1,
        mesh=newton.Mesh(
            body_verts.detach().cpu().numpy().astype(np.float32),
            body_faces.cpu().numpy().astype(np.int32).flatten(),
            compute_inertia=False,
        ),
        cfg=newton.ModelBuilder.ShapeConfig(
            mu=material.soft_contact_mu, ke=config.contact_ke, kd=config.contact_kd
        ),
    )
    # the floor under the feet: trousers' legs, lengthened by a waist drop and a soft membrane, pool on it
    # (without it a seed-105 pair hung 4.7 cm through it)
    floor = float(body_verts[:, 1].min())
    builder.add_ground_plane(
        height=floor,
        cfg=newton.ModelBuilder.ShapeConfig(
            mu=material.soft_contact_mu, ke=config.contact_ke, kd=config.contact_kd
        ),
    )
    _add_springs(builder, cloth, config.seam_ke)
    nmodel = builder.finalize(device="cpu")
    nmodel.soft_contact_ke, nmodel.soft_contact_kd = config.contact_ke, config.contact_kd
    nmodel.soft_contact_mu = material.soft_contact_mu
    return nmodel


def _add_springs(builder, cloth: NewtonCloth, ke: float) -> None:
    """``cloth``'s zero-length springs at stiffness ``ke`` [N/m] (none: nothing), and the VBD colouring:
    Newton's own without springs, `vertex_coloring` (springs included) with them."""
    pairs = cloth.spring_pairs
    if pairs is None or not len(pairs):
        builder.color(include_bending=True)
        return
    for i, j in np.asarray(pairs).tolist():
        builder.add_spring(i, j, ke, 0.0, control=0.0)
    builder.spring_rest_length[-len(pairs) :] = [0.0] * len(pairs)  # the builder took the start distances
    builder.set_coloring(vertex_coloring(builder.particle_count, cloth))


def _settle(newton, nmodel, body_verts, body_faces, config: NewtonDrapeConfig) -> NewtonDrapeResult:
    """Step ``nmodel`` from rest at its particles' positions until the mean speed stays under tolerance."""
    from torch_diffavatar.sim.forward_drape import penetration_diagnostics

    solver = newton.solvers.SolverVBD(nmodel, iterations=config.iterations)
    pipeline = newton.CollisionPipeline(nmodel, soft_contact_gap=config.contact_gap)
    contacts = pipeline.contacts()
    control = nmodel.control()
    s0, s1 = nmodel.state(), nmodel.state()
    dt = 1.0 / config.fps / config.substeps
    t0 = time.perf_counter()
    calm, frames, converged = 0, 0, False
    while frames < config.max_frames:
        pipeline.collide(s0, contacts)  # once per frame, within the detection band
        for _ in range(config.substeps):
            s0.clear_forces()
            solver.step(s0, s1, control, contacts, dt)
            s0, s1 = s1, s0
        frames += 1
        qd = s0.particle_qd.numpy()
        speed = np.linalg.norm(qd, axis=1)
        if not np.all(np.isfinite(speed)) or speed.max() > config.blow_up_speed:
            raise SimulationError(
                f"the Newton settle blew up at frame {frames} (max speed {speed.max():.3g} m/s)"
            )
        s0.particle_qd.assign(qd * config.velocity_scale)
        calm = calm + 1 if speed.mean() < config.speed_tol and speed.max() < config.max_speed_tol else 0
        if frames >= config.min_frames and calm >= config.settle_frames:
            converged = True
            break
    seconds = time.perf_counter() - t0
    xf = torch.from_numpy(s0.particle_q.numpy().astype(np.float64))
    pen = penetration_diagnostics(xf, body_verts.double(), body_faces)
    return NewtonDrapeResult(
        x=xf,
        frames=frames,
        seconds=seconds,
        mean_speed=float(speed.mean()),
        max_speed=float(speed.max()),
        converged=converged,
        penetrating_count=int(pen["penetrating_count"]),
    )
