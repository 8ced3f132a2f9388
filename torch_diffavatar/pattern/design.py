"""Design changes of a pattern at its hem: raised or lowered, widened or narrowed.

The hem is the panel corners on the garment's bottom openings (`measurements.HEM_OPENINGS`, found on the
pattern meshed): ``hem_up`` raises them in their panels (a shorter garment; negative: longer), ``hem_widen``
spreads them about their panel's hem centre (more flare). Synthetic scans change their truths' design this way
(`synthetic_scans`), and a fit sets its template's hem from the scan's with it (`fit_design`).
"""

from __future__ import annotations

import copy

import torch

from torch_diffavatar.pattern.measurements import HEM_OPENINGS
from torch_diffavatar.pattern.mesher import mesh_pattern


def changed_pattern(pattern, hem_up: float = 0.0, hem_widen: float = 0.0, spacing: float = 0.03):
    """A copy of ``pattern`` with its hem raised by ``hem_up`` [m] and widened by ``hem_widen`` [-].

    The hem corners are the pattern vertices of each panel that lie on the garment's bottom openings
    (`HEM_OPENINGS` of the template meshed at ``spacing``); in each panel they move up by ``hem_up`` and
    away from their mean x by the factor ``1 + hem_widen`` (panel frame). A pattern without a bottom
    opening is returned unchanged.
    """
    garment = mesh_pattern(pattern, spacing=spacing)
    hem_sim = [loop.vertices for loop in garment.boundary_loops if loop.name in HEM_OPENINGS]
    if not hem_sim:
        return copy.deepcopy(pattern)
    on_loop = torch.isin(garment.vert_to_sim, torch.cat(hem_sim))
    hem_verts = set(torch.nonzero(on_loop).flatten().tolist())  # panel vertices on the hem
    out = copy.deepcopy(pattern)
    for name in garment.panel_names:
        panel = out.panels[name]
        on_hem = []
        for k, edge in enumerate(panel.edges):
            ids = garment.edge_vertices[(name, k)]
            first, last = int(ids[0]), int(ids[-1])
            if first in hem_verts:
                on_hem.append(edge.start)
            if last in hem_verts:
                on_hem.append(edge.end)
        corners = sorted(set(on_hem))
        if not corners:
            continue
        v = panel.vertices
        centre = v[corners, 0].mean()
        v[corners, 0] = centre + (v[corners, 0] - centre) * (1.0 + hem_widen)
        v[corners, 1] += hem_up
    return out
