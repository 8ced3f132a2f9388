"""The one place that picks a simulator kernel: the C++ op when available, else the PyTorch twin.

``torch.ops.diffavatar.<name>`` is used when the extension is built (`torch_diffavatar._ext.has_extension`),
registers an op of that name, and the tensors are on the CPU; otherwise `torch_diffavatar.sim.reference`.
Both follow the contract documented in `torch_diffavatar.sim.reference` (in-place ops return ``None``).
Pass ``use_extension=False`` to force the reference (the tests and benchmarks compare the two).
"""

from __future__ import annotations

import torch

from torch_diffavatar import geometry
from torch_diffavatar._ext import has_extension
from torch_diffavatar.sim import reference
from torch_diffavatar.sim.substep import SubstepInputs

__all__ = [
    "bend_hessians",
    "bend_project_",
    "bend_project_jacobi_",
    "block_cholesky_analyze",
    "block_cholesky_apply",
    "block_cholesky_factor",
    "block_cholesky_solve",
    "closest_point_index",
    "closest_point_index_available",
    "closest_point_on_mesh",
    "closest_point_query",
    "closest_point_candidates",
    "closest_point_among",
    "contact_cache_query_",
    "contact_outermost",
    "extension_op",
    "max_abs_green_strain",
    "stretch_hessians",
    "stretch_project_",
    "stretch_project_jacobi_",
    "xpbd_substeps_",
]

_FAKES_REGISTERED: set[str] = set()


def extension_op(name: str):
    """The compiled op ``torch.ops.diffavatar.<name>``, or None when the extension or the op is missing."""
    if not has_extension():
        return None
    namespace = torch.ops.diffavatar
    if not hasattr(namespace, name):
        return None
    _register_fake(name)
    return getattr(namespace, name)


def _register_fake(name: str) -> None:
    """Shape-only (fake) kernels so `torch.compile` and `torch.library.opcheck` can trace the ops."""
    if name in _FAKES_REGISTERED:
        return
    _FAKES_REGISTERED.add(name)

    def fake_inplace(*args):
        return None

    def fake_closest(points, verts, faces, max_dist):
        n = points.shape[0]
        return (
            points.new_empty((n,), dtype=torch.int64),
            points.new_empty((n, 3)),
            points.new_empty((n,)),
        )

    def fake_scalar(x, *args):
        return x.new_empty(())

    def fake_stretch_hessians(x, tri_vertices, *args):
        return x.new_empty((tri_vertices.shape[0], 9, 9))

    def fake_bend_hessians(x, edge_quads, *args):
        return x.new_empty((edge_quads.shape[0], 12, 12))

    def fake_analyze(crow, col, perm):
        return perm.new_empty(perm.shape), perm.new_empty((perm.shape[0] + 1,))

    def fake_cholesky_solve(crow, col, val, b, *args):
        return torch.empty_like(b), b.new_empty((4,), dtype=torch.float64)

    def fake_cholesky_factor(crow, col, val, perm, parent, l_colptr):
        nnzl = torch.library.get_ctx().new_dynamic_size()  # l_colptr[-1]: data, not shape
        return (
            perm.new_empty((nnzl,)),
            val.new_empty((nnzl, 9), dtype=torch.float64),
            val.new_empty((4,), dtype=torch.float64),
        )

    def fake_cholesky_apply(l_row, l_val, perm, l_colptr, b):
        return torch.empty_like(b)

    def fake_value_grad(uv, *args):
        return uv.new_empty(()), torch.empty_like(uv)

    fake = {
        "closest_point_on_mesh": fake_closest,
        "max_abs_green_strain": fake_scalar,
        "stretch_hessians": fake_stretch_hessians,
        "bend_hessians": fake_bend_hessians,
        "block_cholesky_analyze": fake_analyze,
        "block_cholesky_solve": fake_cholesky_solve,
        "block_cholesky_factor": fake_cholesky_factor,
        "block_cholesky_apply": fake_cholesky_apply,
        "rest_seam_length": fake_value_grad,
        "rest_curvature": fake_value_grad,
        "rest_triangle_hinges": fake_value_grad,
        "rest_openings": fake_value_grad,
    }.get(name, fake_inplace)
    try:
        torch.library.register_fake(f"diffavatar::{name}")(fake)
    except RuntimeError:
        pass  # the extension already provides a fake/Meta kernel


def _pick(name: str, x: torch.Tensor, use_extension: bool):
    if use_extension and x.device.type == "cpu":
        op = extension_op(name)
        if op is not None:
            return op
    return getattr(reference, name)


def stretch_project_(
    x: torch.Tensor,
    lam: torch.Tensor,
    vert_inv_mass: torch.Tensor,
    tri_vertices: torch.Tensor,
    tri_rest_inv: torch.Tensor,
    tri_compliance: torch.Tensor,
    order: torch.Tensor,
    color_offsets: torch.Tensor,
    dt: float,
    *,
    use_extension: bool = True,
) -> None:
    """Colour-ordered Gauss–Seidel pass of the StVK stretch constraints (see `reference.stretch_project_`)."""
    _pick("stretch_project_", x, use_extension)(
        x, lam, vert_inv_mass, tri_vertices, tri_rest_inv, tri_compliance, order, color_offsets, float(dt)
    )


def stretch_project_jacobi_(
    x: torch.Tensor,
    lam: torch.Tensor,
    vert_inv_mass: torch.Tensor,
    tri_vertices: torch.Tensor,
    tri_rest_inv: torch.Tensor,
    tri_compliance: torch.Tensor,
    dt: float,
    omega: float,
    *,
    use_extension: bool = True,
) -> None:
    """Jacobi pass of the stretch constraints (see `reference.stretch_project_jacobi_`)."""
    _pick("stretch_project_jacobi_", x, use_extension)(
        x, lam, vert_inv_mass, tri_vertices, tri_rest_inv, tri_compliance, float(dt), float(omega)
    )


def bend_project_(
    x: torch.Tensor,
    lam: torch.Tensor,
    vert_inv_mass: torch.Tensor,
    edge_quads: torch.Tensor,
    edge_rest_angle: torch.Tensor,
    edge_compliance: torch.Tensor,
    order: torch.Tensor,
    color_offsets: torch.Tensor,
    dt: float,
    *,
    use_extension: bool = True,
) -> None:
    """Colour-ordered Gauss–Seidel pass of the bending constraints (see `reference.bend_project_`)."""
    _pick("bend_project_", x, use_extension)(
        x, lam, vert_inv_mass, edge_quads, edge_rest_angle, edge_compliance, order, color_offsets, float(dt)
    )


def bend_project_jacobi_(
    x: torch.Tensor,
    lam: torch.Tensor,
    vert_inv_mass: torch.Tensor,
    edge_quads: torch.Tensor,
    edge_rest_angle: torch.Tensor,
    edge_compliance: torch.Tensor,
    dt: float,
    omega: float,
    *,
    use_extension: bool = True,
) -> None:
    """Jacobi pass of the bending constraints (see `reference.bend_project_jacobi_`)."""
    _pick("bend_project_jacobi_", x, use_extension)(
        x, lam, vert_inv_mass, edge_quads, edge_rest_angle, edge_compliance, float(dt), float(omega)
    )


def closest_point_on_mesh(
    points: torch.Tensor,
    verts: torch.Tensor,
    faces: torch.Tensor,
    max_dist: float,
    *,
    use_extension: bool = True,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Closest triangle, barycentrics and distance per point: `geometry.closest_point_on_mesh`, the one
    place that picks between the op and its twin for this query (body fit and losses call it too).

    Returns:
        tri (N,) int64 (-1 when farther than ``max_dist``), bary (N, 3), dist (N,) [m] (inf when -1).
    """
    if use_extension:
        extension_op("closest_point_on_mesh")  # registers its fake kernel, as for every op picked here
    return geometry.closest_point_on_mesh(points, verts, faces, max_dist, use_extension=use_extension)


def _index_op(name: str):
    """``closest_point_index`` / ``closest_point_query`` / ``closest_point_query_hinted`` with their fake
    kernels (None without the op)."""
    if has_extension() and hasattr(torch.ops.diffavatar, name) and name not in _FAKES_REGISTERED:
        _FAKES_REGISTERED.add(name)  # registered here, before `extension_op` would register a default

        def fake_index(verts, faces, cell_size):
            ctx = torch.library.get_ctx()
            return (
                verts.new_empty((11,), dtype=torch.float64),
                verts.new_empty((ctx.new_dynamic_size(),), dtype=torch.int64),
                verts.new_empty((ctx.new_dynamic_size(), 7), dtype=torch.int32),
            )

        def fake_query(points, verts, faces, header, cell_start, cell_items, *hint_and_max_dist):
            n = points.shape[0]
            return (
                points.new_empty((n,), dtype=torch.int64),
                points.new_empty((n, 3)),
                points.new_empty((n,)),
            )

        def fake_candidates(points, verts, faces, header, cell_start, cell_items, radius):
            ctx = torch.library.get_ctx()
            return points.new_empty((points.shape[0], ctx.new_dynamic_size()), dtype=torch.int64)

        def fake_among(points, verts, faces, cand, max_dist):
            return fake_query(points, verts, faces, None, None, None, max_dist)

        def fake_cache(points, *args):
            return fake_query(points, None, None, None, None, None, 0.0)[:2] + (
                points.new_empty((3,), dtype=torch.int64),
            )

        def fake_outermost(points, verts, faces, across, ring, tri, bary):
            return torch.empty_like(tri), torch.empty_like(bary)

        fakes = {
            "closest_point_index": fake_index,
            "closest_point_candidates": fake_candidates,
            "closest_point_among": fake_among,
            "contact_cache_query_": fake_cache,
            "contact_outermost": fake_outermost,
        }
        fake = fakes.get(name, fake_query)
        try:
            torch.library.register_fake(f"diffavatar::{name}")(fake)
        except RuntimeError:
            pass  # the extension already provides a fake/Meta kernel
    return extension_op(name)


def _pick_index(name: str, x: torch.Tensor, use_extension: bool):
    """`_pick` for the ops whose fake kernels `_index_op` registers."""
    op = _index_op(name) if use_extension and x.device.type == "cpu" else None
    return op if op is not None else getattr(reference, name)


def closest_point_index_available(device: torch.device, use_extension: bool = True) -> bool:
    """Whether `closest_point_index` / `closest_point_query` can run (C++ only; CPU tensors)."""
    return (
        use_extension and torch.device(device).type == "cpu" and _index_op("closest_point_query") is not None
    )


def closest_point_index(
    verts: torch.Tensor, faces: torch.Tensor, cell_size: float = 0.0
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The uniform grid `closest_point_on_mesh` builds per call, built once (C++ only, no autograd).

    Args:
        verts: (Vb, 3) float32/float64 [m]; faces: (Fb, 3) int64.
        cell_size: grid cell edge [m]; <= 0 picks the mean triangle size (what `closest_point_on_mesh`
            uses). The cell size changes the speed, never the result.

    Returns:
        header (11,) float64, cell_start (cells + 1,) int64, cell_items (M, 7) int32: pass them, with the
        same ``verts`` and ``faces``, to `closest_point_query`.
    """
    op = _index_op("closest_point_index")
    if op is None:
        raise RuntimeError("closest_point_index needs the C++ extension")
    return op(verts, faces, float(cell_size))


def closest_point_query(
    points: torch.Tensor,
    verts: torch.Tensor,
    faces: torch.Tensor,
    grid: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    max_dist: float,
    hint: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """`closest_point_on_mesh` on a prebuilt ``grid`` = `closest_point_index` (verts, faces): the same
    (tri, bary, dist), bit for bit (C++ only).

    ``hint``: (N,) int64, a triangle per point that the search tests first (-1: none), e.g. the point's
    triangle of the last frame: a close one prunes the search from the start. The result does not depend
    on it (its PyTorch twin ignores it).
    """
    name = "closest_point_query" if hint is None else "closest_point_query_hinted"
    op = _index_op(name)
    if op is None:
        raise RuntimeError(f"{name} needs the C++ extension")
    if hint is None:
        return op(points, verts, faces, *grid, float(max_dist))
    return op(points, verts, faces, *grid, hint, float(max_dist))


def closest_point_candidates(
    points: torch.Tensor,
    verts: torch.Tensor,
    faces: torch.Tensor,
    grid: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    radius: torch.Tensor,
) -> torch.Tensor:
    """Every triangle within ``radius`` of each point, found on a prebuilt ``grid`` (C++ only; twin:
    `reference.closest_point_candidates`). The radii get the query's rounding slack (1e-6 relative plus
    1e-6 (1 + |p|) m), so that no triangle within the radius is ever missed.

    Args:
        points: (N, 3) [m]; verts, faces, grid: as `closest_point_query`; radius: (N,) float64 [m] (< 0:
            none).

    Returns:
        (N, K) int64 triangle ids, each row padded with -1 (K >= 1, in no particular order).
    """
    op = _index_op("closest_point_candidates")
    if op is None:
        raise RuntimeError("closest_point_candidates needs the C++ extension")
    return op(points, verts, faces, *grid, radius)


def closest_point_among(
    points: torch.Tensor,
    verts: torch.Tensor,
    faces: torch.Tensor,
    cand: torch.Tensor,
    max_dist: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(tri, bary, dist) as `closest_point_on_mesh`, but among each point's candidate triangles only:
    ``cand`` (N, K) int64, each row ending at its first -1 (C++ only; twin: `reference.closest_point_among`).
    The same distance test and tie-break (lowest id) as the grid query: when every triangle as close as the
    closest one is a candidate (`closest_point_candidates` within a large enough radius), the result is the
    grid query's, bit for bit."""
    op = _index_op("closest_point_among")
    if op is None:
        raise RuntimeError("closest_point_among needs the C++ extension")
    return op(points, verts, faces, cand, float(max_dist))


def contact_cache_query_(
    points: torch.Tensor,
    verts: torch.Tensor,
    faces: torch.Tensor,
    grid: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    state: tuple[torch.Tensor, ...],
    band: float,
    probe: float,
    margin: float,
    max_radius: float,
    *,
    use_extension: bool = True,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One frame of `collision.ContactCache` in one call (twin: `reference.contact_cache_query_`, which
    ignores the grid), in place on ``state`` = (last_x (N, 3) f64, lower (N,) f64, last_tri (N,) i64, cand_x
    (N, 3) f64, cand (N, K) i64).

    Returns:
        tri (N,) int64 and bary (N, 3), those of `closest_point_query` (points, band), bit for bit;
        counts (3,) int64: the points queried, of those the ones answered among their candidates, and
        the longest candidate list that did not fit in K (0: none; those points keep no candidates).
    """
    fn = _pick_index("contact_cache_query_", points, use_extension)
    limits = (float(band), float(probe), float(margin), float(max_radius))
    return fn(points, verts, faces, *grid, *state, *limits)


def contact_outermost(
    points: torch.Tensor,
    verts: torch.Tensor,
    faces: torch.Tensor,
    across: torch.Tensor,
    ring: torch.Tensor,
    tri: torch.Tensor,
    bary: torch.Tensor,
    *,
    use_extension: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Contact ties broken to the outermost face (`collision._FeatureFaces.outermost`; twin:
    `reference.contact_outermost`). points (C, 3), verts (Vb, 3) of the points' dtype, faces (Fb, 3), across
    (Fb, 3), ring (Vb, R) int64, tri (C,), bary (C, 3). Returns the new (tri, bary)."""
    fn = _pick_index("contact_outermost", points, use_extension)
    return fn(points, verts, faces, across, ring, tri, bary)


def xpbd_substeps_(
    x: torch.Tensor, v: torch.Tensor, inputs: SubstepInputs, *, use_extension: bool = True
) -> None:
    """XPBD substeps, in place on x and v (Vs, 3): the op (or `reference.xpbd_substeps_`) called with
    ``inputs.op_args()`` (`SubstepInputs` documents the arguments)."""
    _pick("xpbd_substeps_", x, use_extension)(x, v, *inputs.op_args())


def max_abs_green_strain(
    x: torch.Tensor, tri_vertices: torch.Tensor, tri_rest_inv: torch.Tensor, *, use_extension: bool = True
) -> torch.Tensor:
    """0-dim tensor: the largest |Green strain component| (see `reference.max_abs_green_strain`)."""
    return _pick("max_abs_green_strain", x, use_extension)(x, tri_vertices, tri_rest_inv)


def stretch_hessians(
    x: torch.Tensor,
    tri_vertices: torch.Tensor,
    tri_rest_inv: torch.Tensor,
    tri_area: torch.Tensor,
    stiffness: torch.Tensor,
    project: bool,
    *,
    use_extension: bool = True,
) -> torch.Tensor:
    """(F, 9, 9) membrane-energy Hessians per triangle, PSD-projected on request (see
    `reference.stretch_hessians`)."""
    return _pick("stretch_hessians", x, use_extension)(
        x, tri_vertices, tri_rest_inv, tri_area, stiffness, bool(project)
    )


def bend_hessians(
    x: torch.Tensor,
    edge_quads: torch.Tensor,
    edge_weight: torch.Tensor,
    edge_rest_angle: torch.Tensor,
    bend_stiffness: float,
    project: bool,
    *,
    use_extension: bool = True,
) -> torch.Tensor:
    """(E, 12, 12) bending-energy Hessians per interior edge, PSD-projected on request (see
    `reference.bend_hessians`)."""
    return _pick("bend_hessians", x, use_extension)(
        x, edge_quads, edge_weight, edge_rest_angle, float(bend_stiffness), bool(project)
    )


def block_cholesky_analyze(
    crow: torch.Tensor, col: torch.Tensor, perm: torch.Tensor, *, use_extension: bool = True
) -> tuple[torch.Tensor, torch.Tensor]:
    """Symbolic 3×3-block sparse Cholesky: (parent, l_colptr) (see `reference.block_cholesky_analyze`)."""
    return _pick("block_cholesky_analyze", crow, use_extension)(crow, col, perm)


def block_cholesky_solve(
    crow: torch.Tensor,
    col: torch.Tensor,
    val: torch.Tensor,
    b: torch.Tensor,
    perm: torch.Tensor,
    parent: torch.Tensor,
    l_colptr: torch.Tensor,
    *,
    use_extension: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Sparse Cholesky solve of the SPD ``H x = b``: (x, info) (see `reference.block_cholesky_solve`,
    whose dense twin is for small problems only)."""
    return _pick("block_cholesky_solve", b, use_extension)(crow, col, val, b, perm, parent, l_colptr)


def block_cholesky_factor(
    crow: torch.Tensor,
    col: torch.Tensor,
    val: torch.Tensor,
    perm: torch.Tensor,
    parent: torch.Tensor,
    l_colptr: torch.Tensor,
    *,
    use_extension: bool = True,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The numeric block Cholesky factor of the SPD ``H``: (l_row, l_val, info) (see
    `reference.block_cholesky_factor`), to solve with later (`block_cholesky_apply`)."""
    return _pick("block_cholesky_factor", val, use_extension)(crow, col, val, perm, parent, l_colptr)


def block_cholesky_apply(
    l_row: torch.Tensor,
    l_val: torch.Tensor,
    perm: torch.Tensor,
    l_colptr: torch.Tensor,
    b: torch.Tensor,
    *,
    use_extension: bool = True,
) -> torch.Tensor:
    """``H⁻¹ b`` (n,) with a `block_cholesky_factor` of H (see `reference.block_cholesky_apply`)."""
    return _pick("block_cholesky_apply", b, use_extension)(l_row, l_val, perm, l_colptr, b)
