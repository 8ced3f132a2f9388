"""The arguments of one call of the fused XPBD substeps, by role: the op's argument list, written once.

The C++ op (csrc/xpbd_substeps.cpp, schema in csrc/registration.cpp) updates ``x`` and ``v`` in place::

    xpbd_substeps_(Tensor(a!) x, Tensor(b!) v, Tensor vert_inv_mass, Tensor[] stretch, Tensor[] bend,
                   Tensor[] seams, Tensor[] body, float[] coefficients, int substeps, int iterations,
                   bool jacobi, int num_threads) -> ()

Each tensor list holds the fields of one dataclass below in field order (`StretchInputs`, `BendInputs`,
`SeamInputs`, `BodyInputs`) and ``coefficients`` the float fields of `SubstepParams` in field order
(gravity expanded to its 3 components). `SubstepInputs.op_args` builds that argument list, and
`SubstepInputs.from_op_args` reads it back (the op's PyTorch twin, `reference.xpbd_substeps_`); the C++
op unpacks the same order and checks each list's length. Everything that calls the substeps (the solver,
`sim.ops`, the reference twin, the trajectory adjoint's replays) goes through `SubstepInputs`, built from a
model by `solver.substep_inputs`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch

from torch_diffavatar.sim.contacts import Contacts


@dataclass(frozen=True)
class StretchInputs:
    """The orthotropic StVK stretch constraints, one 3-vector block per triangle (`reference.stretch_project_`
    explains the fields).

    Attributes:
        tri_vertices: (F, 3) int64 sim-vertex ids.
        tri_rest_inv: (F, 2, 2) inverse rest edge matrices [1/m].
        tri_compliance: (F, 3, 3) compliances [1/(N·m)].
        tri_order: (F',) int64 triangle ids colour by colour (Gauss–Seidel).
        tri_color_offsets: (n_colors + 1,) int64 start of each colour in ``tri_order``.
    """

    tri_vertices: torch.Tensor
    tri_rest_inv: torch.Tensor
    tri_compliance: torch.Tensor
    tri_order: torch.Tensor
    tri_color_offsets: torch.Tensor


@dataclass(frozen=True)
class BendInputs:
    """The dihedral bending constraints, one per interior edge (`reference.bend_project_`).

    Attributes:
        edge_quads: (E, 4) int64 (v0, v1, v2, v3), v0–v1 the shared edge.
        edge_rest_angle: (E,) [rad]; edge_compliance: (E,) [1/(N·m)].
        edge_order: (E',) int64 edge ids colour by colour; edge_color_offsets: (n_colors + 1,) int64.
    """

    edge_quads: torch.Tensor
    edge_rest_angle: torch.Tensor
    edge_compliance: torch.Tensor
    edge_order: torch.Tensor
    edge_color_offsets: torch.Tensor


@dataclass(frozen=True)
class SeamInputs:
    """Stitches and waist attachments (`reference.stitch_project_`, `reference.attach_project_`).

    Attributes:
        stitch_vertices: (S, 2) int64 stitched vertex pairs.
        attach_vertices: (A,) int64 distinct attached vertices; attach_height: (A,) target heights y [m].
    """

    stitch_vertices: torch.Tensor
    attach_vertices: torch.Tensor
    attach_height: torch.Tensor


@dataclass(frozen=True)
class BodyInputs:
    """The body and this call's contact set (empty tensors without contacts).

    Attributes:
        body_verts: (Vb, 3) [m]; body_faces: (Fb, 3) int64 (outward normals).
        contact_vert: (C,) int64 distinct cloth vertices; contact_tri: (C,) int64 body faces;
        contact_bary: (C, 3) barycentric contact points on them.
    """

    body_verts: torch.Tensor
    body_faces: torch.Tensor
    contact_vert: torch.Tensor
    contact_tri: torch.Tensor
    contact_bary: torch.Tensor

    def contacts(self) -> Contacts | None:
        """The contact set as `Contacts`, or None when empty."""
        if self.contact_vert.numel() == 0:
            return None
        return Contacts(self.contact_vert, self.contact_tri, self.contact_bary)


@dataclass(frozen=True)
class SubstepParams:
    """The scalars of one call. The fields up to ``contact_bounce`` are the op's ``coefficients``.

    Attributes:
        gravity: (3,) gravitational acceleration [m/s²].
        velocity_decay: damping factor on v per substep [-].
        dt: substep [s].
        stitch_compliance: [m/N]; stitch_max_move: bound on a stitch pass's pull [m]; stitch_snap: gaps
            under this close without the bound [m] (`reference.stitch_project_`).
        attach_compliance: [m/N].
        thickness: cloth–body distance kept by the contacts [m]; friction: Coulomb coefficient μ [-].
        jacobi_omega: relaxation factor of the Jacobi scheme [-].
        contact_bounce: the share of its outward normal velocity that a vertex pushed out by a body contact
            in a substep keeps (1: all of the push, as a velocity; 0: none, an inelastic contact) [-].
        substeps, iterations: counts; jacobi: the Jacobi scheme instead of colour-ordered Gauss–Seidel;
        num_threads: OpenMP threads of the C++ op (0 = torch's setting; unused by the twin).
    """

    gravity: tuple[float, float, float]
    velocity_decay: float
    dt: float
    stitch_compliance: float
    stitch_max_move: float
    stitch_snap: float
    attach_compliance: float
    thickness: float
    friction: float
    jacobi_omega: float
    contact_bounce: float
    substeps: int
    iterations: int
    jacobi: bool
    num_threads: int

    def op_args(self) -> tuple:
        """(coefficients, substeps, iterations, jacobi, num_threads) as the op takes them."""
        coefficients = [float(g) for g in self.gravity]
        coefficients += [float(getattr(self, name)) for name in _COEFFICIENTS[1:]]
        return (
            coefficients,
            int(self.substeps),
            int(self.iterations),
            bool(self.jacobi),
            int(self.num_threads),
        )

    @classmethod
    def from_op_args(cls, coefficients, substeps, iterations, jacobi, num_threads) -> SubstepParams:
        if len(coefficients) != len(_COEFFICIENTS) + 2:
            raise ValueError(f"coefficients must hold {len(_COEFFICIENTS) + 2} floats {_COEFFICIENTS}")
        values = dict(zip(_COEFFICIENTS[1:], coefficients[3:]))
        return cls(tuple(coefficients[:3]), **values, substeps=substeps, iterations=iterations, jacobi=jacobi,
                   num_threads=num_threads)  # fmt: skip


_COUNTS = ("substeps", "iterations", "jacobi", "num_threads")
_COEFFICIENTS = tuple(f.name for f in dataclasses.fields(SubstepParams) if f.name not in _COUNTS)
_GROUPS = (StretchInputs, BendInputs, SeamInputs, BodyInputs)


@dataclass(frozen=True)
class SubstepInputs:
    """Everything one call of the substeps reads besides the state (x, v).

    The tensors may require grad: the out-of-place twin `reference.xpbd_substeps` is differentiable in
    all of them (the trajectory adjoint's replays); the in-place op runs under ``no_grad``.

    Attributes:
        vert_inv_mass: (Vs,) inverse masses [1/kg] (0 = pinned).
        stretch, bend, seams, body: the constraints and contacts by role; params: the scalars.
    """

    vert_inv_mass: torch.Tensor
    stretch: StretchInputs
    bend: BendInputs
    seams: SeamInputs
    body: BodyInputs
    params: SubstepParams

    def op_args(self) -> tuple:
        """The op's arguments after x and v: (vert_inv_mass, stretch, bend, seams, body, coefficients,
        substeps, iterations, jacobi, num_threads)."""
        groups = (self.stretch, self.bend, self.seams, self.body)
        lists = tuple([getattr(g, f.name) for f in dataclasses.fields(g)] for g in groups)
        return (self.vert_inv_mass, *lists, *self.params.op_args())

    @classmethod
    def from_op_args(
        cls,
        vert_inv_mass,
        stretch,
        bend,
        seams,
        body,
        coefficients,
        substeps,
        iterations,
        jacobi,
        num_threads,
    ) -> SubstepInputs:
        """The inverse of `op_args`."""
        groups = []
        for kind, tensors in zip(_GROUPS, (stretch, bend, seams, body)):
            names = [f.name for f in dataclasses.fields(kind)]
            if len(tensors) != len(names):
                raise ValueError(f"{kind.__name__} takes {len(names)} tensors {names}, got {len(tensors)}")
            groups.append(kind(*tensors))
        params = SubstepParams.from_op_args(coefficients, substeps, iterations, jacobi, num_threads)
        return cls(vert_inv_mass, *groups, params)
