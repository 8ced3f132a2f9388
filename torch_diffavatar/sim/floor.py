"""The floor a person stands on: a horizontal plane (y up) at the body's soles that the cloth rests on.

Trousers and dresses longer than the body's legs reach the floor in a real capture and pile on it; with
no floor our drapes let them hang through it (a captured trousers scan's truth hung 16.6 cm below the
soles, docs/BENCHMARKS.md, "Trousers through the floor"). The floor is two upward-facing triangles
appended to the body mesh (`with_floor`), so that every part of the simulator that answers body contacts
(the C++ substep op, its twin, both adjoints) answers floor contacts as they are. One thing is the floor's
own: where a foot's side meets the floor the two form a valley whose sides share no vertex, and a vertex
there gets both contacts (`XPBDConfig.floor_faces`). The quad reaches `FLOOR_MARGIN` beyond the body's
horizontal extent; its height follows the body's lowest vertex (differentiably); its extent is fixed.

Cloth that the placement lays below the floor (legs longer than the body's) would be pushed up through
the floor's whole depth in one substep, a velocity of metres per second: `fold_above_floor` mirrors it
up at the floor first (a mirror: nothing stretched), and gravity lays the fold down onto the floor.
"""

from __future__ import annotations

import torch

# How far [m] the floor quad reaches beyond the body's horizontal extent: farther than cloth spreads
# around the feet (a hem's radius beyond the body is ~0.3 m) and the body grid grows with it.
FLOOR_MARGIN = 0.75
# the floor's faces, appended last to the body's (`XPBDConfig.floor_faces`)
FLOOR_FACES = 2


def sole_height(body_verts: torch.Tensor) -> float:
    """The floor's height [m]: the lowest body vertex's y (the soles of a standing body). body_verts:
    (..., Vb, 3) [m]."""
    return float(body_verts.detach()[..., 1].min())


def floor_quad(body_verts: torch.Tensor, height: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The floor under ``body_verts`` (..., Vb, 3) [m] (all of them): (4, 3) vertices in their dtype and
    device, and (2, 3) int64 faces numbered from 0, normals +y. Its height is ``height`` [m], or the
    lowest body vertex's y, differentiable (the gradient of a floor contact reaches that vertex: a body
    moved down takes its floor along)."""
    b = body_verts.detach().reshape(-1, 3)
    lo, hi = b[:, [0, 2]].amin(0) - FLOOR_MARGIN, b[:, [0, 2]].amax(0) + FLOOR_MARGIN
    xz = torch.stack((lo, torch.stack((lo[0], hi[1])), hi, torch.stack((hi[0], lo[1]))))  # (4, 2)
    y = body_verts[..., 1].amin() if height is None else body_verts.new_tensor(float(height))
    verts = torch.stack((xz[:, 0], y.expand(4), xz[:, 1]), dim=-1)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]], dtype=torch.int64, device=body_verts.device)
    return verts, faces


def with_floor(
    body_verts: torch.Tensor, body_faces: torch.Tensor, height: float | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The body (..., Vb, 3) [m], one or several poses, with the floor appended (`floor_quad`, the same
    in each): (..., Vb + 4, 3) vertices, differentiable in ``body_verts``, and (Fb + 2, 3) int64 faces.
    The body's own vertex and face numbers are unchanged."""
    verts, faces = floor_quad(body_verts, height)
    verts = verts.expand(*body_verts.shape[:-2], 4, 3)
    return (
        torch.cat((body_verts, verts), dim=-2),
        torch.cat((body_faces.to(torch.int64), faces + body_verts.shape[-2])),
    )


def fold_above_floor(x: torch.Tensor, height: float, clearance: float) -> torch.Tensor:
    """``x`` (..., 3) [m] with every point below ``height + clearance`` [m] mirrored up at that plane (the
    rest unchanged): cloth placed through the floor folded onto its top side, stretched nowhere (an edge
    across the fold gets shorter, the others keep their length)."""
    top = height + clearance
    y = x[..., 1]
    return torch.cat((x[..., :1], torch.where(y < top, 2 * top - y, y)[..., None], x[..., 2:]), dim=-1)
