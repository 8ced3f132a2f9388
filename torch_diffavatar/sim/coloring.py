"""Greedy graph colouring of constraints so that no two constraints of one colour share a vertex.

The colour-ordered Gauss–Seidel kernels (`sim/ops.py`) process one colour at a time; inside a colour the
constraints are independent, so they can run in parallel (C++) or vectorised (reference).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class Coloring:
    """Constraint ids grouped by colour.

    Attributes:
        order: (K,) int64 constraint ids, colour by colour.
        color_offsets: (n_colors + 1,) int64 start of each colour in ``order`` (last entry = K).
    """

    order: torch.Tensor
    color_offsets: torch.Tensor

    @property
    def color_count(self) -> int:
        return int(self.color_offsets.shape[0]) - 1

    def to(self, device=None) -> Coloring:
        return Coloring(self.order.to(device), self.color_offsets.to(device))


def greedy_coloring(constraint_vertices: torch.Tensor) -> Coloring:
    """Colour constraints greedily (first-fit, in index order) so that colours share no vertex.

    Args:
        constraint_vertices: (K, m) int64 vertex ids of each constraint.

    Returns:
        a `Coloring` on the CPU.
    """
    cv = constraint_vertices.detach().cpu().to(torch.int64)
    k = int(cv.shape[0])
    if k == 0:
        return Coloring(torch.zeros(0, dtype=torch.int64), torch.zeros(1, dtype=torch.int64))
    masks: dict[int, int] = {}
    colors = [0] * k
    for i, verts in enumerate(cv.tolist()):
        used = 0
        for v in verts:
            used |= masks.get(v, 0)
        c = (~used & (used + 1)).bit_length() - 1  # lowest free colour
        colors[i] = c
        bit = 1 << c
        for v in verts:
            masks[v] = masks.get(v, 0) | bit
    color_t = torch.tensor(colors, dtype=torch.int64)
    order = torch.argsort(color_t, stable=True)
    counts = torch.bincount(color_t)
    offsets = torch.cat((torch.zeros(1, dtype=torch.int64), torch.cumsum(counts, 0)))
    return Coloring(order, offsets)


def coloring_is_valid(constraint_vertices: torch.Tensor, coloring: Coloring) -> bool:
    """True when every constraint appears once and no two constraints of one colour share a vertex."""
    k = int(constraint_vertices.shape[0])
    if sorted(coloring.order.tolist()) != list(range(k)):
        return False
    offsets = coloring.color_offsets.tolist()
    for s, e in zip(offsets[:-1], offsets[1:]):
        verts = constraint_vertices[coloring.order[s:e]].reshape(-1)
        if verts.unique().numel() != verts.numel():
            return False
    return True
