"""XPBD stepping (Macklin et al. 2016 "XPBD"; small steps, Macklin et al. 2019) for the cloth model.

One `XPBDSolver.step` is one frame of ``dt`` seconds: body contacts are detected once, then
``substeps`` times: predict (damping, gravity), reset multipliers, ``iterations`` × project all
constraints (stretch, bending, attachments, body contacts, stitches), friction, update velocities.
Constraint passes are Gauss–Seidel over a graph colouring (default) or Jacobi. The solver keeps no
state; `step` returns a new `ClothState`, `advance` the state and the frame's contacts. Blow-ups raise
`SimulationError`.

All substeps of a frame run in one call of `ops.xpbd_substeps_` with the arguments `substep_inputs`
builds (`sim/substep.py`): the fused C++ op when the extension is built (about 0.5 ms of CPU per substep
on the 64×64 benchmark sheet, `python -m torch_diffavatar.sim.benchmark`), else its PyTorch twin
`reference.xpbd_substeps_`, whose maths `reference.xpbd_substeps` (the per-constraint reference kernels,
stitches, attachments, `sim.contacts`' projection and friction) is the maths of record, and also the
frame that the trajectory adjoint replays.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from torch_diffavatar.errors import SimulationError
from torch_diffavatar.geometry import green_strain
from torch_diffavatar.sim import collision, ops
from torch_diffavatar.sim.constraints import RestData
from torch_diffavatar.sim.contacts import Contacts
from torch_diffavatar.sim.model import ClothModel
from torch_diffavatar.sim.state import ClothState
from torch_diffavatar.sim.substep import (
    BendInputs,
    BodyInputs,
    SeamInputs,
    StretchInputs,
    SubstepInputs,
    SubstepParams,
)

SCHEMES = ("gauss_seidel", "jacobi")


# Grid cell of the body index [m]: cells about twice the contact band visit fewer cells per query;
# measured fastest (4 and 5 cm alike) on the Anny body with 2.3–5 cm bands; never changes the contacts.
_CONTACT_CELL = 0.04


@dataclass(frozen=True)
class XPBDConfig:
    """Stepping options.

    Defaults: 40 substeps × 1 iteration (Macklin et al. 2019 "small steps"; also Newton's fastest correct
    CPU configuration). Measured on a dress hanging from its straps on the Anny body (8k vertices, 12
    frames): 99th-percentile Green strain 0.05 at 40×1, 0.10 at 20×2 and 10×8, 0.44 at 10×2 — substeps
    buy stiffness far more cheaply than iterations.

    Attributes:
        substeps: substeps per `step` (frame).
        iterations: constraint passes per substep.
        scheme: ``"gauss_seidel"`` (colour-ordered) or ``"jacobi"``.
        jacobi_omega: Jacobi relaxation factor (used with ``scheme="jacobi"``).
        gravity: (3,) gravitational acceleration [m/s²] (world frame, Y up).
        collision_band: detection band beyond the thickness [m]; cloth farther from the body than
            ``thickness + max(collision_band, 1.5 · max speed · dt)`` at the start of a frame is not
            checked during that frame.
        stitch_compliance: compliance of the zero-length stitch constraints [m/N].
        stitch_max_speed: in one substep the stitch constraints move a vertex by at most
            ``stitch_max_speed · substep`` [m/s] (a bounded pull: inertia still accumulates over substeps,
            and the sewing damping ``velocity_scale`` bleeds it).
        stitch_snap: stitch gaps under this [m] are closed without the ``stitch_max_speed`` limit.
        attach_compliance: compliance of the waist attachment constraints [m/N].
        max_speed: a vertex faster than this [m/s] is a blow-up.
        max_strain: a Green strain component |E| beyond this [-] is a blow-up (3 = stretch ×2.65; real
            blow-ups reach 10–100 within a frame or two, while a triangle pinched at a seam corner can
            sit at E ≈ 1 in a sane drape), where it covers more than ``max_strain_area``.
        max_strain_area: rest area [m²] that triangles beyond ``max_strain`` may cover without a blow-up
            (5 cm²; one triangle is ~2.5 cm² at 3 cm spacing). GarmentCode's tops have 5.6 mm seam edges at
            the shoulder tips, whose triangles (0.14–0.19 cm²) sat at E = 1.0–2.7 in 18 of 54 fitted drapes
            and rose to 2.5 as the arms moved: a sliver stretched by the cloth around it, which more substeps
            do not change, is not a blow-up (docs/BENCHMARKS.md, "Slivers at the shoulder tips").
        use_extension: use the C++ ops when built (else the PyTorch reference kernels).
        num_threads: OpenMP threads of the C++ substep op (0 = ``torch.get_num_threads()``). 1 by
            default: its Gauss–Seidel colours need a barrier each, and on the shared 2-core development
            machine a second thread made a substep slower, not faster (scripts/bench_kernels.py).
        contact_bounce: the share of its outward normal velocity that a vertex pushed out of the body in a
            substep keeps (1, the default: all of it, the push becoming a velocity; 0: an inelastic contact).
            Below 1 fewer contact vertices rock: on a fitted dress (its own drape continued for 80 frames)
            71-90 of 1,992 vertices still moved faster than 2 cm/s at 1, 9-14 at 0, among them an armpit
            vertex jumping between two body triangles each frame, which no bounce cures (``valley_contacts``
            does; docs/BENCHMARKS.md, "Drapes that never settle" and "Valley contacts").
        contact_cache: against a static body, query only the vertices that can be in the contact band,
            seeded with last frame's triangles (`collision.ContactCache`; C++ only). The contacts, hence
            the results, are the same with and without it.
        valley_contacts: a contact vertex within ``valley_margin`` of the thickness from a body triangle
            around its own that rises above its contact plane (a valley: the armpit, the spine's groove)
            gets a second contact there (`collision.detect_contacts`' ``valley``; see `sim/collision.py`).
            Off by default: one contact per vertex. On a fitted dress two armpit vertices otherwise jumped
            6.5–8.9 mm between the two sides every frame for good, and 71-88 vertices never came to rest (none
            with it); a strip in a frictionless groove is flung out (docs/BENCHMARKS.md, "Valley contacts").
        valley_margin: see ``valley_contacts`` [m].
        floor_faces: the body mesh's last ``floor_faces`` faces are a floor (`sim.floor.with_floor`, which
            `DrapeConfig.floor` sets up): a contact vertex within the thickness plus ``valley_margin`` of it
            also gets a floor contact (`collision.detect_contacts`' ``floor``). 0: no floor.
    """

    substeps: int = 40
    iterations: int = 1
    scheme: str = "gauss_seidel"
    jacobi_omega: float = 1.0
    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)
    collision_band: float = 0.02
    stitch_compliance: float = 1e-5
    stitch_max_speed: float = 0.5
    stitch_snap: float = 0.005
    attach_compliance: float = 1e-5
    max_speed: float = 50.0
    max_strain: float = 3.0
    max_strain_area: float = 5e-4
    use_extension: bool = True
    num_threads: int = 1
    contact_bounce: float = 1.0
    contact_cache: bool = True
    valley_contacts: bool = False
    valley_margin: float = 0.001
    floor_faces: int = 0

    def __post_init__(self):
        if self.scheme not in SCHEMES:
            raise ValueError(f"XPBDConfig.scheme must be one of {SCHEMES}, got {self.scheme!r}")
        if self.substeps < 1 or self.iterations < 1:
            raise ValueError(f"substeps and iterations must be >= 1, got {self.substeps}, {self.iterations}")
        if len(self.gravity) != 3:
            raise ValueError(f"XPBDConfig.gravity must have 3 components, got {self.gravity}")
        if self.num_threads < 0:
            raise ValueError(f"XPBDConfig.num_threads must be >= 0, got {self.num_threads}")
        if not 0 <= self.contact_bounce <= 1:
            raise ValueError(f"XPBDConfig.contact_bounce must be in [0, 1], got {self.contact_bounce}")
        if not 0 <= self.valley_margin < math.inf:
            raise ValueError(f"XPBDConfig.valley_margin must be finite and >= 0, got {self.valley_margin}")
        if self.floor_faces < 0:
            raise ValueError(f"XPBDConfig.floor_faces must be >= 0, got {self.floor_faces}")
        if not 0 <= self.max_strain_area < math.inf:
            raise ValueError(
                f"XPBDConfig.max_strain_area must be finite and >= 0 [m²], got {self.max_strain_area}"
            )

    def valley_radius(self, thickness) -> float | None:
        """The ``valley`` radius [m] of `collision.detect_contacts` for cloth of ``thickness`` [m] (None:
        valley contacts off)."""
        return float(thickness) + self.valley_margin if self.valley_contacts else None

    def floor_contacts(self, face_count: int, thickness) -> tuple[int, float] | None:
        """The ``floor`` of `collision.detect_contacts` for a body mesh of ``face_count`` faces and cloth of
        ``thickness`` [m] (None: no floor)."""
        if not self.floor_faces:
            return None
        return face_count - self.floor_faces, float(thickness) + self.valley_margin


@dataclass(frozen=True)
class StepResult:
    """One frame of `XPBDSolver.advance`.

    Attributes:
        state: the new `ClothState`.
        contacts: the body contacts the frame projected against (detected once, at its start), or None
            without a body or without a vertex in the contact band. The trajectory adjoint records them
            to replay the frame against the same set.
    """

    state: ClothState
    contacts: Contacts | None


class XPBDSolver:
    """Steps a `ClothModel` (static data) from one `ClothState` to the next.

    The solver keeps nothing that changes the results between frames: each frame's contacts are an
    output of `advance`. (It caches the closest-point grid of a static body and, with
    ``config.contact_cache``, what the last frames' contact queries learnt about each vertex
    (`collision.ContactCache`): both only save time, the contacts are those of a full query.)

    Args:
        model: the cloth model.
        config: stepping options.
    """

    def __init__(self, model: ClothModel, config: XPBDConfig | None = None):
        self.model = model
        self.config = XPBDConfig() if config is None else config
        # closest-point grid of the last static body seen by `advance` (rebuilt when the body changes), and
        # what the last frames' queries against it learnt per cloth vertex (dropped with it)
        self._body_index: collision.BodyIndex | None = None
        self._contact_cache: collision.ContactCache | None = None

    def step(self, state: ClothState, rest: RestData, dt: float, **kwargs) -> ClothState:
        """Advance one frame and return the new `ClothState` (`advance` without the contacts; the same
        keyword arguments)."""
        return self.advance(state, rest, dt, **kwargs).state

    def advance(
        self,
        state: ClothState,
        rest: RestData,
        dt: float,
        *,
        body_verts: torch.Tensor | None = None,
        body_faces: torch.Tensor | None = None,
        gravity_scale: float = 1.0,
        stitch_compliance: float | None = None,
        velocity_scale: float = 1.0,
        friction_scale: float = 1.0,
        body_verts_end: torch.Tensor | None = None,
    ) -> StepResult:
        """Advance one frame.

        Args:
            state: current positions/velocities (Vs, 3).
            rest: `ClothModel.rest_data(rest_uv, material)`.
            dt: frame time [s] (split into ``config.substeps``).
            body_verts: (Vb, 3) body vertices [m] (an explicit input: the response depends on them).
            body_faces: (Fb, 3) int64 body triangles (outward normals).
            gravity_scale: multiplies ``config.gravity`` (0 while sewing).
            stitch_compliance: overrides ``config.stitch_compliance`` [m/N] (sewing ramps it down).
            velocity_scale: extra factor on the velocities at the end of the frame (sewing damping).
            friction_scale: multiplies the material's friction (0 while sewing, so that seams pulled
                over the body can slide into place).
            body_verts_end: (Vb, 3) the body at the end of the frame, for a moving body: then
                ``body_verts`` is its start, and substep k sees the body interpolated linearly to
                (k + 1) / substeps of the way, so cloth in contact takes on the body's velocity instead
                of being overtaken by it (no tunnelling). The contacts are detected once, at the start,
                in a band widened by the body's largest displacement.

        Returns:
            `StepResult`: the new state and the frame's contacts.

        Raises:
            SimulationError: NaN/inf, a vertex faster than ``max_speed`` or strain beyond ``max_strain``
                over more than ``max_strain_area`` of cloth.
        """
        if (body_verts is None) != (body_faces is None):
            raise ValueError("pass both body_verts and body_faces, or neither")
        if dt <= 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        if body_verts_end is not None and (body_verts is None or body_verts_end.shape != body_verts.shape):
            raise ValueError("body_verts_end needs body_verts of the same (Vb, 3) shape")
        x = state.x.detach().clone().contiguous()
        v = state.v.detach().clone().contiguous()
        with torch.no_grad():
            contacts = None
            if body_verts is not None:
                contacts = self._detect(x, v, rest, dt, body_verts, body_faces, body_verts_end)
            inputs = substep_inputs(
                self.model, rest, self.config, dt, contacts=contacts, body_verts=body_verts,
                body_faces=body_faces, gravity_scale=gravity_scale, stitch_compliance=stitch_compliance,
                friction_scale=friction_scale,
            )  # fmt: skip
            if contacts is None or body_verts_end is None:
                self._substeps(x, v, inputs)
            else:
                self._substeps_moving_body(x, v, inputs, body_verts_end)
            if velocity_scale != 1.0:
                v = v * velocity_scale
            self._check(x, v, rest)
        return StepResult(ClothState(x, v), contacts)

    def _detect(self, x, v, rest, dt, body_verts, body_faces, body_verts_end) -> Contacts | None:
        """The frame's contacts: cloth vertices within `contact_band` of the body (None when none)."""
        band = contact_band(v, rest.material, self.config, dt)
        if body_verts_end is not None:
            band += float((body_verts_end - body_verts).norm(dim=-1).max())
        index = cache = None
        if body_verts_end is None:  # a static body: reuse its grid from frame to frame
            index = self._body_index
            if index is None or not index.matches(body_verts, body_faces):
                index = collision.BodyIndex(
                    body_verts, body_faces, cell_size=_CONTACT_CELL, use_extension=self.config.use_extension
                )
                self._body_index = index
                self._contact_cache = None
            if self.config.contact_cache and index.grid is not None:
                if self._contact_cache is None:
                    self._contact_cache = collision.ContactCache(index)
                cache = self._contact_cache
        thickness = rest.material.thickness
        contacts = collision.detect_contacts(
            x, body_verts, body_faces, band, use_extension=self.config.use_extension, index=index,
            cache=cache, valley=self.config.valley_radius(thickness),
            floor=self.config.floor_contacts(body_faces.shape[0], thickness),
        )  # fmt: skip
        return contacts if contacts.count else None

    def _substeps(self, x: torch.Tensor, v: torch.Tensor, inputs: SubstepInputs) -> None:
        """Run the frame's substeps in place on x and v (`ops.xpbd_substeps_`)."""
        ops.xpbd_substeps_(x, v, inputs, use_extension=self.config.use_extension)

    def _substeps_moving_body(self, x, v, inputs: SubstepInputs, body_verts_end: torch.Tensor) -> None:
        """One substep per call, each against the body interpolated to the substep's end."""
        start = inputs.body.body_verts
        end = body_verts_end.detach().to(x.dtype)
        substeps = inputs.params.substeps
        one = dataclasses.replace(inputs.params, substeps=1)
        for k in range(substeps):
            body = dataclasses.replace(
                inputs.body, body_verts=(start + (k + 1) / substeps * (end - start)).contiguous()
            )
            self._substeps(x, v, dataclasses.replace(inputs, body=body, params=one))

    def _check(self, x, v, rest):
        cfg = self.config
        if not (torch.isfinite(x).all() and torch.isfinite(v).all()):
            raise SimulationError(
                "simulation produced NaN/inf positions or velocities (time step too large?)"
            )
        speed = float(v.norm(dim=-1).max()) if v.numel() else 0.0
        if speed > cfg.max_speed:
            fastest = _where(x[int(v.norm(dim=-1).argmax())])
            raise SimulationError(
                f"simulation blew up: a vertex at {fastest} moves at {speed:.3g} m/s > max_speed "
                f"{cfg.max_speed:g} m/s (reduce dt or increase substeps)"
            )
        strain = float(
            ops.max_abs_green_strain(
                x,
                self.model.tri_vertices,
                rest.tri_rest_inv.detach().contiguous(),
                use_extension=cfg.use_extension,
            )
        )
        if strain > cfg.max_strain:
            # which triangles (the op gives the largest strain only): slivers alone are no blow-up
            e, over, area = strained_triangles(x, self.model, rest, cfg.max_strain)
            if area <= cfg.max_strain_area:
                return
            worst = _where(x[self.model.tri_vertices[int(e.argmax())]].mean(0))
            raise SimulationError(
                f"simulation blew up: Green strain {strain:.3g} > max_strain {cfg.max_strain:g} in "
                f"{int(over.sum())} triangle(s) of {1e4 * area:.3g} cm², the worst at {worst} (reduce dt, "
                "increase substeps/iterations, or check the rest shape)"
            )


def strained_triangles(
    x: torch.Tensor, model: ClothModel, rest: RestData, max_strain: float
) -> tuple[torch.Tensor, torch.Tensor, float]:
    """What the blow-up test measures (`XPBDSolver`, ``XPBDConfig.max_strain_area``): per triangle of
    ``model`` the largest |Green strain| component (F,) of ``x`` (Vs, 3) [m] against ``rest``, the mask (F,)
    of those beyond ``max_strain``, and the rest area [m²] they cover."""
    e = green_strain(x, model.tri_vertices, rest.tri_rest_inv.detach()).abs().amax(-1)
    over = e > max_strain
    return e, over, float(rest.tri_area.detach()[over].sum())


def _where(p: torch.Tensor) -> str:
    """A point (3,) [m] for a message: "(x, y, z) m", to the millimetre."""
    return "(" + ", ".join(f"{float(c):.3f}" for c in p) + ") m"


def contact_band(v: torch.Tensor, material, config: XPBDConfig, dt: float) -> float:
    """The contact-detection band [m] of a frame starting with velocities ``v`` (Vs, 3) [m/s]: the
    thickness plus ``config.collision_band``, or how far the fastest vertex can travel in ``dt`` [s]
    (× 1.5) when that is more (a moving body widens it further by its largest displacement)."""
    reach = 1.5 * float(v.norm(dim=-1).max()) * dt if v.numel() else 0.0
    return float(material.thickness) + max(config.collision_band, reach)


def substep_inputs(
    model: ClothModel,
    rest: RestData,
    config: XPBDConfig,
    dt: float,
    *,
    contacts: Contacts | None = None,
    body_verts: torch.Tensor | None = None,
    body_faces: torch.Tensor | None = None,
    gravity_scale: float = 1.0,
    stitch_compliance: float | None = None,
    friction_scale: float = 1.0,
) -> SubstepInputs:
    """The arguments of one frame's substeps (`ops.xpbd_substeps_`, `reference.xpbd_substeps`): the one
    place that maps the model, its rest data and the options onto them (the solver and the trajectory
    adjoint's replays both call it, so a replayed frame is the frame the solver ran).

    Args:
        model, rest, config: the cloth model, `ClothModel.rest_data` (its tensors may require grad: they
            are passed as they are) and the stepping options.
        dt: frame time [s]; contacts: the frame's contact set or None; body_verts: (Vb, 3) [m];
        body_faces: (Fb, 3) int64 (read when ``contacts`` is given); gravity_scale, stitch_compliance,
        friction_scale: as `XPBDSolver.advance`.
    """
    h = dt / config.substeps
    mat = rest.material
    w = rest.vert_inv_mass
    if contacts is not None:
        body = BodyInputs(
            body_verts.to(w.dtype).contiguous(), body_faces.contiguous(), contacts.vert, contacts.tri,
            contacts.bary.to(w.dtype).contiguous(),
        )  # fmt: skip
    else:
        no_index = model.tri_vertices.new_zeros(0)
        body = BodyInputs(
            w.new_zeros(0, 3), model.tri_vertices.new_zeros(0, 3), no_index, no_index, w.new_zeros(0, 3)
        )
    tc, ec = model.tri_coloring, model.edge_coloring
    params = SubstepParams(
        gravity=tuple(gi * gravity_scale for gi in config.gravity),
        velocity_decay=math.exp(-float(mat.damping) * h),
        dt=h,
        stitch_compliance=config.stitch_compliance if stitch_compliance is None else stitch_compliance,
        stitch_max_move=config.stitch_max_speed * h / config.iterations,
        stitch_snap=config.stitch_snap,
        attach_compliance=config.attach_compliance,
        thickness=float(mat.thickness),
        friction=float(mat.friction) * friction_scale,
        jacobi_omega=config.jacobi_omega,
        contact_bounce=config.contact_bounce,
        substeps=config.substeps,
        iterations=config.iterations,
        jacobi=config.scheme == "jacobi",
        num_threads=config.num_threads,
    )
    return SubstepInputs(
        vert_inv_mass=w.contiguous(),
        stretch=StretchInputs(
            model.tri_vertices,
            rest.tri_rest_inv.contiguous(),
            rest.tri_compliance.contiguous(),
            tc.order,
            tc.color_offsets,
        ),  # fmt: skip
        bend=BendInputs(
            model.edge_quads,
            rest.edge_rest_angle.contiguous(),
            rest.edge_compliance.contiguous(),
            ec.order,
            ec.color_offsets,
        ),  # fmt: skip
        seams=SeamInputs(model.stitch_vertices, model.attach_vertices, rest.attach_height.contiguous()),
        body=body,
        params=params,
    )
