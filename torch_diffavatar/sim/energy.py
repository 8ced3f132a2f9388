"""The drape energy ``U(x; θ)`` whose minimiser XPBD approximates, and its sparse Hessian.

``U = stretch + bend + gravity + stitches + attachments + active contacts`` (paper §3.2: XPBD's compliance
α is the inverse stiffness, ``U = ½ Cᵀ α⁻¹ C``). Stretch, bending and gravity reuse `sim/constraints.py`;
the zero-length stitches and the waist attachments are ``½ |C|²/α`` with the solver's compliances; an
active contact (vertex i frozen on body triangle t with barycentrics b) is the stiff quadratic
``½ k_c (s_i − thickness)²`` on its signed distance ``s_i = (x_i − p(b, body))·n(body)`` to the plane of
the triangle (the XPBD contact projection's constraint, `collision.signed_distance_along_normal`), so U
is a smooth function of x, rest_uv, the material and the body vertices.

`hessian_blocks` returns the per-element Hessian blocks (exact, or projected to PSD for Newton; closed
form in C++, `sim/reference.py` twins). `hessian_pattern` builds the CSR structure over the free degrees
of freedom once per model (the topology is fixed) with a scatter map per element kind, so assembling is
one ``index_add_`` per kind; `assemble_csr` is the general (slower) reference assembly of a block list.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field

import torch

from torch_diffavatar.sim import collision, constraints, ops
from torch_diffavatar.sim.collision import Contacts
from torch_diffavatar.sim.constraints import RestData
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.model import ClothModel


@dataclass(frozen=True)
class EnergyParams:
    """Constants of the drape energy that are not material fields.

    Attributes:
        gravity: (3,) gravitational acceleration [m/s²].
        stitch_compliance: zero-length stitch compliance [m/N].
        attach_compliance: waist attachment compliance [m/N].
        contact_stiffness: stiffness k_c of the active-contact quadratic [N/m].
    """

    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)
    stitch_compliance: float = 1e-5
    attach_compliance: float = 1e-5
    contact_stiffness: float = 1e4


def drape_energy(
    x: torch.Tensor,
    model: ClothModel,
    rest: RestData,
    material: ClothMaterial,
    params: EnergyParams,
    *,
    body_verts: torch.Tensor | None = None,
    body_faces: torch.Tensor | None = None,
    contacts: Contacts | None = None,
) -> torch.Tensor:
    """() total energy [J] at positions ``x`` (Vs, 3) [m] (differentiable in every tensor argument).

    Args:
        rest: ``model.rest_data(rest_uv, material)``; material: the same material.
        body_verts: (Vb, 3) [m]; body_faces: (Fb, 3) int64; contacts: the frozen active contact set.
    """
    u = constraints.stretch_energy(x, model.tri_vertices, rest, material)
    if model.edge_count:
        u = u + constraints.bend_energy(x, model.edge_quads, rest, material)
    u = u + constraints.gravity_energy(x, rest.vert_mass, x.new_tensor(params.gravity))
    if model.stitch_vertices.shape[0]:
        a, b = model.stitch_vertices[:, 0], model.stitch_vertices[:, 1]
        u = u + 0.5 / params.stitch_compliance * ((x[a] - x[b]) ** 2).sum()
    if model.attach_vertices.shape[0]:
        dy = x[model.attach_vertices, 1] - rest.attach_height
        u = u + 0.5 / params.attach_compliance * (dy**2).sum()
    if contacts is not None and contacts.count:
        s = collision.signed_distance_along_normal(x, body_verts, body_faces, contacts)
        u = u + 0.5 * params.contact_stiffness * ((s - material.thickness) ** 2).sum()
    return u


@dataclass(frozen=True)
class HessianBlocks:
    """Element Hessian blocks of `drape_energy` by kind (dofs ordered 3·element vertex + axis).

    Attributes:
        tri: (F, 9, 9) membrane blocks of ``model.tri_vertices``.
        edge: (E, 12, 12) bending blocks of ``model.edge_quads`` (None without interior edges).
        stitch: (S, 6, 6) stitch blocks of ``model.stitch_vertices`` (None without stitches).
        vert: [(ids (K,) int64, blocks (K, 3, 3))] single-vertex blocks (attachments, active contacts).
    """

    tri: torch.Tensor
    edge: torch.Tensor | None
    stitch: torch.Tensor | None
    vert: list[tuple[torch.Tensor, torch.Tensor]]

    def max_diagonal(self) -> float:
        """The largest |diagonal entry| over all element blocks (the scale of the diagonal shift)."""
        parts = [self.tri, self.edge, self.stitch] + [b for _, b in self.vert]
        parts = [b for b in parts if b is not None and b.numel()]
        return max(float(b.diagonal(dim1=1, dim2=2).abs().max()) for b in parts)


def hessian_blocks(
    x: torch.Tensor,
    model: ClothModel,
    rest: RestData,
    material: ClothMaterial,
    params: EnergyParams,
    *,
    body_verts: torch.Tensor | None = None,
    body_faces: torch.Tensor | None = None,
    contacts: Contacts | None = None,
    project: bool = False,
    dtype: torch.dtype | None = None,
    use_extension: bool = True,
) -> HessianBlocks:
    """Per-element Hessian blocks of `drape_energy` with respect to x (no autograd through them).

    Args:
        project: project the stretch and bending blocks to PSD (projected Newton, the fit's adjoint).
        dtype: compute in this dtype (default x's); the adjoint asks for float64.
        use_extension: closed-form C++ kernels (`ops.stretch_hessians`, `ops.bend_hessians`) when built,
            else their autograd twins in `sim/reference.py`.
    """
    dt = x.dtype if dtype is None else dtype
    x = x.detach().to(dt)
    k = constraints.membrane_stiffness(material, x).detach()
    h_tri = ops.stretch_hessians(
        x, model.tri_vertices, rest.tri_rest_inv.detach().to(dt).contiguous(), rest.tri_area.detach().to(dt),
        k, project, use_extension=use_extension,
    )  # fmt: skip
    h_edge = None
    if model.edge_count:
        h_edge = ops.bend_hessians(
            x, model.edge_quads, rest.edge_weight.detach().to(dt), rest.edge_rest_angle.detach().to(dt),
            float(torch.as_tensor(material.bend_stiffness).detach()), project, use_extension=use_extension,
        )  # fmt: skip
    eye = torch.eye(3, dtype=dt, device=x.device)
    h_stitch = None
    if model.stitch_vertices.shape[0]:
        blk = torch.cat((torch.cat((eye, -eye), 1), torch.cat((-eye, eye), 1)), 0) / params.stitch_compliance
        h_stitch = blk.expand(model.stitch_vertices.shape[0], 6, 6)
    vert = []
    if model.attach_vertices.shape[0]:
        blk = torch.zeros(3, 3, dtype=dt, device=x.device)
        blk[1, 1] = 1.0 / params.attach_compliance
        vert.append((model.attach_vertices, blk.expand(model.attach_vertices.shape[0], 3, 3)))
    if contacts is not None and contacts.count:
        _, n = collision.contact_frames(body_verts.detach().to(dt), body_faces, contacts)
        vert.append((contacts.vert, params.contact_stiffness * n[:, :, None] * n[:, None, :]))
    return HessianBlocks(h_tri, h_edge, h_stitch, vert)


def hessian_elements(
    x: torch.Tensor,
    model: ClothModel,
    rest: RestData,
    material: ClothMaterial,
    params: EnergyParams,
    *,
    body_verts: torch.Tensor | None = None,
    body_faces: torch.Tensor | None = None,
    contacts: Contacts | None = None,
    project: bool = False,
    use_extension: bool = True,
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """`hessian_blocks` as a list of (dofs (K, n) int64 global dof ids 3·vertex + axis, blocks (K, n, n)),
    the input of the reference assembly `assemble_csr`."""
    h = hessian_blocks(
        x, model, rest, material, params, body_verts=body_verts, body_faces=body_faces, contacts=contacts,
        project=project, use_extension=use_extension,
    )  # fmt: skip
    out = [(_dofs(model.tri_vertices), h.tri)]
    if h.edge is not None:
        out.append((_dofs(model.edge_quads), h.edge))
    if h.stitch is not None:
        out.append((_dofs(model.stitch_vertices), h.stitch))
    out += [(_dofs(ids[:, None]), b) for ids, b in h.vert]
    return out


def _dofs(verts: torch.Tensor) -> torch.Tensor:
    """(K, 3m) global dof ids of the (K, m) vertex ids."""
    return (3 * verts[:, :, None] + torch.arange(3, device=verts.device)).reshape(verts.shape[0], -1)


def assemble_csr(
    elements: list[tuple[torch.Tensor, torch.Tensor]], free_index: torch.Tensor, free_count: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Scatter element blocks into a CSR matrix over the free dofs (pinned dofs dropped).

    Args:
        elements: from `hessian_elements`.
        free_index: (3Vs,) int64 position of each dof among the free ones, −1 for pinned dofs.
        free_count: number of free dofs ``n``.

    Returns:
        crow (n+1,) int64, col (nnz,) int64, val (nnz,) — sorted columns, duplicates summed.
    """
    rows, cols, vals = [], [], []
    for dofs, blocks in elements:
        m = dofs.shape[1]
        r = free_index[dofs][:, :, None].expand(-1, m, m)
        c = free_index[dofs][:, None, :].expand(-1, m, m)
        keep = (r >= 0) & (c >= 0)
        rows.append(r[keep])
        cols.append(c[keep])
        vals.append(blocks[keep])
    r, c, v = torch.cat(rows), torch.cat(cols), torch.cat(vals)
    key = r * free_count + c
    uniq, inverse = torch.unique(key, return_inverse=True)
    val = v.new_zeros(uniq.shape[0]).index_add_(0, inverse, v)
    row, col = uniq // free_count, uniq % free_count
    crow = torch.zeros(free_count + 1, dtype=torch.int64, device=v.device)
    crow[1:] = torch.cumsum(torch.bincount(row, minlength=free_count), 0)
    return crow, col, val


@dataclass(eq=False)
class HessianPattern:
    """CSR structure of the drape energy's Hessian over the free dofs of one model, and scatter maps.

    The structure has 3×3 blocks: vertices coupled by a triangle, a bending quad or a stitch, plus every
    free vertex's diagonal block (rows 3v..3v+2 share one pattern of whole column triples), so the
    block sparse Cholesky of `adjoint.linsolve` can work on the vertex graph.

    Attributes:
        free_vert: (Vs,) bool the free (unpinned) vertices the rows belong to.
        crow: (n+1,) int64; col: (nnz,) int64 sorted per row; n = 3 × free vertices.
        tri_map, edge_map, stitch_map: (K·m²·9,) int64 position in ``val`` of every entry of the element
            blocks (K, 3m, 3m) of `HessianBlocks`, ``nnz`` (a discarded slot) for pinned dofs.
        vert_map: (Vs·9,) int64 the same for each vertex's diagonal 3×3 block.
        solver_cache: filled by `adjoint.linsolve.solve_symmetric` with its symbolic factorisation.
    """

    free_vert: torch.Tensor
    crow: torch.Tensor
    col: torch.Tensor
    tri_map: torch.Tensor
    edge_map: torch.Tensor
    stitch_map: torch.Tensor
    vert_map: torch.Tensor
    solver_cache: dict = field(default_factory=dict)

    @property
    def nnz(self) -> int:
        return int(self.col.shape[0])

    def assemble(self, blocks: HessianBlocks, diagonal_shift: float = 0.0) -> torch.Tensor:
        """(nnz,) float64 CSR values of Σ blocks + ``diagonal_shift`` · I (pinned dofs dropped)."""
        val = torch.zeros(self.nnz + 1, dtype=torch.float64, device=self.col.device)
        kinds = ((blocks.tri, self.tri_map), (blocks.edge, self.edge_map), (blocks.stitch, self.stitch_map))
        for blk, where in kinds:
            if blk is not None and blk.numel():
                val.index_add_(0, where, blk.reshape(-1).to(torch.float64))
        vb = torch.zeros(self.free_vert.shape[0], 3, 3, dtype=torch.float64, device=val.device)
        for ids, blk in blocks.vert:
            vb.index_add_(0, ids, blk.to(torch.float64))
        if diagonal_shift:
            vb += diagonal_shift * torch.eye(3, dtype=torch.float64, device=val.device)
        val.index_add_(0, self.vert_map, vb.reshape(-1))
        return val[: self.nnz]


# one pattern per live model (the topology is frozen in ClothModel); dropped with the model
_PATTERNS: dict[int, tuple[weakref.ref, HessianPattern]] = {}


def hessian_pattern(model: ClothModel, free_vert: torch.Tensor) -> HessianPattern:
    """The `HessianPattern` of ``model`` over the vertices ``free_vert`` (Vs,) bool, built on first use."""
    key = id(model)
    hit = _PATTERNS.get(key)
    if hit is not None and hit[0]() is model and torch.equal(hit[1].free_vert, free_vert):
        return hit[1]
    pattern = _build_pattern(model, free_vert)
    _PATTERNS[key] = (weakref.ref(model, lambda _ref, k=key: _PATTERNS.pop(k, None)), pattern)
    return pattern


def _build_pattern(model: ClothModel, free_vert: torch.Tensor) -> HessianPattern:
    dev = free_vert.device
    nv = model.vert_count
    nf = int(free_vert.sum())
    fv = torch.full((nv,), -1, dtype=torch.int64, device=dev)
    fv[free_vert] = torch.arange(nf, device=dev)
    verts = torch.arange(nv, device=dev)[:, None]
    keys = []
    for g in (model.tri_vertices, model.edge_quads, model.stitch_vertices, verts):
        r, c = fv[g][:, :, None], fv[g][:, None, :]
        ok = (r >= 0) & (c >= 0)
        keys.append((r * nf + c).expand(ok.shape)[ok])
    keys = torch.unique(torch.cat(keys))  # sorted (block row, block column) pairs
    brow, bcol = keys // nf, keys % nf
    bcrow = torch.zeros(nf + 1, dtype=torch.int64, device=dev)
    bcrow[1:] = torch.cumsum(torch.bincount(brow, minlength=nf), 0)
    deg = bcrow[1:] - bcrow[:-1]
    n = 3 * nf
    a3 = torch.arange(3, device=dev)
    crow = torch.empty(n + 1, dtype=torch.int64, device=dev)
    crow[:-1] = (9 * bcrow[:-1, None] + a3 * 3 * deg[:, None]).reshape(-1)
    crow[-1] = 9 * keys.shape[0]

    def block_pos(r, c):  # start of block (r, c) in its first row, and the row stride (r, c free)
        t = torch.searchsorted(keys, r * nf + c)
        return 9 * bcrow[r] + 3 * (t - bcrow[r]), 3 * deg[r]

    base, stride = block_pos(brow, bcol)
    entry = a3[:, None] * stride[:, None, None] + a3  # (nnzb, 3, 3) offsets of the 3x3 entries
    col = torch.empty(9 * keys.shape[0], dtype=torch.int64, device=dev)
    block_cols = (3 * bcol[:, None, None] + a3).expand(-1, 3, 3)
    col[(base[:, None, None] + entry).reshape(-1)] = block_cols.reshape(-1)
    nnz = col.shape[0]

    def element_map(g):
        r, c = fv[g][:, :, None], fv[g][:, None, :]  # (K, m, m) block rows and columns
        ok = (r >= 0) & (c >= 0)
        r, c = torch.where(ok, r, 0).expand(ok.shape), torch.where(ok, c, 0).expand(ok.shape)
        base, stride = block_pos(r, c)
        # (K, m, 3, m, 3): entry (axis a of vertex α, axis b of vertex β)
        out = base[:, :, None, :, None] + a3[:, None, None] * stride[:, :, None, :, None] + a3
        return torch.where(ok[:, :, None, :, None], out, nnz).reshape(-1)

    return HessianPattern(
        free_vert=free_vert.clone(),
        crow=crow,
        col=col,
        tri_map=element_map(model.tri_vertices),
        edge_map=element_map(model.edge_quads),
        stitch_map=element_map(model.stitch_vertices),
        vert_map=element_map(verts),
    )
