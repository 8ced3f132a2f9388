"""Small synthetic garments for tests and benchmarks: a rectangular sheet and a two-panel stitched tube;
and the harness of the drapes' gradchecks (`drape_of`, `drape_gradcheck`).

The garments are real `GarmentMesh` objects (regular grid triangulation), so they exercise the same code
path as meshed sewing patterns without needing the pattern mesher.
"""

from __future__ import annotations

import torch

from torch_diffavatar.geometry import merge_pairs
from torch_diffavatar.pattern.garment_mesh import BoundaryLoop, GarmentMesh


def _grid(nx: int, ny: int, width: float, height: float):
    """Vertices (nx*ny, 2) uv [m] (index i + nx*j) and CCW (in uv) triangles (2(nx-1)(ny-1), 3)."""
    if nx < 2 or ny < 2:
        raise ValueError(f"a grid needs at least 2x2 vertices, got {nx}x{ny}")
    u = torch.linspace(0.0, width, nx, dtype=torch.float64)
    v = torch.linspace(0.0, height, ny, dtype=torch.float64)
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    uv = torch.stack((uu.reshape(-1), vv.reshape(-1)), dim=1)
    i, j = torch.meshgrid(torch.arange(nx - 1), torch.arange(ny - 1), indexing="xy")
    a = (i + nx * j).reshape(-1)
    b, c, d = a + 1, a + nx, a + nx + 1
    # alternate the diagonal so the mesh has no preferred shear direction
    flip = ((i + j) % 2 == 1).reshape(-1)
    t1 = torch.where(flip[:, None], torch.stack((a, b, c), 1), torch.stack((a, b, d), 1))
    t2 = torch.where(flip[:, None], torch.stack((b, d, c), 1), torch.stack((a, d, c), 1))
    return uv, torch.cat((t1, t2))


def _merge(n: int, pairs: torch.Tensor):
    """Stitched pairs -> (vert_to_sim (n,), sim_count)."""
    labels, count = merge_pairs(n, pairs.numpy())
    return torch.from_numpy(labels), count


def rectangle_garment(
    nx: int = 9,
    ny: int = 9,
    width: float = 1.0,
    height: float = 1.0,
    origin=(0.0, 0.0, 0.0),
    axis_u=(1.0, 0.0, 0.0),
    axis_v=(0.0, 0.0, -1.0),
) -> GarmentMesh:
    """A single-panel rectangular sheet, triangulated on a regular ``nx`` × ``ny`` vertex grid.

    Args:
        width, height: rest size along u and v [m].
        origin: 3D position [m] of uv (0, 0); axis_u, axis_v: unit 3D directions of u and v (default a
            horizontal sheet in the XZ plane whose normal ``axis_u × axis_v`` points up, +Y).

    Vertex ``i + nx*j`` sits at uv ``(i·width/(nx−1), j·height/(ny−1))``. The ``"top"`` label holds the
    row v = height.
    """
    uv, tri = _grid(nx, ny, width, height)
    o, au, av = (torch.tensor(t, dtype=torch.float64) for t in (origin, axis_u, axis_v))
    pos = o + uv[:, :1] * au + uv[:, 1:] * av
    n = uv.shape[0]
    ring = torch.cat(
        (
            torch.arange(nx),
            torch.arange(1, ny) * nx + nx - 1,
            (ny - 1) * nx + torch.arange(nx - 2, -1, -1),
            torch.arange(ny - 2, 0, -1) * nx,
        )
    )
    return GarmentMesh(
        panel_names=["sheet"],
        vert_uv=uv,
        vert_panel=torch.zeros(n, dtype=torch.int64),
        vert_pos=pos,
        tri_vertices=tri,
        stitch_pairs=torch.zeros(0, 2, dtype=torch.int64),
        vert_to_sim=torch.arange(n),
        sim_vert_count=n,
        boundary_loops=[BoundaryLoop("opening_0", ring)],
        panel_boundary=[ring],
        vert_labels={"top": (ny - 1) * nx + torch.arange(nx)},
        garment_type=None,
        spacing=width / (nx - 1),
    )


def tube_garment(
    nx: int = 9, ny: int = 9, width: float = 0.4, height: float = 0.4, gap: float = 0.1, y0: float = 0.0
) -> GarmentMesh:
    """Two flat rectangular panels (front at z = +gap/2, back at z = −gap/2) stitched along both sides.

    The seams start open (``gap`` apart); sewing closes them into a flattened tube whose normals point
    outward. The top rows are labelled ``"lower_interface"`` (an unstitched waist, like a skirt's).

    Args:
        nx, ny: grid vertices per panel; width, height: panel size [m]; gap: initial distance of the
            panels [m]; y0: height of the panels' bottom row [m].
    """
    uv, tri = _grid(nx, ny, width, height)
    n = uv.shape[0]
    front = torch.stack((uv[:, 0] - width / 2, uv[:, 1] + y0, torch.full((n,), gap / 2, dtype=uv.dtype)), 1)
    back = torch.stack((width / 2 - uv[:, 0], uv[:, 1] + y0, torch.full((n,), -gap / 2, dtype=uv.dtype)), 1)
    rows = torch.arange(ny) * nx
    left_f, right_f = rows, rows + nx - 1
    left_b, right_b = rows + n, rows + nx - 1 + n  # back u=0 is at x=+w/2, u=w at x=-w/2
    stitches = torch.cat((torch.stack((left_f, right_b), 1), torch.stack((right_f, left_b), 1)))
    v2s, n_sim = _merge(2 * n, stitches)
    top = (ny - 1) * nx + torch.arange(nx)
    bottom = torch.arange(nx)
    return GarmentMesh(
        panel_names=["front", "back"],
        vert_uv=torch.cat((uv, uv)),
        vert_panel=torch.cat((torch.zeros(n, dtype=torch.int64), torch.ones(n, dtype=torch.int64))),
        vert_pos=torch.cat((front, back)),
        tri_vertices=torch.cat((tri, tri + n)),
        stitch_pairs=stitches,
        vert_to_sim=v2s,
        sim_vert_count=n_sim,
        boundary_loops=[
            BoundaryLoop("waist", torch.unique(v2s[torch.cat((top, top + n))])),
            BoundaryLoop("hem", torch.unique(v2s[torch.cat((bottom, bottom + n))])),
        ],
        vert_labels={"lower_interface": torch.cat((top, top + n))},
        garment_type="skirt",
        spacing=width / (nx - 1),
    )


def drape_of(group: str, nominal: dict, model, material, body_faces, **drape_kwargs):
    """(f, t0) for a gradcheck of `sim.differentiable.drape` in one input: ``f(t)`` drapes ``model`` with
    ``nominal``'s ``"rest_uv"`` (V, 2) [m] and ``"body"`` (Vb, 3) [m], ``group`` (one of the two) replaced by
    ``t``; ``t0`` is a leaf copy of ``nominal[group]`` that requires grad. ``drape_kwargs`` go to `drape`."""
    from torch_diffavatar.sim.differentiable import drape

    def f(t):
        v = dict(nominal, **{group: t})
        return drape(v["rest_uv"], model, v["body"], material, body_faces=body_faces, **drape_kwargs)

    return f, nominal[group].clone().requires_grad_(True)


def drape_gradcheck(f, t: torch.Tensor) -> bool:
    """`torch.autograd.gradcheck` of ``f`` at ``t`` (float64) with the tolerances of the drapes' tests."""
    return torch.autograd.gradcheck(f, (t,), eps=1e-6, atol=1e-7, rtol=1e-4, fast_mode=True)
