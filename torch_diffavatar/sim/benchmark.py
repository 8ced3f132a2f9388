"""Timing of the XPBD step on the project's performance anchor (notes/warp-newton.md).

The anchor: a 64×64-vertex sheet (1 m × 1 m, 4,096 vertices, 7,938 triangles) falling from 0.5 m above
onto a sphere mesh (radius 0.3 m), 60 frames/s, 100 frames. Newton's XPBD at 40 substeps × 1 iteration
took ~1.0 ms per substep single-threaded (edge springs; 0.28% mean / 5.3% max edge strain at the end).
Run ``python -m torch_diffavatar.sim.benchmark`` (add ``--help``).

Every frame is timed separately, in wall time and in this process's CPU time; the medians over the
frames are reported (the machine is shared: the CPU time is the steadier number, the wall time shows
what the load did). Frame 0 (warm-up) is not timed.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from torch_diffavatar.json_io import dumps_json
from torch_diffavatar.sim import ops, reference
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.model import ClothModelBuilder
from torch_diffavatar.sim.solver import XPBDConfig, XPBDSolver
from torch_diffavatar.sim.testing import rectangle_garment


class _UnfusedSolver(XPBDSolver):
    """The solver's former path, for before/after timings: the per-constraint C++ kernels called once per
    substep and iteration from Python, with the contact, stitch, attachment and friction steps in torch
    (`reference.xpbd_substeps` with the `sim.ops` kernels as its membrane)."""

    def _substeps(self, x, v, inputs) -> None:
        xs, vs = reference.xpbd_substeps(x, v, inputs, reference.KernelMembrane(inputs, ops))
        x.copy_(xs)
        v.copy_(vs)


def sphere_mesh(radius: float = 0.3, subdivisions: int = 4, dtype=torch.float32):
    """(verts (Vb, 3), faces (Fb, 3)) of an icosphere centred at the origin (needs trimesh)."""
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return torch.as_tensor(s.vertices, dtype=dtype), torch.as_tensor(s.faces, dtype=torch.int64)


def time_sheet_on_sphere(
    n: int = 64,
    frames: int = 100,
    substeps: int = 40,
    iterations: int = 1,
    scheme: str = "gauss_seidel",
    use_extension: bool = True,
    dtype: torch.dtype = torch.float32,
    num_threads: int = 1,
    fused: bool = True,
) -> dict:
    """Drop an ``n``×``n`` sheet on a sphere for ``frames`` frames and time every frame.

    ``fused=False`` times the former, unfused path (`_UnfusedSolver`) for comparison.

    Returns:
        a dict with ``ms_per_substep`` (median over frames, wall), ``cpu_ms_per_substep`` (median, process
        CPU time), ``mean_ms_per_substep`` (total wall / substeps), ``vertices``, ``mean_edge_strain``,
        ``max_edge_strain`` (|edge| / rest − 1 over the triangle edges at the end), ``min_radius_m``
        (closest vertex to the sphere centre; the sphere is 0.3 m, the cloth thickness 5 mm) and the options.
    """
    verts, faces = sphere_mesh(dtype=dtype)
    material = ClothMaterial(k_uu=1e3, k_vv=1e3, k_uv=200.0, bend_stiffness=1e-6, thickness=0.005)
    g = rectangle_garment(n, n, 1.0, 1.0, origin=(-0.5, 0.8, 0.5))
    model = ClothModelBuilder(material).add_garment(g).finalize(dtype=dtype)
    rest = model.rest_data(g.vert_uv.to(dtype))
    cfg = XPBDConfig(
        substeps=substeps,
        iterations=iterations,
        scheme=scheme,
        use_extension=use_extension,
        num_threads=num_threads,
    )
    solver = (XPBDSolver if fused else _UnfusedSolver)(model, cfg)
    state = model.initial_state()
    state = solver.step(state, rest, 1 / 60, body_verts=verts, body_faces=faces)  # warm-up
    wall, cpu = [], []
    for _ in range(frames - 1):
        t0, c0 = time.perf_counter(), time.process_time()
        state = solver.step(state, rest, 1 / 60, body_verts=verts, body_faces=faces)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    tv = model.tri_vertices
    edges = torch.cat((tv[:, [0, 1]], tv[:, [1, 2]], tv[:, [2, 0]]))
    uv = g.vert_uv.to(dtype)
    rest_len = (uv[edges[:, 0]] - uv[edges[:, 1]]).norm(dim=-1)
    strain = (state.x[edges[:, 0]] - state.x[edges[:, 1]]).norm(dim=-1) / rest_len - 1
    return {
        "vertices": model.vert_count,
        "substeps": substeps,
        "iterations": iterations,
        "scheme": scheme,
        "extension": use_extension,
        "threads": num_threads,
        "fused": fused,
        "dtype": str(dtype).removeprefix("torch."),
        "frames": frames,
        "ms_per_substep": 1e3 * statistics.median(wall) / substeps,
        "cpu_ms_per_substep": 1e3 * statistics.median(cpu) / substeps,
        "mean_ms_per_substep": 1e3 * sum(wall) / (len(wall) * substeps),
        "mean_edge_strain": float(strain.abs().mean()),
        "max_edge_strain": float(strain.abs().max()),
        "min_radius_m": float(state.x.norm(dim=-1).min()),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=64)
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--substeps", type=int, default=40)
    parser.add_argument("--iterations", type=int, default=1)
    parser.add_argument("--scheme", default="gauss_seidel", choices=["gauss_seidel", "jacobi"])
    parser.add_argument("--float64", action="store_true", help="simulate in float64 (default float32)")
    parser.add_argument("--threads", type=int, default=1, help="XPBDConfig.num_threads of the C++ substep op")
    parser.add_argument("--reference", action="store_true", help="force the PyTorch reference kernels")
    parser.add_argument(
        "--unfused",
        action="store_true",
        help="the former path: per-constraint ops called from Python (before)",
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    out = time_sheet_on_sphere(
        args.n,
        args.frames,
        args.substeps,
        args.iterations,
        args.scheme,
        use_extension=not args.reference,
        dtype=torch.float64 if args.float64 else torch.float32,
        num_threads=args.threads,
        fused=not args.unfused,
    )
    print(dumps_json(out))


if __name__ == "__main__":
    main()
