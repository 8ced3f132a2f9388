"""What a fit reports: the summary of one evaluation, the report of a run and the warnings about its result.

Units: metres. The report's Chamfer distance is measured on the draped *surface* (`chamfer.surface_chamfer_m`,
[m], not squared: the symmetric average of scan → surface and surface samples → scan), so it does not depend
on the mesh's resolution; the boundary Chamfers are vertex-based mean nearest-neighbour distances [m]
(`chamfer_m`).
"""

from __future__ import annotations

import math

import torch

from torch_diffavatar.chamfer import nearest_indices, surface_chamfer_m
from torch_diffavatar.losses import rest_area_ratio
from torch_diffavatar.metrics import scan_noise_sigma_m, triangle_quality
from torch_diffavatar.objective import FitObjective, ObjectiveOutput, membrane_stiffnesses
from torch_diffavatar.opening_lengths import rest_loop_length

# a draped triangle below this quality (`metrics.triangle_quality`) is flagged in the fit's report: the
# evaluation's target for a simulation-ready drape (docs/RESULTS.md)
DRAPED_QUALITY_FLOOR = 0.3
# A fit whose surface Chamfer ends above max(this × the scan's noise (`metrics.scan_noise_sigma_m`), the
# floor below) is flagged. Measured on fits of our synthetic scans (σ = 3 mm, read as 2.2 mm): 6-14 mm in
# docs/RESULTS.md, 17 mm for short trouser fits; fits that went wrong on real captures ended at 23 mm.
FAR_FROM_SCAN_NOISE = 8.0
FAR_FROM_SCAN_FLOOR_M = 0.02
# An opening whose boundary Chamfer ends above this is flagged. Matched openings of fits of our synthetic
# scans end at 1-5 cm (hems the widest); a hem segmented 20-30 cm low on a real capture pulled its pattern.
FAR_OPENING_M = 0.08
# A garment whose lowest scan points lie this close [m] above a scan's floor reaches it (the intake removes
# points up to at least 1.5 cm above it; trousers' hems at the ankles end 3 cm and more above it).
FLOOR_REACH_M = 0.03

CHAMFER_DEFINITION = (
    "symmetric mean surface distance, not squared: (mean distance of the scan "
    "garment points to the draped surface + mean distance of 50k area samples of the draped surface "
    "to the nearest scan garment point) / 2; boundary chamfers: mean nearest-neighbour distance "
    "between loop vertices and scan loop points, (a->b + b->a) / 2 (a neck under a folded collar: "
    "its fold, losses.folded_collar_loop)"
)


def chamfer_m(x: torch.Tensor, y: torch.Tensor) -> float:
    """Symmetric mean nearest-neighbour distance [m] ``(mean_x d(x, Y) + mean_y d(y, X)) / 2``."""
    x, y = x.detach().double().cpu(), y.detach().double().cpu()
    dxy = (x - y[torch.from_numpy(nearest_indices(x, y))]).norm(dim=1).mean()
    dyx = (y - x[torch.from_numpy(nearest_indices(y, x))]).norm(dim=1).mean()
    return float(0.5 * (dxy + dyx))


def summarize(out: ObjectiveOutput, objective: FitObjective, garment_points: torch.Tensor, body=None) -> dict:
    """Numbers and tensors of one evaluation kept for the report and the before/after picture.

    Args:
        out: the evaluation; objective: its objective (faces, scan openings); garment_points: (P, 3)
            all the scan's garment points [m] (the surface Chamfer's); body: the fitted `BodyModel` or None.
    """
    return {
        "x": out.x.detach().clone(),
        "body_verts": None if out.body_verts is None else out.body_verts.detach().clone(),
        "loss": float(out.loss.detach()),
        "terms": {k: float(v.detach()) for k, v in out.terms.items()},
        "chamfer_m": surface_chamfer_m(out.x, objective.garment.sim_faces, garment_points)["symmetric"],
        "boundary_chamfer_m": {
            lp.name: chamfer_m(out.x[lp.vertices], objective.scan_boundaries[lp.name]) for lp in out.openings
        },
        "bend_stiffness": float(out.bend_stiffness.detach()),
        "stretch_scale": 1.0 if out.stretch is None else float(out.stretch.detach()),
        "waist_shift_m": 0.0 if out.waist_shift is None else float(out.waist_shift.detach()),
        "phenotypes": None
        if body is None
        else dict(zip(body.phenotype_labels, body.phenotypes[0].detach().tolist())),
        "rest_uv": out.rest_uv.detach().clone(),
    }


def fit_report(first: dict, final: dict, objective: FitObjective, run: dict) -> dict:
    """The metrics of a fit: initial vs final Chamfer [m], loss terms, material, body, quality.

    Args:
        first, final: `summarize` of the first and of the resulting evaluation.
        objective: the fit's objective (garment, template, config, matched openings).
        run: the driver's counts: ``iterations``, ``result_iteration``, ``seconds``, ``rejected_steps``,
            ``rejection_reasons``, ``nan_gradients``, ``adjoint_failures``, ``first_drape_candidates``,
            ``resewings`` (`fit_start.resew`).
    """
    garment, config = objective.garment, objective.config
    with torch.no_grad():
        q_rest = triangle_quality(final["rest_uv"], garment.tri_vertices)
        q_drape = triangle_quality(final["x"], garment.sim_faces)
        ratio = rest_area_ratio(final["rest_uv"], objective.template_uv, garment.tri_vertices)
    return {
        "units": "m",
        "chamfer_definition": CHAMFER_DEFINITION,
        "template": config.template,
        "chamfer_initial": first["chamfer_m"],
        "chamfer_final": final["chamfer_m"],
        "boundary_chamfer_initial": first["boundary_chamfer_m"],
        "boundary_chamfer_final": final["boundary_chamfer_m"],
        "iterations": run["iterations"],
        "result_iteration": run["result_iteration"],
        "seconds": round(run["seconds"], 2),
        "loss_initial": first["loss"],
        "loss_final": final["loss"],
        "loss_terms_initial": first["terms"],
        "loss_terms_final": final["terms"],
        "material": {
            "bend_stiffness_initial": first["bend_stiffness"],
            "bend_stiffness_final": final["bend_stiffness"],
            "unit": "N*m",
            # the factor of the base material's k_uu, k_vv, k_uv [-], and those stiffnesses [N/m]
            "stretch_scale_initial": first["stretch_scale"],
            "stretch_scale_final": final["stretch_scale"],
            "membrane_initial": dict(
                membrane_stiffnesses(objective.material, first["stretch_scale"]), unit="N/m"
            ),
            "membrane_final": dict(
                membrane_stiffnesses(objective.material, final["stretch_scale"]), unit="N/m"
            ),
        },
        # the waist attachments' height change [m] (up positive), for garments held at the waist
        "waist_shift_initial": first["waist_shift_m"],
        "waist_shift_final": final["waist_shift_m"],
        "body_phenotypes_initial": first["phenotypes"],
        "body_phenotypes_final": final["phenotypes"],
        "rest_quality": {"min": float(q_rest.min()), "mean": float(q_rest.mean())},
        "draped_quality": {"min": float(q_drape.min()), "mean": float(q_drape.mean())},
        "inverted_rest_triangles": int((ratio <= 0).sum()),
        "min_rest_area_ratio": float(ratio.min()),
        "rejected_steps": run["rejected_steps"],
        "rejection_reasons": dict(run["rejection_reasons"]),
        "nan_gradients": run["nan_gradients"],
        "adjoint_failures": run["adjoint_failures"],
        "adjoint": config.adjoint,
        "vertices": garment.sim_vert_count,
        "faces": garment.tri_count,
        "matched_boundaries": [lp.name for lp in objective.loops],
        "opening_lengths": opening_lengths(objective, first["rest_uv"], final["rest_uv"]),
        "first_drape_candidates": list(run["first_drape_candidates"]),
        "resewings": list(run.get("resewings", [])),
        "warnings": result_warnings(final["x"], garment.sim_faces, ratio, config.spacing)
        + stall_warnings(run)
        + unheld_opening_warnings(config, garment),
    }


def unheld_opening_warnings(config, garment) -> list[str]:
    """A warning for each name of ``config.opening_template_names`` that no opening of ``garment`` has (a
    misspelt name, or a config written for another garment): it is held nowhere."""
    names = {loop.name for loop in garment.boundary_loops}
    missing = [n for n in config.opening_template_names if n not in names]
    if not missing:
        return []
    return [
        f"opening_template_names names {', '.join(missing)}, which this garment has no opening of (it has "
        f"{', '.join(sorted(names))}): held nowhere"
    ]


def stall_warnings(run: dict) -> list[str]:
    """A warning when the fit never left its first drape: no iteration lowered the loss, and at least as many
    trials as iterations were rejected (a T-shirt's ring capture, 51 rejected trials in 30 iterations, the
    assets its first drape, said nothing). ``run``: `fit_report`'s."""
    rejected, iterations = run["rejected_steps"], run["iterations"]
    if run["result_iteration"] != 0 or iterations == 0 or rejected < iterations:
        return []
    reasons = ", ".join(
        f"{n} {why}" for why, n in sorted(run["rejection_reasons"].items(), key=lambda kv: -kv[1])
    )
    return [
        f"the fit kept its first drape: none of its {iterations} iterations lowered the loss ({rejected} "
        f"trials rejected: {reasons}); the pattern and material are where the fit started, not fitted "
        "to the scan; look at scan_fit.png"
    ]


def opening_lengths(objective: FitObjective, first_uv: torch.Tensor, final_uv: torch.Tensor) -> dict:
    """Each held opening's length [m] (``config.opening_length_names``: the hems, a trouser waist; and
    ``config.opening_template_names``, ``template`` true: held at the template's, the scan not asked) as
    the scan's points trace it (``scan``: a lower bound, `torch_diffavatar.opening_lengths`; None where
    they trace none) and the share of the loop they show (``seen``, 0-1: its angular bins with points;
    None where not asked), the least the fit held it to (``least``: on a partial scan no less than the
    template's; ``held_to``: the openings whose traces gave it, its mirror's for a mirrored pair's
    worse-seen one, `opening_lengths.mirrored_lengths`), the most (``most``: ``least`` again for the
    openings held ``"exact"``, None for the others; ``held``: whether the term was on,
    ``weights.opening_length`` > 0), and as the pattern's rest edges give it at the first (``initial``)
    and at the resulting rest coordinates ``first_uv``, ``final_uv`` (V, 2) [m] (``final``): opening
    name -> those nine."""
    out = {}
    on = bool(objective.weight_opening_length > 0)
    held = zip(
        objective.opening_names,
        objective.opening_traced,
        objective.opening_seen,
        objective.opening_edges,
        objective.opening_held_to,
        strict=True,
    )
    for k, (name, traced, seen, edges, held_to) in enumerate(held):
        out[name] = {
            "scan": traced if math.isfinite(traced) else None,
            "seen": float(seen) if math.isfinite(seen) else None,
            "held_to": list(held_to),
            "template": name in objective.config.opening_template_names,
            "least": float(objective.opening_least[k]),
            "most": float(objective.opening_most[k]) if math.isfinite(objective.opening_most[k]) else None,
            "held": on,
            "initial": float(rest_loop_length(first_uv.detach(), edges)),
            "final": float(rest_loop_length(final_uv.detach(), edges)),
        }
    return out


def result_warnings(
    x: torch.Tensor, sim_faces: torch.Tensor, area_ratio: torch.Tensor, spacing: float
) -> list[str]:
    """What a user should know about a fit's result before simulating it (empty when nothing).

    Args:
        x: (Vs, 3) draped positions [m]; sim_faces: (F, 3) int64; area_ratio: (F,) rest areas over the
            template's (`losses.rest_area_ratio`); spacing: the mesh spacing [m].
    """
    warnings = []
    q = triangle_quality(x, sim_faces)
    bad = q < DRAPED_QUALITY_FLOOR
    if bool(bad.any()):
        worst = int(q.argmin())
        where = [round(float(c), 3) for c in x[sim_faces[worst]].mean(0)]
        # measured on tops fitted on arms held low: slivers pressed flat on the upper arm and held there
        # by friction (docs/BENCHMARKS.md, "Arms held low"); at 2 cm instead of 2.5, gone on three of four
        warnings.append(
            f"{int(bad.sum())} draped triangles have quality below {DRAPED_QUALITY_FLOOR} (min "
            f"{float(q.min()):.2f}, at {where} m): crushed cloth, e.g. pressed flat on the body where a mesh "
            f"this coarse does not fold; a finer spacing than {spacing:g} m (e.g. --spacing "
            f"{0.8 * spacing:.3g}) usually removes them"
        )
    inverted = int((area_ratio <= 0).sum())
    if inverted:
        warnings.append(f"{inverted} rest triangles are inverted: the pattern cannot be cut as it is")
    return warnings


def scan_warnings(report: dict, garment_points: torch.Tensor, coverage: dict | None = None) -> list[str]:
    """What a fit's result says about the scan it was fitted to (empty when nothing): the fit ends far
    above the scan's own noise, an opening ends far from the scan's opening, the scan is partial (and
    which held openings it shows too little of to measure), or a full scan shows a held opening with a gap
    (`gapped_opening_warnings`).

    Args:
        report: `fit_report`'s (``chamfer_final``, ``boundary_chamfer_final`` [m], ``opening_lengths``).
        garment_points: (P, 3) the scan's garment points [m].
        coverage: the sides the scan sees (`scan_intake.coverage`), or None.
    """
    warnings = []
    sigma = scan_noise_sigma_m(garment_points) if len(garment_points) > 16 else 0.0
    limit = max(FAR_FROM_SCAN_NOISE * sigma, FAR_FROM_SCAN_FLOOR_M)
    if report["chamfer_final"] > limit:
        warnings.append(
            f"the fitted garment ends {1e3 * report['chamfer_final']:.1f} mm from the scan, far above the "
            f"scan's own noise (about {1e3 * sigma:.1f} mm): the body fit, the scan's segmentation or the "
            "garment type is probably wrong; look at scan_fit.png and before_after.png"
        )
    far = {k: v for k, v in report["boundary_chamfer_final"].items() if v > FAR_OPENING_M}
    for name, distance in far.items():
        warnings.append(
            f"the {name} opening ends {1e2 * distance:.1f} cm from the scan's {name}: that scan opening is "
            "probably misplaced (segmentation) and has pulled the pattern toward it"
        )
    held = report.get("opening_lengths", {})
    if not coverage or coverage["sectors_seen"] == coverage["sectors"]:
        return warnings + gapped_opening_warnings(held)
    warnings.append(
        f"a partial scan: it sees {coverage['sectors_seen']} of {coverage['sectors']} sides of the "
        "person; only the cloth on those sides was pulled toward it, the rest follows the simulation"
    )
    # the openings the scan shows too little of to measure: held at the template's length at least
    unmeasured = [
        n
        for n, v in held.items()
        if v.get("held", True) and not v.get("template") and (v["scan"] is None or v["scan"] < v["least"])
    ]
    if unmeasured:
        names = ", ".join(unmeasured)
        warnings.append(
            f"the partial scan shows too little of these openings to measure them: {names}; each is "
            "held no shorter than the template's, so its width is the template's, not the scan's"
        )
    return warnings


def gapped_opening_warnings(held: dict) -> list[str]:
    """A warning naming the held openings (``held``: the report's ``opening_lengths``) that a full scan
    shows with a gap (``seen`` < 1, as a report written before ``seen`` existed never says): the length
    the scan's points trace is a lower bound, and the fitted opening follows it, short by whatever the
    hidden part holds. Measured on ring captures of 20 tops (docs/BENCHMARKS.md, "End to end on ten
    seeds"): the 7 hems traced whole were fitted within 0.8 cm of the truth; of the 13 with a gap (a fold
    lifted by a hand, out of the cameras' view), 9 were fitted 3.0-9.3 cm short. An opening held to its
    mirror's trace (``held_to``) is not named: its own gap does not count."""
    gapped = [
        (n, v)
        for n, v in held.items()
        if v.get("held", True)
        and v["scan"] is not None
        and v.get("seen", 1) < 1
        and n in v.get("held_to", [n])
    ]
    if not gapped:
        return []
    each = ", ".join(
        f"the {n} ({100 * v['seen']:.1f} % of it, {100 * v['scan']:.1f} cm traced)" for n, v in gapped
    )
    return [
        f"the scan shows part of an opening only: {each}; a traced length is a lower bound and the fitted "
        "opening follows it, so it may be short by what the hidden part holds (such as a fold lifted by a "
        "hand)"
    ]


def floor_warnings(floor: dict | None, garment_points) -> list[str]:
    """A warning when the scan had a floor (``floor``: the intake's, which put it at y = 0; None: none) and
    the garment's (P, 3) scan points [m] reach it (`FLOOR_REACH_M`): a hem that pools on the floor, or that
    the floor's removal cut off, does not show where the pattern ends. Trousers on a short body that hung
    through the floor were cut off there, and their fits shrank the body by 3.7-6.1 cm and the legs by 7 cm
    (docs/BENCHMARKS.md, "Trousers through the floor"); trousers piled on the floor, fitted on a floor
    (`FitConfig.drape_floor`), kept 2.6-5.3 cm of the template's extra leg in the pile ("A floor under the
    body"); of 40 ring-captured garments four trousers reached the floor, and the three whose lowest points
    lay 1.5 cm above it (cut with the floor) ended with their leg openings 3.8-6.5 cm off, the fourth (2.9
    cm) and the six other trousers within 0.8 cm ("End to end on ten seeds")."""
    if floor is None or len(garment_points) == 0:
        return []
    low = float(garment_points[:, 1].min())
    if low > FLOOR_REACH_M:
        return []
    return [
        f"the garment reaches the floor (its lowest scan points {100 * low:.1f} cm above it): where it "
        "pools or was cut off with the floor, the scan does not show where the pattern ends nor how wide its "
        "hem is; the fitted length and hem may be off by the cloth that pools (or, without the fit's floor, "
        "the length come out short with the body's height)"
    ]


def animation_warnings(assets_dir, seconds: float, anny_model=None) -> list[str]:
    """A warning when the assets in ``assets_dir`` blow up in a ``seconds`` [s] walk (`animate.animate`,
    `motion.WalkCycle`, its amplitudes ramped over half of it; nothing written). Assets that a simulator
    cannot move are not simulation-ready, however well they fit the scan: the fits of the captured trousers
    343 (docs/BENCHMARKS.md, "Trousers through the floor") blew up within 0.5 s; those of a dress, a T-shirt
    and a skirt, and the trousers template, did not. 0 s: no check. ``anny_model``: the fit's (or loaded)."""
    if seconds <= 0:
        return []
    from torch_diffavatar.animate import animate
    from torch_diffavatar.assets import load_assets
    from torch_diffavatar.errors import SimulationError
    from torch_diffavatar.motion import WalkCycle

    walk = WalkCycle(seconds, ramp=seconds / 2)
    assets = load_assets(assets_dir)
    try:
        summary = animate(
            assets, walk, None, duration=seconds, gif=False, write_body=False, anny_model=anny_model
        )
    except SimulationError as exc:
        said = f"the assets blew up in a {seconds:g} s walk ({exc}): the garment is not simulation-ready"
        return [said + _tangle_cause(assets)]
    if not summary["finite"]:
        return [f"the assets' cloth left the finite numbers in a {seconds:g} s walk: not simulation-ready"]
    return []


def _tangle_cause(assets) -> str:
    """What to say after a walk's blow-up: the drape's edges through the body (`sim.tangles`), where there
    are some, else that the fit probably went wrong."""
    from torch_diffavatar.sim.tangles import edges_through_body

    tangled = edges_through_body(
        assets.draped_x, assets.garment.sim_faces, assets.body_verts, assets.body_faces
    )
    if tangled.shape[0] == 0:
        return ", and the fit probably went wrong (look at before_after.png)"
    heights = assets.draped_x[tangled].mean(dim=1)[:, 1] - assets.body_verts[:, 1].min()
    lo, hi = (round(float(h) * 100) for h in (heights.min(), heights.max()))
    where = f"{lo} cm" if lo == hi else f"{lo}-{hi} cm"
    return (
        f" as it is: {tangled.shape[0]} edge(s) of its drape pass through the body, {where} above the soles "
        "(a part thinner than the cloth's edges, such as the toes, pokes through the cloth; moving, it drags "
        'them and tears the cloth: docs/BENCHMARKS.md, "Floor-length trousers in a walk")'
    )
