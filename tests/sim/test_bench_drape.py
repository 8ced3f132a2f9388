"""scripts/bench_drape.py: the edge-strain measure both simulators are judged by, and the wrapper that gives
Newton's model our rest data (run here on a stand-in for newton_drape.py, without Warp or Newton)."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from torch_diffavatar.sim.testing import rectangle_garment, tube_garment

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "bench_drape.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_drape", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_edge_rest_counts_and_strain_of_a_stretched_sheet(bench):
    nx, ny, w, h = 5, 4, 0.4, 0.3
    g = rectangle_garment(nx, ny, w, h)
    er = bench.EdgeRest(g, spacing=0.1)
    # grid edges: rows + columns + one diagonal per cell; the outline is the boundary
    assert len(er.rest) == (nx - 1) * ny + nx * (ny - 1) + (nx - 1) * (ny - 1)
    assert int(er.boundary.sum()) == 2 * (nx - 1) + 2 * (ny - 1)
    assert np.array_equal(er.edges, np.unique(np.sort(er.edges, axis=1), axis=0))
    x = g.vert_pos.numpy()
    assert np.abs(er.strain(x)).max() < 1e-12
    # stretch by 10 % along u (x): u-edges at +10 %, v-edges (z) unchanged, diagonals in between
    xs = x * np.array([1.1, 1.0, 1.0])
    s = er.strain(xs)
    du = np.abs(x[er.edges[:, 0], 0] - x[er.edges[:, 1], 0]) > 1e-9
    dv = np.abs(x[er.edges[:, 0], 2] - x[er.edges[:, 1], 2]) > 1e-9
    assert np.allclose(s[du & ~dv], 0.1) and np.allclose(s[dv & ~du], 0.0)
    assert np.all((s[du & dv] > 0.0) & (s[du & dv] < 0.1))
    stats = bench.EdgeRest(g, spacing=0.1).stats(xs)
    assert stats["edge_strain_max"] == pytest.approx(0.1, abs=1e-4)
    assert stats["edge_strain_mean"] == pytest.approx(float(s.mean()), abs=1e-5)
    assert stats["edge_strain_p99"] <= stats["edge_strain_max"]


def test_small_triangles_and_their_exclusion(bench):
    g = rectangle_garment(5, 4, 0.4, 0.3)  # 0.1 m cells
    assert bench.EdgeRest(g, spacing=0.1).small_tri_count == 0
    er = bench.EdgeRest(g, spacing=0.3)  # every triangle's shortest edge (0.1) is below 0.5 × 0.3
    assert er.small_tri_count == g.tri_count and er.in_small_tri.all()
    # stretch one interior edge only: the maximum sees it, the "no small" maximum of a mesh whose
    # triangles are not small sees it too, and the interior maximum equals the maximum
    er = bench.EdgeRest(g, spacing=0.1)
    x = g.vert_pos.numpy().copy()
    x[6] += np.array([0.02, 0.0, 0.0])  # interior vertex (i=1, j=1)
    stats = er.stats(x)
    assert stats["edge_strain_max"] == stats["edge_strain_max_no_small"] == stats["edge_strain_max_interior"]
    assert stats["edge_strain_max"] > 0.1
    assert not stats["worst_edge"]["boundary"]


def test_seam_edge_rest_length_is_the_mean_of_both_sides(bench):
    nx, ny, h = 4, 5, 0.4
    g = tube_garment(nx, ny, 0.3, h)
    n = nx * ny
    uv = g.vert_uv.clone()
    uv[n:, 1] *= 1.1  # the back panel is 10 % longer along v
    er = bench.EdgeRest(dataclasses.replace(g, vert_uv=uv), spacing=0.1)
    faces = g.sim_faces.numpy()
    sim_edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key, count = np.unique(np.sort(sim_edges, axis=1), axis=0, return_counts=True)
    assert np.array_equal(key, er.edges)
    v2s = g.vert_to_sim.numpy()
    seam_vertices = set(v2s[g.stitch_pairs[:, 0].numpy()])
    on_seam = np.array([a in seam_vertices and b in seam_vertices for a, b in er.edges])
    vertical = on_seam & np.isclose(er.rest, 0.5 * (1.0 + 1.1) * h / (ny - 1))
    assert vertical.sum() == 2 * (ny - 1)  # both side seams, every row
    assert not er.boundary[vertical].any() and (count[vertical] == 2).all()


FAKE_NEWTON = """
import json, time
import numpy as np

class _FakeArray:  # the two methods of a wp.array the wrapper uses
    def __init__(self, data):
        self.data = np.asarray(data)

    def numpy(self):
        return self.data

    def assign(self, values):
        assert np.asarray(values).shape == self.data.shape
        self.data = np.asarray(values).copy()

def unique_edges(faces):
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)

class Model:
    pass

def build(args, rest, faces, body_v, body_f, requires_grad):
    m = Model()
    edges = unique_edges(faces)
    m.spring_indices = _FakeArray(edges.reshape(-1))
    m.spring_rest_length = _FakeArray(np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1))
    m.particle_mass = _FakeArray(np.full(len(rest), 9.0))
    m.particle_inv_mass = _FakeArray(np.full(len(rest), 1.0 / 9.0))
    m.edge_count = 3
    m.edge_rest_angle = _FakeArray(np.full(3, 0.5))
    return m

def main():
    rest = np.array({rest!r})
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    t = time.perf_counter()
    m = build(None, rest, faces, None, None, False)
    time.perf_counter()
    print(json.dumps({{"rest": m.spring_rest_length.numpy().tolist(),
                      "mass": m.particle_mass.numpy().tolist(),
                      "inv_mass": m.particle_inv_mass.numpy().tolist(),
                      "angle": m.edge_rest_angle.numpy().tolist()}}))
"""


def test_newton_wrapper_overwrites_the_rest_data(bench, tmp_path):
    rest = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]]
    (tmp_path / "fake_newton.py").write_text(FAKE_NEWTON.format(rest=rest))
    (tmp_path / "wrapper.py").write_text(bench.NEWTON_WRAPPER)
    edges = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]])
    mass = np.array([0.1, 0.2, 0.0, 0.4])
    np.savez(tmp_path / "rest.npz", edges=edges, rest_length=np.arange(1.0, 6.0), mass=mass)
    cmd = [sys.executable, str(tmp_path / "wrapper.py"), str(tmp_path / "fake_newton.py")]

    def run(env_extra):
        env = {**os.environ, **env_extra}
        return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=60)

    plain = run({})
    assert plain.returncode == 0, plain.stderr
    out, clock = (json.loads(line) for line in plain.stdout.strip().splitlines()[-2:])
    assert out["rest"][1] == pytest.approx(np.sqrt(2.0)) and out["angle"] == [0.5] * 3
    assert clock["perf_counter_calls"] == 2
    patched = run({"BENCH_NEWTON_REST": str(tmp_path / "rest.npz")})
    assert patched.returncode == 0, patched.stderr
    out = json.loads(patched.stdout.strip().splitlines()[-2])
    assert out["rest"] == pytest.approx([1.0, 2.0, 3.0, 4.0, 5.0])
    assert out["mass"] == pytest.approx(mass.tolist())
    assert out["inv_mass"] == pytest.approx([10.0, 5.0, 0.0, 2.5])
    assert out["angle"] == [0.0] * 3
    # springs that are not the file's edges are refused
    np.savez(tmp_path / "rest.npz", edges=edges[::-1], rest_length=np.arange(1.0, 6.0), mass=mass)
    wrong = run({"BENCH_NEWTON_REST": str(tmp_path / "rest.npz")})
    assert wrong.returncode != 0 and "not the file's edges" in wrong.stderr


def test_parse_setting(bench):
    assert bench.parse_setting("80:1") == (80, 1.0)
    assert bench.parse_setting("160:50") == (160, 50.0)
    with pytest.raises(ValueError):
        bench.parse_setting("80")
