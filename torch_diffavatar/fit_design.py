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
import statistics
from dataclasses import asdict, dataclass, replace

import torch

from torch_diffavatar.fit_config import FitConfig, first_drape_config
from torch_diffavatar.opening_lengths import rest_loop_edges, rest_loop_length, scan_loop_length
from torch_diffavatar.pattern.measurements import HEM_OPENINGS

# a hem within this of the scan's height [m] and length [-] is left as the template has it
HEM_UP_TOLERANCE = 0.01
HEM_WIDEN_TOLERANCE = 0.02
# the bands of heights above a floor-cut garment's lowest scan point [m] whose points trace its legs
FLOOR_CUT_BANDS = ((0.01, 0.06), (0.06, 0.10), (0.10, 0.15), (0.15, 0.25))
# a garment whose lowest scan points lie within this [m] of the intake's floor margin was cut off there
FLOOR_CUT_SLACK = 0.005
# a floor-cut band's points per bin of its trace at the least (`scan_loop_length`; no reference curve: the
# first drape's hem, crumpled in its pile, is no cross-section of a leg): the medians of a 5 cm tall band of
# ten points jitter and lengthen it (a 320x240 capture's 330 points per leg 1-6 cm up: 76.6 / 80.7 cm
# against a true hem of 68.8; at 30 per bin 69.3 / 67.3; the ring captures 401 and 501, 1,000-1,260 per
# leg, 68.5-70.9 either way)
FLOOR_CUT_PER_BIN = 30


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
        floor_cut: hem loops the scan does not show, measured where the floor cut the garment off
            (`floor_cut_hems`): their length counts in ``hem_widen``, not their height in ``hem_up``.
    """

    hem_up: float
    hem_widen: float
    loops: tuple[str, ...]
    applied: bool
    waist_up: float = 0.0
    floor_cut: tuple[str, ...] = ()

    def as_dict(self) -> dict:
        return asdict(self) | {"loops": list(self.loops), "floor_cut": list(self.floor_cut)}


def hem_design(
    garment,
    drape_x: torch.Tensor,
    boundaries: dict[str, torch.Tensor],
    bin_length: float = 0.02,
    floor_cut: dict[str, float] | None = None,
) -> HemDesign | None:
    """The scan's hem against the template's first drape; None when the scan shows no hem of the garment.

    Args:
        garment: the placed template (`GarmentMesh`; its ``vert_uv`` is the template's rest shape).
        drape_x: (Vs, 3) its first drape [m], +y up (the fit's frame).
        boundaries: the scan's openings (`ScanTarget.boundaries`: name -> (k, 3) points [m]).
        bin_length: `scan_loop_length`'s bin [m] (`FitConfig.opening_length_bin`).
        floor_cut: the lengths [m] of the hem loops that the floor's removal cut off (`floor_cut_hems`):
            they count in ``hem_widen``, the loops' heights in nothing.
    """
    cut = floor_cut or {}
    loops = [lp for lp in garment.boundary_loops if lp.name in HEM_OPENINGS and lp.name in boundaries]
    loops = [lp for lp in loops if len(boundaries[lp.name]) > 0 and lp.name not in cut]
    cut_loops = [lp for lp in garment.boundary_loops if lp.name in cut]
    if not loops and not cut_loops:
        return None
    waist_up = _waist_up(garment, drape_x, boundaries) if loops else 0.0
    hem_up = 0.0
    if loops:
        scan_y = torch.cat([boundaries[lp.name][:, 1].double() for lp in loops])
        drape_y = torch.cat([drape_x[lp.vertices, 1].double() for lp in loops])
        hem_up = float(scan_y.median() - drape_y.median()) - waist_up
    traced, rest = 0.0, 0.0
    for lp in loops + cut_loops:
        if lp.name in cut:
            length = cut[lp.name]
        else:
            length, _ = scan_loop_length(
                boundaries[lp.name], bin_length=bin_length, reference=drape_x[lp.vertices]
            )
        if math.isfinite(length):  # too few of the hem's points for a length: its height still counts
            traced += length
            rest += float(rest_loop_length(garment.vert_uv.double(), rest_loop_edges(garment, lp)))
    hem_widen = max(traced / rest - 1.0, 0.0) if rest > 0 else 0.0
    applied = abs(hem_up) > HEM_UP_TOLERANCE or hem_widen > HEM_WIDEN_TOLERANCE
    names = tuple(lp.name for lp in loops)
    return HemDesign(hem_up, hem_widen, names, applied, waist_up, tuple(lp.name for lp in cut_loops))


def floor_cut_hems(
    garment,
    drape_x: torch.Tensor,
    boundaries: dict[str, torch.Tensor],
    garment_points,
    margin: float,
    bin_length: float = 0.02,
) -> dict[str, float]:
    """The lengths of the hems that the intake's floor removal cut off, from the legs above the floor.

    Trousers too long for their wearer pile on the floor, and the intake takes every point up to ``margin``
    above it (`scan_intake.floor_margin`), the pile and its hems with them. The scan then shows no hem, or
    the rim of the cut, which says nothing of the hem's height (the first drape's hems lie somewhere in
    its own pile). A leg above the pile hangs about as wide as its hem: each hem's length is the median of
    the loops its leg's scan points trace in the bands `FLOOR_CUT_BANDS` above the garment's lowest point,
    each point going to the hem whose first drape lies nearest it horizontally. The median, because a tall
    pile's top bulges in the lowest band (a 1.32 m body's trousers: 84 and 88 cm there against a true hem
    of 68.8) and a leg bunched over it folds in (58 cm); on four ring captures the two legs' medians
    came within 0.2-1.4 cm of the true hem on average (docs/BENCHMARKS.md, "Trousers piled on the floor").

    Args:
        garment: the placed template (`GarmentMesh`).
        drape_x: (Vs, 3) its first drape [m], +y up, the floor at y = 0.
        boundaries: the scan's openings (name -> (k, 3) points [m]).
        garment_points: (P, 3) the scan's garment points [m] (numpy or tensor).
        margin: the height above the floor up to which the intake removed the points [m].
        bin_length: `scan_loop_length`'s bin [m] (at least `FLOOR_CUT_PER_BIN` points per bin).

    Returns:
        name -> length [m] (nan when no band traces one) of each hem loop cut off: not in ``boundaries``,
        or there only within the lowest band's top of the lowest point. Empty when the garment's lowest
        scan point lies more than `FLOOR_CUT_SLACK` above ``margin`` (it ends above the cut), or no hem was
        cut off.
    """
    points = torch.as_tensor(garment_points).double()
    if len(points) == 0:
        return {}
    low = float(points[:, 1].min())
    if low > margin + FLOOR_CUT_SLACK:
        return {}

    def cut_off(name: str) -> bool:
        shown = boundaries.get(name)
        top = low + FLOOR_CUT_BANDS[0][1]
        return shown is None or len(shown) == 0 or float(shown[:, 1].double().median()) <= top

    missing = [lp for lp in garment.boundary_loops if lp.name in HEM_OPENINGS and cut_off(lp.name)]
    if not missing:
        return {}
    centres = torch.stack([drape_x[lp.vertices].double().mean(0)[[0, 2]] for lp in missing])
    nearest = torch.cdist(points[:, [0, 2]], centres).argmin(1)
    height = points[:, 1] - low
    lengths = {}
    for k, lp in enumerate(missing):
        traced = []
        for bottom, top in FLOOR_CUT_BANDS:
            band = points[(nearest == k) & (height >= bottom) & (height <= top)]
            traced.append(scan_loop_length(band, bin_length=bin_length, points_per_bin=FLOOR_CUT_PER_BIN)[0])
        traced = [t for t in traced if math.isfinite(t)]
        lengths[lp.name] = statistics.median(traced) if traced else math.nan
    return lengths


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
