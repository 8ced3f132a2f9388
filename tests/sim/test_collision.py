"""Cloth–body collision: detection, projection outside the body, differentiability, friction."""

from __future__ import annotations

import pytest
import torch

from torch_diffavatar.sim import collision, ops, reference
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.model import ClothModelBuilder
from torch_diffavatar.sim.solver import XPBDConfig, XPBDSolver
from torch_diffavatar.sim.testing import rectangle_garment

F64 = torch.float64


def _box(extent=(1.0, 0.2, 1.0)):
    trimesh = pytest.importorskip("trimesh")
    b = trimesh.creation.box(extents=extent)
    return torch.as_tensor(b.vertices, dtype=F64), torch.as_tensor(b.faces, dtype=torch.int64)


def test_projection_pushes_points_to_thickness_outside():
    verts, faces = _box()  # top face at y = 0.1
    x = torch.tensor([[0.0, 0.095, 0.0], [0.2, 0.08, 0.1], [0.3, 0.2, 0.0], [0.1, 0.105, 0.2]], dtype=F64)
    contacts = collision.detect_contacts(x, verts, faces, 0.05)
    assert sorted(contacts.vert.tolist()) == [0, 1, 3]  # the point 10 cm above is outside the band
    w = torch.ones(4, dtype=F64)
    y, depth, normal = collision.project_contacts(x, w, verts, faces, contacts, 0.01)
    torch.testing.assert_close(y[[0, 1, 3], 1], torch.full((3,), 0.11, dtype=F64))
    torch.testing.assert_close(y[:, [0, 2]], x[:, [0, 2]])
    assert float(depth.min()) > 0
    torch.testing.assert_close(normal, torch.tensor([[0.0, 1.0, 0.0]], dtype=F64).expand(3, 3))
    # pinned vertices do not move
    y2, _, _ = collision.project_contacts(x, torch.zeros(4, dtype=F64), verts, faces, contacts, 0.01)
    assert torch.equal(y2, x)


def test_projection_is_differentiable_in_body_vertices():
    verts, faces = _box()
    gen = torch.Generator().manual_seed(0)
    # tilt the box a little so the normals are generic
    verts = verts + 0.01 * torch.randn(verts.shape, generator=gen, dtype=F64)
    x = torch.tensor([[0.05, 0.09, 0.02], [-0.2, 0.095, 0.3], [0.31, 0.1, -0.22]], dtype=F64)
    contacts = collision.detect_contacts(x, verts, faces, 0.05)
    assert contacts.count == 3
    w = torch.ones(3, dtype=F64)

    def f(body_verts, x):
        return collision.project_contacts(x, w, body_verts, faces, contacts, 0.01)[0]

    assert torch.autograd.gradcheck(f, (verts.clone().requires_grad_(), x.clone().requires_grad_()))


def test_friction_static_and_kinetic():
    verts, faces = _box()
    x_start = torch.tensor([[0.0, 0.11, 0.0], [0.2, 0.11, 0.0]], dtype=F64)
    x = x_start + torch.tensor([[0.001, -0.005, 0.0], [0.05, -0.005, 0.0]], dtype=F64)
    contacts = collision.detect_contacts(x, verts, faces, 0.05)
    y, depth, normal = collision.project_contacts(x, torch.ones(2, dtype=F64), verts, faces, contacts, 0.01)
    z = collision.apply_friction(y, x_start, contacts, normal, depth, 0.5)
    # small slide (1 mm < 0.5 * 5 mm): cancelled; large slide (5 cm): reduced by mu * depth = 2.5 mm
    torch.testing.assert_close(z[0, [0, 2]], x_start[0, [0, 2]])
    torch.testing.assert_close(z[1, 0], torch.tensor(0.2 + 0.05 - 0.0025, dtype=F64))


def test_cloth_on_tilted_box_sticks_with_friction_and_slides_without():
    verts, faces = _box((1.0, 0.2, 1.0))
    angle = 0.25  # [rad] ~14°, tan = 0.26
    c, s = torch.cos(torch.tensor(angle, dtype=F64)), torch.sin(torch.tensor(angle, dtype=F64))
    rot = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    verts = verts @ rot.T
    # small sheet lying on the tilted top face, just above the thickness
    normal = rot[:, 1]
    origin = (rot @ torch.tensor([-0.1, 0.1 + 0.004, 0.1], dtype=F64)).tolist()
    g = rectangle_garment(4, 4, 0.2, 0.2, origin=origin, axis_u=rot[:, 0].tolist(), axis_v=(0.0, 0.0, -1.0))
    drift = {}
    for mu in (0.0, 0.6):
        mat = ClothMaterial(k_uu=1e3, k_vv=1e3, k_uv=100.0, thickness=0.004, friction=mu, damping=0.0)
        model = ClothModelBuilder(mat).add_garment(g).finalize(dtype=F64)
        rest = model.rest_data(g.vert_uv)
        solver = XPBDSolver(model, XPBDConfig(substeps=10, iterations=2))
        state = model.initial_state()
        for _ in range(20):
            state = solver.step(state, rest, 1 / 60, body_verts=verts, body_faces=faces)
        drift[mu] = float((state.x - model.vert_init_pos).mean(0).norm())
        # stays on the surface (neither sinks into the box nor lifts off)
        assert float(((state.x @ normal) - (model.vert_init_pos @ normal)).abs().max()) < 5e-3
    # g sin(angle) ~ 2.4 m/s²: frictionless it slides ~ 0.5 * 2.4 * (1/3)^2 = 0.13 m in 1/3 s
    assert drift[0.0] > 0.08
    assert drift[0.6] < 0.01


def test_edge_ties_pick_the_farthest_plane():
    # a roof: two faces meeting at the ridge x = 0 (y = 0.1), sloping down at ±45°. Points above the ridge
    # are equally close to both faces (closest point on the ridge edge); the contact must use the face whose
    # plane is farther from the point (the left face for a point left of the ridge), whichever face the query
    # returned, and keep the same closest point
    corners = [[-1.0, -0.9, -1], [0, 0.1, -1], [0, 0.1, 1], [-1, -0.9, 1], [1, -0.9, -1], [1, -0.9, 1]]
    verts = torch.tensor(corners, dtype=F64)
    faces = torch.tensor([[0, 2, 1], [0, 3, 2], [1, 2, 5], [1, 5, 4]], dtype=torch.int64)  # outward = +y side
    x = torch.tensor([[-0.002, 0.11, 0.3], [0.003, 0.11, -0.2], [0.5, -0.2, 0.0]], dtype=F64)
    c = collision.detect_contacts(x, verts, faces, 0.05)
    assert c.vert.tolist() == [0, 1]  # the third point is 0.2 m above the right face
    left = (c.tri <= 1).tolist()
    assert left == [True, False]
    point, normal = collision.contact_frames(verts, faces, c)
    torch.testing.assert_close(point[:, [0, 1]], torch.tensor([[0.0, 0.1], [0.0, 0.1]], dtype=F64))
    s = ((x[c.vert] - point) * normal).sum(-1)
    other = torch.tensor([[1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]], dtype=F64) / 2**0.5  # the other faces' normals
    assert bool((s > ((x[c.vert] - point) * other).sum(-1)).all())
    torch.testing.assert_close(c.bary.sum(-1), torch.ones(2, dtype=F64))


@pytest.mark.skipif(
    not ops.closest_point_index_available(torch.device("cpu")), reason="needs the C++ extension"
)
def test_outermost_op_matches_its_twin_on_edges_and_corners():
    """`contact_outermost` (C++) against `reference.contact_outermost`: points above a bumpy sphere whose
    contacts sit on an edge (one zero barycentric), a corner (two) or inside (none; kept)."""
    trimesh = pytest.importorskip("trimesh")
    s = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    verts = torch.as_tensor(s.vertices, dtype=F64)
    verts = verts * (1 + 0.05 * torch.sin(7 * verts[:, :1]))  # not convex everywhere
    faces = torch.as_tensor(s.faces, dtype=torch.int64)
    features = collision._feature_faces(faces, verts.shape[0])
    gen = torch.Generator().manual_seed(2)
    n = 300
    tri = torch.randint(0, faces.shape[0], (n,), generator=gen)
    bary = torch.rand(n, 3, generator=gen, dtype=F64)
    bary[: n // 3, 0] = 0  # on the edge opposite corner 0
    bary[n // 3 : 2 * n // 3, 1:] = 0  # on corner 0
    bary = bary / bary.sum(-1, keepdim=True)
    corners = verts[faces[tri]]
    on = (bary[:, :, None] * corners).sum(1)
    normal = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=F64), dim=-1)
    x = on + 0.01 * normal * torch.rand(n, 1, generator=gen, dtype=F64)
    for dtype in (torch.float32, F64):
        args = (x.to(dtype), verts.to(dtype), faces, features.across, features.ring, tri, bary.to(dtype))
        got = ops.contact_outermost(*args)
        want = reference.contact_outermost(*args)
        assert torch.equal(got[0], want[0])
        torch.testing.assert_close(got[1], want[1], rtol=0, atol=0)
        moved = got[0] != tri
        assert 30 < int(moved.sum()) and not bool(moved[2 * n // 3 :].any())  # inside contacts stay
        # the contact point is the same on the new face
        new_point = (got[1].to(F64)[:, :, None] * verts[faces[got[0]]]).sum(1)
        torch.testing.assert_close(new_point, on, rtol=0, atol=1e-6 if dtype == torch.float32 else 1e-12)
    few = (args[0][:40], *args[1:5], args[5][:40], args[6][:40])
    torch.library.opcheck(ops._index_op("contact_outermost").default, few)
