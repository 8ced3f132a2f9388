"""XPBD stepping (Macklin et al. 2016 "XPBD"; small steps, Macklin et al. 2019) for the cloth model.

One `XPBDSolver.step` is one frame of ``dt`` seconds: body contacts are detected once, then
``substeps`` times: predict (damping, gravity), reset multipliers, ``iterations`` × project all
constraints (stretch, bending, attachments, body contacts, stitches), friction, update velocities.
Constraint passes are Gauss–Seidel over a graph colouring (default) or Jacobi. The solver keeps no
state; `step` returns a new `ClothState`. Blow-ups raise `SimulationError`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torch_diffavatar.errors import SimulationError
from torch_diffavatar.sim import collision, ops
from torch_diffavatar.sim.constraints import RestData, green_strain
from torch_diffavatar.sim.model import ClothModel
from torch_diffavatar.sim.state import ClothState

SCHEMES = ("gauss_seidel", "jacobi")


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
            sit at E ≈ 1 in a sane drape).
        use_extension: use the C++ ops when built (else the PyTorch reference kernels).
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
    use_extension: bool = True

    def __post_init__(self):
        if self.scheme not in SCHEMES:
            raise ValueError(f"XPBDConfig.scheme must be one of {SCHEMES}, got {self.scheme!r}")
        if self.substeps < 1 or self.iterations < 1:
            raise ValueError(f"substeps and iterations must be >= 1, got {self.substeps}, {self.iterations}")
        if len(self.gravity) != 3:
            raise ValueError(f"XPBDConfig.gravity must have 3 components, got {self.gravity}")


class XPBDSolver:
    """Steps a `ClothModel` (static data) from one `ClothState` to the next.

    Args:
        model: the cloth model.
        config: stepping options.
    """

    def __init__(self, model: ClothModel, config: XPBDConfig | None = None):
        self.model = model
        self.config = XPBDConfig() if config is None else config

    def step(
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
    ) -> ClothState:
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

        Returns:
            the new `ClothState`.

        Raises:
            SimulationError: NaN/inf, a vertex faster than ``max_speed`` or strain beyond ``max_strain``.
        """
        cfg, model = self.config, self.model
        if (body_verts is None) != (body_faces is None):
            raise ValueError("pass both body_verts and body_faces, or neither")
        if dt <= 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        h = dt / cfg.substeps
        mat = rest.material
        x = state.x.detach().clone()
        v = state.v.detach().clone()
        w = rest.vert_inv_mass.detach().contiguous()
        movable = (w > 0).to(x.dtype)[:, None]
        g = x.new_tensor(cfg.gravity) * gravity_scale
        damp = math.exp(-float(mat.damping) * h)
        alpha_stitch = cfg.stitch_compliance if stitch_compliance is None else stitch_compliance
        contacts = None
        with torch.no_grad():
            if body_verts is not None:
                # the band also covers how far the fastest vertex can travel in this frame
                reach = 1.5 * float(v.norm(dim=-1).max()) * dt if v.numel() else 0.0
                band = float(mat.thickness) + max(cfg.collision_band, reach)
                contacts = collision.detect_contacts(
                    x, body_verts, body_faces, band, use_extension=cfg.use_extension
                )
                if contacts.count == 0:
                    contacts = None
            tri_c, edge_c = (
                rest.tri_compliance.detach().contiguous(),
                rest.edge_compliance.detach().contiguous(),
            )
            tri_inv, edge_rest = (
                rest.tri_rest_inv.detach().contiguous(),
                rest.edge_rest_angle.detach().contiguous(),
            )
            for _ in range(cfg.substeps):
                x_start = x
                v = (v * damp + g * h) * movable
                x = (x + v * h).contiguous()
                lam_tri = x.new_zeros(model.tri_count, 3)
                lam_edge = x.new_zeros(model.edge_count)
                lam_stitch = x.new_zeros(model.stitch_vertices.shape[0], 3)
                lam_attach = x.new_zeros(model.attach_vertices.shape[0])
                depth_sum = None
                for _ in range(cfg.iterations):
                    self._project_elastic(x, lam_tri, lam_edge, w, tri_inv, tri_c, edge_rest, edge_c, h)
                    if lam_attach.numel():
                        _project_attach(
                            x,
                            lam_attach,
                            w,
                            model.attach_vertices,
                            model.attach_height,
                            cfg.attach_compliance,
                            h,
                        )
                    if contacts is not None:
                        x, depth, normal = collision.project_contacts(
                            x, w, body_verts, body_faces, contacts, mat.thickness
                        )
                        depth_sum = depth if depth_sum is None else depth_sum + depth
                    # stitches last: a seam pressed onto the body still closes (the drape fixes contacts)
                    if lam_stitch.numel():
                        max_move = cfg.stitch_max_speed * h / cfg.iterations
                        pairs = model.stitch_vertices
                        _project_stitches(x, lam_stitch, w, pairs, alpha_stitch, h, max_move, cfg.stitch_snap)
                mu = float(mat.friction) * friction_scale
                if contacts is not None and mu > 0:
                    x = collision.apply_friction(x, x_start, contacts, normal, depth_sum, mu)
                v = (x - x_start) / h
            if velocity_scale != 1.0:
                v = v * velocity_scale
            self._check(x, v, rest)
        return ClothState(x, v)

    def _project_elastic(self, x, lam_tri, lam_edge, w, tri_inv, tri_c, edge_rest, edge_c, h):
        model, cfg = self.model, self.config
        ext = cfg.use_extension
        if cfg.scheme == "gauss_seidel":
            tc, ec = model.tri_coloring, model.edge_coloring
            ops.stretch_project_(
                x,
                lam_tri,
                w,
                model.tri_vertices,
                tri_inv,
                tri_c,
                tc.order,
                tc.color_offsets,
                h,
                use_extension=ext,
            )
            if model.edge_count:
                ops.bend_project_(
                    x,
                    lam_edge,
                    w,
                    model.edge_quads,
                    edge_rest,
                    edge_c,
                    ec.order,
                    ec.color_offsets,
                    h,
                    use_extension=ext,
                )
        else:
            om = cfg.jacobi_omega
            ops.stretch_project_jacobi_(
                x, lam_tri, w, model.tri_vertices, tri_inv, tri_c, h, om, use_extension=ext
            )
            if model.edge_count:
                ops.bend_project_jacobi_(
                    x, lam_edge, w, model.edge_quads, edge_rest, edge_c, h, om, use_extension=ext
                )

    def _check(self, x, v, rest):
        cfg = self.config
        if not (torch.isfinite(x).all() and torch.isfinite(v).all()):
            raise SimulationError(
                "simulation produced NaN/inf positions or velocities (time step too large?)"
            )
        speed = float(v.norm(dim=-1).max()) if v.numel() else 0.0
        if speed > cfg.max_speed:
            raise SimulationError(
                f"simulation blew up: a vertex moves at {speed:.3g} m/s > max_speed {cfg.max_speed:g} m/s "
                "(reduce dt or increase substeps)"
            )
        strain = float(green_strain(x, self.model.tri_vertices, rest.tri_rest_inv.detach()).abs().max())
        if strain > cfg.max_strain:
            raise SimulationError(
                f"simulation blew up: Green strain {strain:.3g} > max_strain {cfg.max_strain:g} "
                "(reduce dt, increase substeps/iterations, or check the rest shape)"
            )


def _project_stitches(x, lam, w, pairs, alpha, h, max_move, snap):
    """Zero-length stitches ``C = x_a − x_b`` (3-vector), Jacobi-averaged per vertex, in place.

    Each pass moves a stitched vertex by at most ``max_move`` [m] unless its gap is under ``snap`` [m]:
    a wide-open seam then closes with a bounded pull that the membrane constraints can follow, instead
    of yanking single vertices out of their triangles (which the Green-strain constraints cannot
    recover from in a few iterations).
    """
    a, b = pairs[:, 0], pairs[:, 1]
    wa, wb = w[a], w[b]
    alpha_t = alpha / (h * h)
    c = x[a] - x[b]
    denom = (wa + wb + alpha_t)[:, None]
    dlam = (-c - alpha_t * lam) / denom
    move = torch.maximum(wa, wb) * dlam.norm(dim=-1)
    # seams already within ``snap`` close without limit (the body cannot hold them open)
    limit = torch.where(c.norm(dim=-1) < snap, move, torch.full_like(move, max_move)).clamp_min(max_move)
    dlam = dlam * (limit / move.clamp_min(limit))[:, None]
    lam += dlam
    idx = torch.cat((a, b))
    dx = torch.cat((wa[:, None] * dlam, -wb[:, None] * dlam))
    total = torch.zeros_like(x).index_add_(0, idx, dx)
    count = x.new_zeros(x.shape[0]).index_add_(0, idx, x.new_ones(idx.shape[0]))
    x += total / count.clamp_min(1.0)[:, None]


def _project_attach(x, lam, w, verts, height, alpha, h):
    """Soft height constraints ``C = y − y_target`` (waist attachments), in place."""
    wv = w[verts]
    alpha_t = alpha / (h * h)
    c = x[verts, 1] - height
    dlam = torch.where(wv > 0, (-c - alpha_t * lam) / (wv + alpha_t), torch.zeros_like(c))
    lam += dlam
    x[verts, 1] += wv * dlam
