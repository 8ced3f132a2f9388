"""`sim.tangles`: cloth edges through a part of the body thinner than they are."""

from __future__ import annotations

import torch

from torch_diffavatar.sim.tangles import edges_through_body, mesh_edges

# a slab 1 cm thick, 10 cm wide: a toe [m]
SLAB_V = torch.tensor(
    [[x, y, z] for x in (-0.05, 0.05) for y in (0.0, 0.01) for z in (-0.05, 0.05)], dtype=torch.float64
)
# 12 outward triangles; each square face split along its diagonal from the corner of the lowest index
SLAB_F = torch.tensor(
    [
        [0, 1, 3], [0, 3, 2],  # x = -0.05
        [4, 6, 7], [4, 7, 5],  # x = +0.05
        [0, 4, 5], [0, 5, 1],  # y = 0
        [2, 3, 7], [2, 7, 6],  # y = 0.01
        [0, 2, 6], [0, 6, 4],  # z = -0.05
        [1, 5, 7], [1, 7, 3],  # z = +0.05
    ]
)  # fmt: skip


def test_mesh_edges_are_distinct_and_sorted():
    edges = mesh_edges(torch.tensor([[0, 1, 2], [2, 1, 3]]))
    assert edges.tolist() == [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]]


def test_an_edge_across_a_thin_part_is_found_and_no_other():
    """A cloth triangle with one corner above the slab and two below it, 4 mm off its faces (as contacts
    keep the cloth 3 mm off): its two edges that cross the slab are tangled; those that run under it or
    beside it are not, nor those with an end inside it (a penetrating vertex: one crossing)."""
    x = torch.tensor(
        [
            [0.0, 0.014, 0.0],  # above
            [0.01, -0.004, 0.0],  # below
            [-0.01, -0.004, 0.01],  # below
            [0.06, -0.004, 0.0],  # below, beside the slab's +x face
            [0.0, 0.005, 0.02],  # inside the slab
            [0.06, 0.014, 0.0],  # beside the +x face, 1 cm off
            [0.07, 0.0, 0.02],  # beside
        ],
        dtype=torch.float64,
    )
    faces = torch.tensor([[0, 1, 2], [3, 1, 2], [4, 1, 2], [3, 5, 6]])
    tangled = edges_through_body(x, faces, SLAB_V, SLAB_F)
    assert tangled.tolist() == [[0, 1], [0, 2]]


def test_a_crossing_on_a_shared_body_edge_counts_once():
    """An edge entering the slab exactly through the diagonal that two of its triangles share, and ending
    inside: two hits at one place, one crossing, no tangle; continued through the far side, a tangle."""
    # the top face's diagonal runs from vertex 2 (-0.05, 0.01, -0.05) to 7 (0.05, 0.01, 0.05)
    inside = torch.tensor([[0.02, 0.014, 0.02], [0.02, 0.005, 0.02], [0.5, 0.5, 0.5]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2]])
    assert edges_through_body(inside, faces, SLAB_V, SLAB_F).shape == (0, 2)
    through = inside.clone()
    through[1, 1] = -0.004
    assert edges_through_body(through, faces, SLAB_V, SLAB_F).tolist() == [[0, 1]]


def test_cloth_away_from_the_body_is_not_cast():
    far = torch.tensor([[0.0, 0.2, 0.0], [0.1, 0.2, 0.0], [0.0, 0.2, 0.1]], dtype=torch.float64)
    assert edges_through_body(far, torch.tensor([[0, 1, 2]]), SLAB_V, SLAB_F).shape == (0, 2)
