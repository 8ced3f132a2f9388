"""Fast differentiable replay of one XPBD frame (the trajectory adjoint's inner loop).

`XPBDSolver.step` runs a frame in the fused C++ op; the trajectory adjoint needs the same frame as a
differentiable function of (x, v), the rest data and the body vertices. The per-constraint reference
kernels of `sim/reference.py` are written for clarity (≈80 small torch ops per colour, in place on
clones), which made a replayed frame cost seconds. `ReplayPlan` computes the same maths with few, larger
ops per colour, so that autograd records few nodes:

* index tensors per colour are built once per plan (triangles whose three vertices are pinned, which
  the kernels skip, are dropped);
* the constant parts of each colour's 3×3 stretch system (inverse masses × rest-shape coefficients) are
  folded into small per-triangle matrices once per frame, so a colour is gather, two batched matmuls
  for F and FᵀF, one for the system, an adjugate solve, one matmul for the corrections and an
  out-of-place ``index_add``;
* bending uses the closed-form dihedral gradient of the reference, stacked (K, 4, 3);
* the multipliers of the first iteration are zero and are not materialised (one iteration per substep
  is the default).

The frame itself is `reference.xpbd_substeps` (the C++ op's twin: per substep predict, then per iteration
stretch colours, bend colours, attachments, contacts, stitches; friction; velocities) with this plan's
batched stretch and bend passes as its ``membrane``, and its arguments come from `solver.substep_inputs`,
as the solver's do. Gauss–Seidel only: the Jacobi scheme replays through `trajectory.replay_frame` (the
reference kernels).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torch_diffavatar.sim import reference
from torch_diffavatar.sim.contacts import Contacts
from torch_diffavatar.sim.model import ClothModel
from torch_diffavatar.sim.solver import XPBDConfig, substep_inputs
from torch_diffavatar.sim.substep import SubstepInputs

# adjugate of a symmetric 3x3 stored as (a00, a01, a02, a11, a12, a22): cof_k = A[i] A[j] - A[l] A[m]
_ADJ = torch.tensor([[3, 2, 1, 0, 1, 0], [5, 4, 4, 5, 2, 3], [4, 1, 2, 2, 0, 1], [4, 5, 3, 2, 4, 1]]).reshape(
    -1
)
_SYM9 = torch.tensor([0, 1, 2, 1, 3, 4, 2, 4, 5])  # full 3x3 from the 6 unique entries
_UPPER = torch.tensor([0, 1, 2, 4, 5, 8])  # the 6 unique entries of a flattened 3x3
_S3 = torch.tensor([0, 3, 1])  # (s00, s11, s01) of a flattened 2x2


@dataclass
class _TriColour:
    ids: torch.Tensor  # (K,) triangle ids
    tri: torch.Tensor  # (K, 3) vertex ids
    flat: torch.Tensor  # (3K,)


@dataclass
class _EdgeColour:
    ids: torch.Tensor  # (K,) edge ids
    quads: torch.Tensor  # (K, 4)
    flat: torch.Tensor  # (4K,)


@dataclass
class _FrameData:
    """Per-frame tensors derived from the (differentiable) rest data."""

    tri: list  # per colour (rest_inv^T (K,2,2), L (K,3,6), al6 (K,6), al (K,3,3), P (K,3,6))
    edge: list  # per colour (w (K,4), rest angle (K,), alpha~ (K,))


class _PlanMembrane:
    """`ReplayPlan`'s stretch and bend passes for `reference.xpbd_substeps` (its ``membrane``)."""

    def __init__(self, plan: ReplayPlan, data: _FrameData):
        self.plan, self.data = plan, data

    def start(self, x: torch.Tensor):
        """Per colour, the substep's multipliers: None until the first pass (they start at 0)."""
        return [None] * len(self.plan.tri_colours), [None] * len(self.plan.edge_colours)

    def project(self, x: torch.Tensor, lam):
        lam_tri, lam_edge = lam
        for k, (c, td) in enumerate(zip(self.plan.tri_colours, self.data.tri)):
            x, lam_tri[k] = self.plan._stretch(x, c, td, lam_tri[k])
        for k, (c, ed) in enumerate(zip(self.plan.edge_colours, self.data.edge)):
            x, lam_edge[k] = self.plan._bend(x, c, ed, lam_edge[k])
        return x, (lam_tri, lam_edge)


class ReplayPlan:
    """Index tensors of a model's Gauss–Seidel colours, to replay frames of `XPBDSolver.step`.

    Args:
        model: the cloth model; xpbd: the stepping options of the forward (``scheme="gauss_seidel"``);
        vert_inv_mass: (Vs,) inverse masses of the forward (only which are 0 matters here).
    """

    def __init__(self, model: ClothModel, xpbd: XPBDConfig, vert_inv_mass: torch.Tensor):
        if xpbd.scheme != "gauss_seidel":
            raise ValueError("ReplayPlan replays the Gauss–Seidel scheme only")
        self.model, self.xpbd = model, xpbd
        free = vert_inv_mass.detach() > 0
        self.tri_colours = []
        offsets = model.tri_coloring.color_offsets.tolist()
        for s, e in zip(offsets[:-1], offsets[1:]):
            ids = model.tri_coloring.order[s:e]
            ids = ids[free[model.tri_vertices[ids]].any(-1)]  # the kernels skip fully pinned triangles
            if ids.numel():
                tri = model.tri_vertices[ids]
                self.tri_colours.append(_TriColour(ids, tri, tri.reshape(-1)))
        self.edge_colours = []
        offsets = model.edge_coloring.color_offsets.tolist()
        for s, e in zip(offsets[:-1], offsets[1:]):
            ids = model.edge_coloring.order[s:e]
            if ids.numel():
                quads = model.edge_quads[ids]
                self.edge_colours.append(_EdgeColour(ids, quads, quads.reshape(-1)))
        dev = model.tri_vertices.device
        self._adj, self._sym9, self._upper, self._s3 = (t.to(dev) for t in (_ADJ, _SYM9, _UPPER, _S3))

    # ------------------------------------------------------------------------------------ per frame

    def frame_data(self, tri_rest_inv, tri_compliance, edge_rest_angle, edge_compliance, vert_inv_mass, h):
        """Fold the rest data into the per-colour matrices (differentiable)."""
        tri = [
            self._tri_colour_data(c, tri_rest_inv, tri_compliance, vert_inv_mass, h) for c in self.tri_colours
        ]
        edge = []
        for c in self.edge_colours:
            edge.append((vert_inv_mass[c.quads], edge_rest_angle[c.ids], edge_compliance[c.ids] / (h * h)))
        return _FrameData(tri, edge)

    def _tri_colour_data(self, c: _TriColour, tri_rest_inv, tri_compliance, vert_inv_mass, h):
        """(rest_inv^T (K,2,2), L (K,3,6), al6 (K,6), al (K,3,3), P (K,3,6)) of one colour of triangles."""
        r = tri_rest_inv[c.ids]  # (K, 2, 2) [[a, b], [c, d]]
        w = vert_inv_mass[c.tri]  # (K, 3)
        a, b, cc, d = r.reshape(-1, 4).unbind(1)
        p = torch.stack((a, cc, -a - cc), 1)  # per corner: F = [f0 f1], dC/dx_i from (p_i, q_i)
        q = torch.stack((b, d, -b - d), 1)
        wpp, wqq, wpq = (w * p * p).sum(1), (w * q * q).sum(1), (w * p * q).sum(1)
        z = torch.zeros_like(wpp)
        # A6 = (s00, s11, s01) @ L, entries (a00, a01, a02, a11, a12, a22) of reference._stretch_delta
        L = torch.stack(
            (
                torch.stack((wpp, z, 0.5 * wpq, z, z, 0.25 * wqq), 1),
                torch.stack((z, z, z, wqq, 0.5 * wpq, 0.25 * wpp), 1),
                torch.stack((z, wpq, 0.5 * wpp, z, 0.5 * wqq, 0.5 * wpq), 1),
            ),
            1,
        )  # (K, 3, 6)
        al = tri_compliance[c.ids] / (h * h)  # (K, 3, 3)
        al6 = al.reshape(-1, 9)[:, self._upper]
        # corrections: cf (K, 3 corners, 2) = dlam @ P; x_i += cf_i0 f0 + cf_i1 f1
        wp, wq = w * p, w * q
        zc = torch.zeros_like(wp)
        P = torch.stack(
            (torch.stack((wp, zc), 2), torch.stack((zc, wq), 2), torch.stack((0.5 * wq, 0.5 * wp), 2)), 1
        ).reshape(-1, 3, 6)
        return r.mT, L, al6, al, P

    def membrane(self, inputs: SubstepInputs) -> _PlanMembrane:
        """The stretch and bend passes of `reference.xpbd_substeps` for one call with ``inputs`` (whose
        topology and colouring are the plan's model's), batched per colour."""
        data = self.frame_data(
            inputs.stretch.tri_rest_inv,
            inputs.stretch.tri_compliance,
            inputs.bend.edge_rest_angle,
            inputs.bend.edge_compliance,
            inputs.vert_inv_mass,
            inputs.params.dt,
        )
        return _PlanMembrane(self, data)

    def frame(
        self,
        x: torch.Tensor,
        v: torch.Tensor,
        rest,
        dt: float,
        *,
        contacts: Contacts | None = None,
        body_verts: torch.Tensor | None = None,
        body_faces: torch.Tensor | None = None,
        velocity_scale: float = 1.0,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One frame of `XPBDSolver.advance` (drape phase), differentiable in every tensor argument.

        Args:
            x, v: (Vs, 3) state at the frame start [m], [m/s].
            rest: `RestData` (its tensors may require grad; its material gives damping, friction and
                thickness).
            dt: frame time [s]; contacts: the frame's contact set or None; body_verts: (Vb, 3) [m];
            body_faces: (Fb, 3) int64; velocity_scale: factor on v at the end of the frame.

        Returns:
            (x, v) at the frame end, (Vs, 3) each.
        """
        inputs = substep_inputs(
            self.model, rest, self.xpbd, dt, contacts=contacts, body_verts=body_verts, body_faces=body_faces
        )
        x, v = reference.xpbd_substeps(x, v, inputs, self.membrane(inputs))
        return x, (v * velocity_scale if velocity_scale != 1.0 else v)

    # ---------------------------------------------------------------------------------- one colour

    def _stretch(self, x, c: _TriColour, td, lam):
        rt, L, al6, al, P = td
        xt = x[c.tri]  # (K, 3, 3) [corner, xyz]
        D = xt[:, :2] - xt[:, 2:]  # (K, 2, 3) rows x0 - x2, x1 - x2
        F = rt @ D  # (K, 2, 3) rows f0, f1
        s3 = (F @ F.mT).reshape(-1, 4)[:, self._s3]  # (K, 3) f0.f0, f1.f1, f0.f1
        A = (s3[:, None, :] @ L).squeeze(1) + al6  # (K, 6) symmetric system
        rhs = 0.5 * s3
        rhs = rhs - rhs.new_tensor([0.5, 0.5, 0.0])  # C = [E00, E11, E01]
        if lam is not None:
            rhs = rhs + (al @ lam[:, :, None]).squeeze(-1)
        m = A[:, self._adj].reshape(-1, 4, 6)
        cof = m[:, 0] * m[:, 1] - m[:, 2] * m[:, 3]  # (K, 6)
        det = (A[:, :3] * cof[:, :3]).sum(-1, keepdim=True)
        dlam = -(cof[:, self._sym9].reshape(-1, 3, 3) @ rhs[:, :, None]).squeeze(-1) / det  # (K, 3)
        dx = (dlam[:, None, :] @ P).reshape(-1, 3, 2) @ F  # (K, 3 corners, 3)
        x = x.index_add(0, c.flat, dx.reshape(-1, 3))
        return x, (dlam if lam is None else lam + dlam)

    def _bend(self, x, c: _EdgeColour, ed, lam):
        wq, rest, alpha_t = ed
        xq = x[c.quads]  # (K, 4, 3)
        x0, x1, x2, x3 = xq.unbind(1)
        e = x1 - x0
        n = torch.stack((torch.linalg.cross(e, x2 - x0), torch.linalg.cross(x3 - x1, e)), 1)  # (K, 2, 3)
        gram = (n @ n.mT).reshape(-1, 4)  # |n1|², n1.n2, n1.n2, |n2|²
        e_len = e.norm(dim=-1)
        with torch.no_grad():
            ok = (e_len >= reference._BEND_EPS_LEN) & (gram[:, 0] >= reference._BEND_EPS_N2)
            ok &= gram[:, 3] >= reference._BEND_EPS_N2
            all_ok = bool(ok.all())
        if not all_ok:  # degenerate quads are skipped: safe denominators, zero correction
            one = torch.ones_like(e_len)
            e_len = torch.where(ok, e_len, one)
            gram = torch.where(ok[:, None], gram, torch.ones_like(gram))
        el = e_len[:, None]
        n1, n2 = n.unbind(1)
        theta = torch.atan2((torch.linalg.cross(n1, n2) * e).sum(-1) / e_len, gram[:, 1])
        m = n / gram[:, [0, 3], None]  # (K, 2, 3) n1/|n1|², n2/|n2|²
        t = ((xq[:, 2:] - x0[:, None]) @ e[:, :, None]).mT / el[:, :, None]  # (K, 1, 2) (x2-x0).ê, (x3-x0).ê
        g1 = t @ m  # (K, 1, 3) dθ/dx1 = ((x2-x0).ê) n1/|n1|² + ((x3-x0).ê) n2/|n2|²
        g23 = -el[:, :, None] * m  # (K, 2, 3) dθ/dx2, dθ/dx3
        grad = torch.cat((-(g1 + g23.sum(1, keepdim=True)), g1, g23), 1)  # dθ/dx0: the four sum to 0
        denom = (wq * (grad * grad).sum(-1)).sum(-1) + alpha_t
        rhs = theta - rest
        if lam is not None:
            rhs = rhs + alpha_t * lam
        if all_ok and bool((denom > 0).all()):
            dlam = -rhs / denom
        else:
            ok = ok & (denom > 0)
            safe = torch.where(ok, denom, torch.ones_like(denom))
            dlam = torch.where(ok, -rhs / safe, torch.zeros_like(rhs))
        dx = (wq * dlam[:, None])[:, :, None] * grad
        x = x.index_add(0, c.flat, dx.reshape(-1, 3))
        return x, (dlam if lam is None else lam + dlam)
