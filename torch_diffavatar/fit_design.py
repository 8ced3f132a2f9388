"""The template's hem set from the scan before the fit starts: its height and its length (issue #30).

A template longer than the garment in the scan leaves its first drape's hem below the scan's, and the fit
then raises the hem every way the drape allows, not only by shortening the panels: on a T-shirt whose
template was 5 cm long, the hem's term pulled the neck 5.2 cm smaller in the first six iterations (it
lifts the shirt on the shoulders), and the rest terms held it there for the remaining 24 (neck −6.2 cm
from the truth; fitted from a template of the right length, +1.2; docs/BENCHMARKS.md, "The hem from the
scan before the fit"). A tailor measures the length first. So does `hem_design`: the template is sewn and
draped once (`first_hem_drape`); the scan's hem points lie ``hem_up`` above the drape's hem loop (medians
of their heights, every hem loop pooled), and they trace a loop ``1 + hem_widen`` times as long as the
template's hem (widened only: folds make a traced hem shorter than the cloth's, not longer). The fit then
starts from `pattern.design.changed_pattern` of the template (`FitConfig.hem_from_scan`).

A skirt or trousers hangs from its waistband, which a real one may wear on the hips: there the scan's hem is
low by the waistband's drop, the panels no longer. So the height the scan's waistband lies above the first
drape's (``waist_up``) is taken off ``hem_up``: Newton's trousers 386, waistband 3 cm lower than ours, had
their hem measured 5.8 cm *down* without it and were lengthened (docs/BENCHMARKS.md, "The hem from the scan
before the fit", "… from the waist down").
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import torch

from torch_diffavatar.fit_config import FitConfig, first_drape_config
from torch_diffavatar.opening_lengths import rest_loop_edges, rest_loop_length, scan_loop_length
from torch_diffavatar.pattern.measurements import HEM_OPENINGS

# a hem within this of the scan's height [m] and length [-] is left as the template has it
HEM_UP_TOLERANCE = 0.01
HEM_WIDEN_TOLERANCE = 0.02


@dataclass(frozen=True)
class HemDesign:
    """What the scan says of the template's hem (`hem_design`).

    Attributes:
        hem_up: the scan's hem lies this far above the first drape's [m] (negative: below), less
            ``waist_up``: how much shorter the panels are to be.
        hem_widen: the scan's hem traces a loop this much longer than the template's hem [-] (>= 0).
        loops: the hem loops measured (names of `HEM_OPENINGS` that both the garment and the scan have).
        applied: the template was changed (either beyond `HEM_UP_TOLERANCE` / `HEM_WIDEN_TOLERANCE`).
        waist_up: the scan's waistband lies this far above the first drape's [m] (0 without a waist).
    """

    hem_up: float
    hem_widen: float
    loops: tuple[str, ...]
    applied: bool
    waist_up: float = 0.0

    def as_dict(self) -> dict:
        return asdict(self) | {"loops": list(self.loops)}


def hem_design(
    garment, drape_x: torch.Tensor, boundaries: dict[str, torch.Tensor], bin_length: float = 0.02
) -> HemDesign | None:
    """The scan's hem against the template's first drape; None when the scan shows no hem of the garment.

    Args:
        garment: the placed template (`GarmentMesh`; its ``vert_uv`` is the template's rest shape).
        drape_x: (Vs, 3) its first drape [m], +y up (the fit's frame).
        boundaries: the scan's openings (`ScanTarget.boundaries`: name -> (k, 3) points [m]).
        bin_length: `scan_loop_length`'s bin [m] (`FitConfig.opening_length_bin`).
    """
    loops = [lp for lp in garment.boundary_loops if lp.name in HEM_OPENINGS and lp.name in boundaries]
    loops = [lp for lp in loops if len(boundaries[lp.name]) > 0]
    if not loops:
        return None
    scan_y = torch.cat([boundaries[lp.name][:, 1].double() for lp in loops])
    drape_y = torch.cat([drape_x[lp.vertices, 1].double() for lp in loops])
    waist_up = _waist_up(garment, drape_x, boundaries)
    hem_up = float(scan_y.median() - drape_y.median()) - waist_up
    traced, rest = 0.0, 0.0
    for lp in loops:
        length, _ = scan_loop_length(
            boundaries[lp.name], bin_length=bin_length, reference=drape_x[lp.vertices]
        )
        if math.isfinite(length):  # too few of the hem's points for a length: its height still counts
            traced += length
            rest += float(rest_loop_length(garment.vert_uv.double(), rest_loop_edges(garment, lp)))
    hem_widen = max(traced / rest - 1.0, 0.0) if rest > 0 else 0.0
    applied = abs(hem_up) > HEM_UP_TOLERANCE or hem_widen > HEM_WIDEN_TOLERANCE
    return HemDesign(hem_up, hem_widen, tuple(lp.name for lp in loops), applied, waist_up)


def _waist_up(garment, drape_x: torch.Tensor, boundaries: dict[str, torch.Tensor]) -> float:
    """How far the scan's waistband lies above the first drape's [m] (medians of their heights; negative:
    below), or 0 for a garment or a scan without a waist. A skirt or trousers hangs from its waistband, and
    a real one may sit on the hips: its hem is then low by as much, with the panels as long."""
    loop = next((lp for lp in garment.boundary_loops if lp.name == "waist"), None)
    scan = boundaries.get("waist")
    if loop is None or scan is None or len(scan) == 0:
        return 0.0
    return float(scan[:, 1].double().median() - drape_x[loop.vertices, 1].double().median())


@torch.no_grad()
def first_hem_drape(
    garment,
    body_verts: torch.Tensor,
    body_faces: torch.Tensor,
    config: FitConfig,
    *,
    fallback=None,
) -> torch.Tensor:
    """(Vs, 3) [m] the template sewn onto the body and settled as a fit's first drape is (its first
    `first_bend_scales`, then the fit's own substeps at its stiffness: `fit_start.first_states`)."""
    from torch_diffavatar.fit_start import settle
    from torch_diffavatar.sim.forward_drape import sew_and_drape
    from torch_diffavatar.sim.material import ClothMaterial
    from torch_diffavatar.sim.state import ClothState

    material = ClothMaterial(bend_stiffness=config.initial_bend_stiffness)
    sewn = sew_and_drape(
        garment,
        body_verts=body_verts.float(),
        body_faces=body_faces,
        fallback=fallback,
        material=replace(material, bend_stiffness=material.bend_stiffness * config.first_bend_scales[0]),
        config=first_drape_config(config),
    )
    state = ClothState(sewn.state.x, torch.zeros_like(sewn.state.x))
    return settle(
        sewn.model, state, garment.vert_uv.float(), body_verts.float(), body_faces, material, config
    ).x
