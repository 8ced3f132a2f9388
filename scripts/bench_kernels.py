"""Time the simulator kernels: C++ ops (`torch.ops.diffavatar.*`) against their PyTorch twins.

Projections: one pass of each op on a perturbed 64 x 64 sheet (4,096 vertices, 7,938 triangles,
11,781 interior edges), float32, greedy colouring from `sim.coloring`. Query: `closest_point_on_mesh`
of 5k and 20k points scattered (sigma 2 cm) around the default Anny body (26,692 triangles),
max_dist 3 cm; the 1-point row is the C++ grid build alone. Threads 1 and 2 (`torch.set_num_threads`).

Usage (build the extension first: `python setup.py build_ext --inplace`):

    PYTHONPATH=/work/main python scripts/bench_kernels.py [--repeats 20] [--no-body]

Reference for the per-substep budget: Newton's XPBD takes about 1.0 ms per substep at 4,096 vertices
(edge springs, 1 iteration, single-threaded; /work/shared/notes/warp-newton.md).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from torch_diffavatar._ext import has_extension
from torch_diffavatar.sim import reference
from torch_diffavatar.sim.coloring import greedy_coloring


def _sheet(n: int, dtype: torch.dtype, seed: int = 0):
    """A perturbed n x n sheet: rest uv (V, 2) [m], positions x (V, 3) [m], faces (F, 3) int64."""
    gen = torch.Generator().manual_seed(seed)
    g = torch.linspace(0.0, 1.0, n, dtype=torch.float64)
    uu, vv = torch.meshgrid(g, g, indexing="ij")
    uv = torch.stack((uu.reshape(-1), vv.reshape(-1)), dim=-1)
    idx = torch.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = torch.cat((torch.stack((a, c, d), -1).reshape(-1, 3), torch.stack((a, d, b), -1).reshape(-1, 3)))
    x = torch.cat((uv * 1.02, 0.05 * torch.sin(6.0 * uv[:, :1])), dim=-1)
    x = x + 0.1 / (n - 1) * torch.randn(x.shape, generator=gen, dtype=torch.float64)
    return uv, x.to(dtype), faces


def _edge_quads(faces: torch.Tensor) -> torch.Tensor:
    """(E, 4) int64 (v0, v1, v2, v3) of the interior edges of a consistently oriented triangle mesh."""
    opposite = {}
    for p, q, r in faces.tolist():
        opposite[(p, q)] = r
        opposite[(q, r)] = p
        opposite[(r, p)] = q
    quads = [(a, b, c, opposite[(b, a)]) for (a, b), c in opposite.items() if a < b and (b, a) in opposite]
    return torch.tensor(quads, dtype=torch.int64)


def _projection_problems(n: int, dtype: torch.dtype, dt: float = 1.0 / 240.0):
    """{op name: argument list} for the four projection ops on an n x n sheet."""
    uv, x, faces = _sheet(n, dtype)
    vert_count, tri_count = x.shape[0], faces.shape[0]
    w = torch.full((vert_count,), float(vert_count), dtype=dtype)  # 1 kg of cloth [1/kg]
    w[:n] = 0.0  # pin one border
    rest = uv[faces]
    rest_inv = torch.linalg.inv(torch.stack((rest[:, 0] - rest[:, 2], rest[:, 1] - rest[:, 2]), -1))
    compliance = (1e-6 * torch.eye(3, dtype=torch.float64)).expand(tri_count, 3, 3)
    quads = _edge_quads(faces)
    tri_col, quad_col = greedy_coloring(faces), greedy_coloring(quads)
    stretch = [
        x,
        torch.zeros(tri_count, 3, dtype=dtype),
        w,
        faces,
        rest_inv.to(dtype).contiguous(),
        compliance.to(dtype).contiguous(),
    ]
    bend = [
        x,
        torch.zeros(quads.shape[0], dtype=dtype),
        w,
        quads,
        torch.zeros(quads.shape[0], dtype=dtype),
        torch.full((quads.shape[0],), 1e-2, dtype=dtype),
    ]
    return {
        "stretch_project_": [*stretch, tri_col.order, tri_col.color_offsets, dt],
        "stretch_project_jacobi_": [*stretch, dt, 0.8],
        "bend_project_": [*bend, quad_col.order, quad_col.color_offsets, dt],
        "bend_project_jacobi_": [*bend, dt, 0.8],
    }, (vert_count, tri_count, quads.shape[0], tri_col.color_count, quad_col.color_count)


def _time_ms(fn, repeats: int) -> tuple[float, float]:
    """(median, min) wall time of fn() [ms] over `repeats` calls after one warm-up.

    The min is the better estimate on a shared machine (other processes only ever add time)."""
    fn()
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(samples), 1e3 * min(samples)


def _projection_rows(repeats: int, threads: list[int]):
    problems, sizes = _projection_problems(64, torch.float32)
    print(
        f"sheet 64x64, float32: {sizes[0]} vertices, {sizes[1]} triangles ({sizes[3]} colours), "
        f"{sizes[2]} bend edges ({sizes[4]} colours)"
    )
    rows = []
    for name, args in problems.items():
        cpp = getattr(torch.ops.diffavatar, name)
        ref = getattr(reference, name)
        for t in threads:
            torch.set_num_threads(t)
            for impl, fn in (("C++", cpp), ("reference", ref)):
                x, lam, rest = args[0].clone(), args[1].clone(), args[2:]
                ms = _time_ms(lambda fn=fn, x=x, lam=lam, rest=rest: fn(x, lam, *rest), repeats)
                rows.append((name, "pass", impl, t, *ms))
    return rows


def _query_rows(repeats: int, threads: list[int], with_reference: bool):
    from torch_diffavatar.body.anny_model import default_body_mesh

    verts, faces = default_body_mesh(dtype=torch.float32)
    gen = torch.Generator().manual_seed(0)
    rows = []
    max_dist = 0.03
    query = torch.ops.diffavatar.closest_point_on_mesh
    for count in (1, 5_000, 20_000):
        points = verts[torch.randint(0, verts.shape[0], (count,), generator=gen)]
        points = (points + 0.02 * torch.randn(points.shape, generator=gen)).contiguous()
        for t in threads:
            torch.set_num_threads(t)
            ms = _time_ms(lambda p=points: query(p, verts, faces, max_dist), repeats)
            rows.append(("closest_point_on_mesh", f"{count} pts", "C++", t, *ms))
            if with_reference and count == 5_000:
                ms = _time_ms(lambda p=points: reference.closest_point_on_mesh(p, verts, faces, max_dist), 2)
                rows.append(("closest_point_on_mesh", f"{count} pts", "reference", t, *ms))
        hit = query(points, verts, faces, max_dist)[0] >= 0
        print(f"query {count} points: {hit.float().mean().item():.0%} within {max_dist} m of the body")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20, help="timed calls per row (median reported)")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="torch.set_num_threads values")
    parser.add_argument("--no-body", action="store_true", help="skip the closest-point query on Anny")
    parser.add_argument("--no-query-reference", action="store_true", help="skip the slow brute-force query")
    args = parser.parse_args()
    if not has_extension():
        raise SystemExit("the C++ extension is not built: python setup.py build_ext --inplace")
    previous = torch.get_num_threads()
    try:
        rows = _projection_rows(args.repeats, args.threads)
        if not args.no_body:
            rows += _query_rows(args.repeats, args.threads, not args.no_query_reference)
    finally:
        torch.set_num_threads(previous)
    print(f"\n{'op':<26}{'case':<12}{'impl':<11}{'threads':>8}{'median ms':>11}{'min ms':>11}")
    for name, case, impl, t, median, best in rows:
        print(f"{name:<26}{case:<12}{impl:<11}{t:>8}{median:>11.3f}{best:>11.3f}")


if __name__ == "__main__":
    main()
