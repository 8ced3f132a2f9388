"""A hem's length read off a scan's opening points and off a pattern's rest shape, and the fit term that
keeps a fitted hem from being narrower than the scan shows (`torch_diffavatar.opening_lengths`)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torch_diffavatar.opening_lengths import (
    mirrored_lengths,
    opening_length_loss,
    opening_split_loss,
    rest_loop_edges,
    rest_loop_length,
    rest_loop_panels,
    rest_loop_shares,
    scan_loop_length,
)


def _ring(radius, n=2000, noise=0.0, wave=(0.0, 0), tilt=0.0, gap_deg=0.0, seed=0):
    """(n, 3) points around a hem-like loop of ``radius`` [m] at height 0.9 m: folds ``wave`` = (amplitude
    [m], count), a Gaussian ``noise`` [m], the loop tilted by ``tilt`` [rad] about X, points of a
    ``gap_deg`` sector left out. Returns (points, the noiseless loop's length [m])."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(0, 2 * np.pi, n))
    amp, k = wave
    r = radius + amp * np.sin(k * t)
    p = np.stack([r * np.cos(t), 0.9 + 0.01 * np.sin(2 * t), r * np.sin(t)], 1)
    fine = np.linspace(0, 2 * np.pi, 20001)
    rf = radius + amp * np.sin(k * fine)
    q = np.stack([rf * np.cos(fine), 0.01 * np.sin(2 * fine), rf * np.sin(fine)], 1)
    length = np.linalg.norm(np.diff(q, axis=0), axis=1).sum()
    c, s = np.cos(tilt), np.sin(tilt)
    p = p @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]]).T
    keep = np.degrees(t) >= gap_deg
    return p[keep] + rng.normal(0, noise, p[keep].shape), length


def test_scan_loop_length_of_a_noisy_folded_ring():
    # a 1.2 m hem with 8 folds of 1.5 cm (15 cm wavelength), 3 mm noise, tilted 20 degrees
    points, truth = _ring(0.19, noise=0.003, wave=(0.015, 8), tilt=math.radians(20))
    length, coverage = scan_loop_length(points)
    assert coverage == 1.0
    assert truth > 2 * math.pi * 0.19 * 1.05  # the folds add length a circle would not have
    assert length == pytest.approx(truth, rel=0.01)
    # folds finer than a few bins are smoothed away: shorter, never longer (14 folds: 8.5 cm wavelength)
    points, truth = _ring(0.19, noise=0.003, wave=(0.015, 14), tilt=math.radians(20))
    assert 0.9 * truth < scan_loop_length(points)[0] < truth


def test_scan_loop_length_is_short_where_the_scan_has_a_hole():
    full, _ = scan_loop_length(_ring(0.19, noise=0.003, wave=(0.015, 14))[0])
    holed, coverage = scan_loop_length(_ring(0.19, noise=0.003, wave=(0.015, 14), gap_deg=60)[0])
    assert 300 / 360 - 0.01 < coverage < 0.9  # the centroid moves away from the hole: it looks narrower
    assert holed < full  # a chord crosses the hole: a lower bound


def _ring_loop(radius, n=200):
    """(n, 3) a garment opening's vertices in loop order: a circle of ``radius`` [m] at height 0.9 m."""
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([radius * np.cos(t), np.full(n, 0.9), radius * np.sin(t)], 1)


def test_scan_loop_length_bridges_a_hole_with_the_reference_curve():
    """A hole over 120 degrees of a hem: the chord across it makes the trace short; with the garment's own
    opening as the reference (a smaller ring: only its shape counts) the hole is bridged by an arc, and
    the length is the loop's. Folds the hole hides are not guessed (the reference has none): between the
    two. A whole loop keeps its trace."""
    points, truth = _ring(0.19, noise=0.003, gap_deg=120)
    chord, _ = scan_loop_length(points)
    length, coverage = scan_loop_length(points, reference=_ring_loop(0.16))
    assert coverage < 0.8
    assert chord < 0.95 * truth
    assert length == pytest.approx(truth, rel=0.01)
    points, truth = _ring(0.19, noise=0.003, wave=(0.015, 8), gap_deg=120)
    chord, _ = scan_loop_length(points)
    assert chord < scan_loop_length(points, reference=_ring_loop(0.16))[0] < truth
    whole = _ring(0.19, noise=0.003, wave=(0.015, 8))[0]
    assert scan_loop_length(whole, reference=_ring_loop(0.16)) == scan_loop_length(whole)


def test_scan_loop_length_with_a_reference_keeps_a_sparse_opening_with_a_gap():
    """A waistband of 91 points (12 bins of 30 degrees) missing one bin: without a reference every bin
    must hold points (nan); with one, its length. A reference is no licence to guess: a scan showing less
    than ``min_seen`` of the loop (a front-only capture's half hem) keeps the chord's lower bound."""
    points, truth = _ring(0.135, n=100, noise=0.003, gap_deg=40, seed=1)
    assert math.isnan(scan_loop_length(points)[0])
    assert scan_loop_length(points, reference=_ring_loop(0.14))[0] == pytest.approx(truth, rel=0.03)
    half, truth = _ring(0.19, noise=0.003, gap_deg=180)
    chord, _ = scan_loop_length(half)
    assert chord < 0.85 * truth
    assert scan_loop_length(half, reference=_ring_loop(0.19))[0] == chord
    with pytest.raises(ValueError, match="reference"):
        scan_loop_length(points, reference=np.zeros((10, 2)))


def test_scan_loop_length_of_a_sparse_band_takes_longer_bins():
    """320 points of a hem band 5 cm tall that flares by 2 cm (a sparse scan's hem): 2 cm bins of a few
    points each jitter in radius and height from bin to bin (+12-22 % on five draws); bins of at least
    ``points_per_bin`` points keep it within 5 %."""
    rng = np.random.default_rng(3)
    t, h = rng.uniform(0, 2 * np.pi, 320), rng.uniform(0, 0.05, 320)
    r = 0.22 - 0.4 * h
    points = np.stack([r * np.cos(t), 0.8 + h, r * np.sin(t)], 1) + rng.normal(0, 0.0015, (320, 3))
    mid = 2 * np.pi * 0.21
    assert scan_loop_length(points, points_per_bin=1)[0] > 1.1 * mid
    assert scan_loop_length(points)[0] == pytest.approx(mid, rel=0.05)


def test_scan_loop_length_needs_points():
    assert math.isnan(scan_loop_length(np.zeros((5, 3)))[0])
    with pytest.raises(ValueError, match=r"\(k, 3\)"):
        scan_loop_length(np.zeros((40, 2)))
    with pytest.raises(ValueError, match="bin_length"):
        scan_loop_length(np.zeros((40, 3)), bin_length=0.0)


@pytest.mark.parametrize("template", ["dress", "pants"])
def test_rest_loop_length_is_the_patterns_hem(template):
    from torch_diffavatar.pattern import load_template, mesh_pattern
    from torch_diffavatar.pattern.measurements import measure_pattern

    pattern = load_template(template)
    garment = mesh_pattern(pattern, spacing=0.03)
    measured = measure_pattern(pattern).lengths
    hems = [lp for lp in garment.boundary_loops if lp.name.startswith("hem")]
    assert hems
    for loop in hems:
        length = rest_loop_length(garment.vert_uv, rest_loop_edges(garment, loop))
        assert float(length) == pytest.approx(measured[f"{loop.name}_circumference"], rel=1e-9)


def test_rest_loop_edges_refuses_another_garments_loop():
    from torch_diffavatar.pattern import load_template, mesh_pattern
    from torch_diffavatar.pattern.garment_mesh import BoundaryLoop

    garment = mesh_pattern(load_template("skirt"), spacing=0.1)
    with pytest.raises(ValueError, match="no panel outline"):
        rest_loop_edges(garment, BoundaryLoop("hem", torch.tensor([0, 5, 9])))


def test_opening_length_loss_is_one_sided_and_its_gradient_checks():
    from torch_diffavatar.pattern import load_template, mesh_pattern

    garment = mesh_pattern(load_template("skirt"), spacing=0.1)
    hem = next(lp for lp in garment.boundary_loops if lp.name == "hem")
    edges = [rest_loop_edges(garment, hem)]
    uv = garment.vert_uv.double()
    length = float(rest_loop_length(uv, edges[0]))
    assert float(opening_length_loss(uv, edges, torch.tensor([0.9 * length]))) == 0.0
    short = opening_length_loss(uv, edges, torch.tensor([1.1 * length], dtype=torch.float64))
    assert float(short) == pytest.approx((0.1 / 1.1) ** 2, rel=1e-9)
    x = uv.clone().requires_grad_()
    least = torch.tensor([1.1 * length], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda u: opening_length_loss(u, edges, least), (x,))
    opening_length_loss(x, edges, least).backward()
    step = x.detach() - 0.01 * x.grad  # a step down the loss lengthens the hem
    assert float(rest_loop_length(step, edges[0])) > length
    with pytest.raises(ValueError, match="openings"):
        opening_length_loss(uv, edges, torch.tensor([1.0, 2.0]))


def test_objective_holds_a_hem_no_narrower_than_the_scan_shows():
    """The skirt's scan hem 20 % wider than the template's: with the weight the rest terms hold an
    ``opening_length`` term that the template pays and whose gradient widens the hem; without it, none."""
    from dataclasses import replace

    from helpers_fit import fit_config

    from torch_diffavatar import fit_report
    from torch_diffavatar.fit_config import LossWeights
    from torch_diffavatar.objective import FitObjective, ScanTarget
    from torch_diffavatar.pattern import load_template, mesh_pattern

    garment = mesh_pattern(load_template("skirt"), spacing=0.1)
    hem = next(lp for lp in garment.boundary_loops if lp.name == "hem")
    template = float(rest_loop_length(garment.vert_uv, rest_loop_edges(garment, hem)))
    wide = torch.as_tensor(_ring(1.2 * template / (2 * math.pi), n=600)[0])  # a hem 20 % longer
    target = ScanTarget(wide, {"hem": wide})
    off = FitObjective(garment, target, fit_config(), dtype=torch.float64)
    assert "opening_length" not in off.rest_terms(off.template_uv)
    cfg = fit_config(weights=replace(LossWeights(), opening_length=1000.0))
    on = FitObjective(garment, target, cfg, dtype=torch.float64)
    assert on.opening_names == ["hem"]
    only_waist = replace(cfg, opening_length_names=("waist",))  # the openings held are the config's
    assert FitObjective(garment, target, only_waist, dtype=torch.float64).opening_names == []
    traced = float(on.opening_least[0]) / (1 - cfg.opening_length_tolerance)
    assert traced == pytest.approx(1.2 * template, rel=0.01)
    uv = on.template_uv.clone().requires_grad_()
    term = on.rest_terms(uv)["opening_length"]
    assert float(term.detach()) > 0
    term.backward()
    wider = uv.detach() - 0.01 * uv.grad
    assert float(rest_loop_length(wider, on.opening_edges[0])) > template
    # the report's record of it (`report.json`'s ``opening_lengths``), with the term on or off
    for objective in (on, off):
        lengths = fit_report.opening_lengths(objective, objective.template_uv, wider)
        assert list(lengths) == ["hem"]
        assert lengths["hem"]["scan"] == pytest.approx(traced, rel=1e-12)
        assert lengths["hem"]["initial"] == pytest.approx(template, rel=1e-12)
        assert lengths["hem"]["final"] > template


def test_a_mirrored_pair_of_openings_is_held_to_the_better_seen_trace():
    # Newton's trousers of seed 0: the left hem seen whole, the right 86 % and traced 5.6 cm longer
    held = mirrored_lengths({"hem_left": (0.702, 1.0), "hem_right": (0.758, 0.86), "waist": (0.83, 1.0)})
    assert held["hem_left"] == held["hem_right"] == (0.702, ["hem_left"])
    assert held["waist"] == (0.83, ["waist"])
    both = mirrored_lengths({"cuff_left": (0.30, 0.9), "cuff_right": (0.32, 0.9)})  # seen alike: the mean
    assert both["cuff_left"][0] == both["cuff_right"][0] == pytest.approx(0.31)
    assert both["cuff_right"][1] == ["cuff_left", "cuff_right"]
    alone = mirrored_lengths({"hem_left": (math.nan, 0.3), "hem_right": (0.7, 0.9)})  # one traced none
    assert alone["hem_right"] == (0.7, ["hem_right"]) and math.isnan(alone["hem_left"][0])
    assert alone["hem_left"][1] == ["hem_left"]


def test_objective_holds_tied_trouser_hems_to_the_better_seen_trace():
    """Trousers with their legs' panels mirror-tied have one hem length: the objective holds both hems to
    the left's trace, seen whole, not to the right's, seen in part and longer; the report says whose trace
    it is and does not warn of the right's gap. Untied, each hem is held to its own."""
    from dataclasses import replace

    from helpers_fit import fit_config

    from torch_diffavatar import fit_report
    from torch_diffavatar.fit_config import LossWeights
    from torch_diffavatar.objective import FitObjective, ScanTarget
    from torch_diffavatar.pattern import load_template, mesh_pattern

    garment = mesh_pattern(load_template("pants"), spacing=0.08)
    placed = garment.sim_positions().double()
    rings = {}
    for name, scale, gap in (("hem_left", 1.0, 0.0), ("hem_right", 1.08, 50.0)):
        loop = next(lp for lp in garment.boundary_loops if lp.name == name)
        template = float(rest_loop_length(garment.vert_uv.double(), rest_loop_edges(garment, loop)))
        ring = _ring(scale * template / (2 * math.pi), n=600, gap_deg=gap)[0]
        rings[name] = torch.as_tensor(ring - [0.0, 0.9, 0.0]) + placed[loop.vertices].mean(0)
    target = ScanTarget(torch.cat(list(rings.values())), rings)
    cfg = fit_config(weights=replace(LossWeights(), opening_length=1000.0), opening_length_names=tuple(rings))
    tied = FitObjective(garment, target, cfg, dtype=torch.float64)
    untied = FitObjective(garment, target, replace(cfg, tie_mirrored=False), dtype=torch.float64)
    left, right = (tied.opening_names.index(n) for n in rings)
    assert tied.opening_seen[left] == 1.0 and tied.opening_seen[right] < 0.95
    assert tied.opening_traced[right] > 1.05 * tied.opening_traced[left]
    assert float(tied.opening_least[right]) == float(tied.opening_least[left])
    assert float(tied.opening_least[left]) == pytest.approx(tied.opening_traced[left], rel=1e-9)
    assert float(untied.opening_least[right]) == pytest.approx(untied.opening_traced[right], rel=1e-9)
    lengths = fit_report.opening_lengths(tied, tied.template_uv, tied.template_uv)
    assert lengths["hem_right"]["held_to"] == lengths["hem_left"]["held_to"] == ["hem_left"]
    assert fit_report.gapped_opening_warnings(lengths) == []
    untied_lengths = fit_report.opening_lengths(untied, untied.template_uv, untied.template_uv)
    (gapped,) = fit_report.gapped_opening_warnings(untied_lengths)
    assert "the hem_right (" in gapped


def test_the_openings_held_are_a_list_of_names():
    from torch_diffavatar.errors import InputError
    from torch_diffavatar.fit_config import config_from_dict

    assert config_from_dict({"opening_length_names": ["hem", "waist"]}).opening_length_names == (
        "hem",
        "waist",
    )
    for bad in ("waist", [1], [""]):
        with pytest.raises(InputError, match="opening_length_names"):
            config_from_dict({"opening_length_names": bad})


def test_opening_split_loss_holds_the_templates_split_and_its_gradient_checks():
    """The dress's hem lies on its front and back skirt panels. Widening both alike keeps the split (0);
    moving hem from the back panel to the front costs, and the gradient moves it back; gradcheck."""
    from torch_diffavatar.pattern import load_template, mesh_pattern

    garment = mesh_pattern(load_template("dress"), spacing=0.05)
    hem = next(lp for lp in garment.boundary_loops if lp.name == "hem")
    edges = [rest_loop_edges(garment, hem)]
    panels = [rest_loop_panels(garment, edges[0])]
    names = {garment.panel_names[int(garment.vert_panel[v])] for v in edges[0][:, 0]}
    assert names == {"skirt_front", "skirt_back"} and sorted(set(panels[0].tolist())) == [0, 1]
    uv = garment.vert_uv.double()
    shares = [rest_loop_shares(uv, edges[0], panels[0])]
    assert float(shares[0].sum()) == pytest.approx(1.0, rel=1e-12)
    assert float(opening_split_loss(uv * 1.1, edges, panels, shares)) == pytest.approx(0.0, abs=1e-20)
    front = garment.panel_names.index("skirt_front")
    on_front = (garment.vert_panel == front)[:, None]
    moved = torch.where(
        on_front, uv * torch.tensor([1.05, 1.0], dtype=uv.dtype), uv * torch.tensor([0.95, 1.0])
    )
    loss = opening_split_loss(moved, edges, panels, shares)
    assert float(loss) > 1e-4
    x = moved.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda u: opening_split_loss(u, edges, panels, shares), (x,))
    opening_split_loss(x, edges, panels, shares).backward()
    step = x.detach() - 0.1 * x.grad
    assert float(opening_split_loss(step, edges, panels, shares)) < float(loss)
    with pytest.raises(ValueError, match="openings"):
        opening_split_loss(uv, edges, panels, [])


def test_objective_holds_the_split_only_with_its_weight():
    from dataclasses import replace

    from helpers_fit import fit_config

    from torch_diffavatar.fit_config import LossWeights
    from torch_diffavatar.objective import FitObjective, ScanTarget
    from torch_diffavatar.pattern import load_template, mesh_pattern

    garment = mesh_pattern(load_template("skirt"), spacing=0.1)
    ring = torch.as_tensor(_ring(0.25, n=600)[0])
    target = ScanTarget(ring, {"hem": ring})
    weights = replace(LossWeights(), opening_length=1000.0)
    off = FitObjective(garment, target, fit_config(weights=weights), dtype=torch.float64)
    assert "opening_split" not in off.rest_terms(off.template_uv)
    on = FitObjective(
        garment, target, fit_config(weights=replace(weights, opening_split=1e4)), dtype=torch.float64
    )
    assert float(on.rest_terms(on.template_uv)["opening_split"]) == pytest.approx(0.0, abs=1e-20)
    assert len(on.opening_shares) == 1 and len(on.opening_shares[0]) == 2


def test_a_partial_scan_holds_an_opening_no_shorter_than_the_template():
    """A front-only capture shows half a hem: its chord traces it short, and the fits narrowed the half they
    did not see (a dress's hem 28.7 cm short). On a partial scan (``seen_sides``) the hem is held no
    shorter than the template's; a full scan of the same points holds it to their trace; a partial scan
    whose hem traces no length still holds the template's (the report: no ``scan`` length, its ``least``)."""
    from dataclasses import replace

    from helpers_fit import fit_config

    from torch_diffavatar import fit_report
    from torch_diffavatar.fit_config import LossWeights
    from torch_diffavatar.objective import FitObjective, ScanTarget
    from torch_diffavatar.pattern import load_template, mesh_pattern

    garment = mesh_pattern(load_template("skirt"), spacing=0.1)
    hem = next(lp for lp in garment.boundary_loops if lp.name == "hem")
    template = float(rest_loop_length(garment.vert_uv.double(), rest_loop_edges(garment, hem)))
    half = torch.as_tensor(_ring(template / (2 * math.pi), n=1200, gap_deg=180)[0])  # the front half
    cfg = fit_config(weights=replace(LossWeights(), opening_length=1000.0))
    seen = torch.tensor([True] * 4 + [False] * 4)
    full = FitObjective(garment, ScanTarget(half, {"hem": half}), cfg, dtype=torch.float64)
    partial = FitObjective(
        garment, ScanTarget(half, {"hem": half}, seen_sides=seen), cfg, dtype=torch.float64
    )
    assert float(full.opening_least[0]) < 0.85 * template
    # the share of the loop the half shows: its angular bins about its own centre (more than half of them)
    assert fit_report.opening_lengths(full, full.template_uv, full.template_uv)["hem"]["seen"] < 0.8
    assert float(partial.opening_least[0]) == pytest.approx(template, rel=1e-9)
    few = half[:10]  # too few points for a length
    none = FitObjective(garment, ScanTarget(half, {"hem": few}, seen_sides=seen), cfg, dtype=torch.float64)
    assert none.opening_names == ["hem"] and math.isnan(none.opening_traced[0])
    lengths = fit_report.opening_lengths(none, none.template_uv, none.template_uv)
    assert lengths["hem"]["scan"] is None and lengths["hem"]["least"] == pytest.approx(template, rel=1e-6)
    assert FitObjective(garment, ScanTarget(half, {"hem": few}), cfg, dtype=torch.float64).opening_names == []


def test_a_neck_held_to_the_template_whatever_the_scan_shows():
    """``opening_template_names``: the scan cannot measure a neck, and the fits shrank necks they started
    right through the curvature term's local scale (and grew a dress's armholes onto the rims of holes under
    the arms). Held to the template's length whether or not the scan shows a neck: a smaller neck pays and
    its gradient widens it; a larger one pays nothing (``opening_template_hold`` ``"least"``, the default)
    or pays and its gradient narrows it (``"exact"``); the report records it
    as the template's (``template``; no ``scan`` length, no ``seen``: valid JSON) and a partial scan's
    warning does not name it among the openings the scan shows too little of."""
    import json
    from dataclasses import replace

    from helpers_fit import fit_config

    from torch_diffavatar import fit_report
    from torch_diffavatar.fit_config import LossWeights
    from torch_diffavatar.objective import FitObjective, ScanTarget
    from torch_diffavatar.pattern import load_template, mesh_pattern

    garment = mesh_pattern(load_template("tshirt"), spacing=0.08)
    neck = next(lp for lp in garment.boundary_loops if lp.name == "neck")
    edges = rest_loop_edges(garment, neck)
    template = float(rest_loop_length(garment.vert_uv.double(), edges))
    small = torch.as_tensor(_ring(0.6 * template / (2 * math.pi), n=600)[0])  # a scan neck 40 % short
    cfg = fit_config(weights=replace(LossWeights(), opening_length=1000.0), opening_template_names=["neck"])
    assert cfg.opening_template_names == ("neck",)
    seen = torch.tensor([True] * 4 + [False] * 4)
    for boundaries, sides in (({"neck": small}, None), ({}, None), ({"neck": small}, seen)):
        objective = FitObjective(
            garment, ScanTarget(small, boundaries, seen_sides=sides), cfg, dtype=torch.float64
        )
        assert "neck" in objective.opening_names
        k = objective.opening_names.index("neck")
        assert float(objective.opening_least[k]) == pytest.approx(template, rel=1e-9)
        assert math.isinf(float(objective.opening_most[k]))
    assert (
        "neck"
        not in FitObjective(
            garment, ScanTarget(small, {"neck": small}), fit_config(), dtype=torch.float64
        ).opening_names
    )
    exact = FitObjective(
        garment,
        ScanTarget(small, {"neck": small}),
        replace(cfg, opening_template_hold="exact"),
        dtype=torch.float64,
    )
    assert float(exact.opening_most[exact.opening_names.index("neck")]) == pytest.approx(template, rel=1e-9)
    uv = objective.template_uv.clone()
    centre = uv[neck.vertices].mean(0)
    for held, scale, pays in (
        (objective, 0.9, True),
        (objective, 1.1, False),
        (exact, 0.9, True),
        (exact, 1.1, True),
    ):
        moved = uv.clone()
        moved[neck.vertices] = centre + scale * (uv[neck.vertices] - centre)
        moved.requires_grad_()
        term = held.rest_terms(moved)["opening_length"]
        assert (float(term.detach()) > 0) == pays
        if pays:
            term.backward()
            stepped = float(rest_loop_length(moved.detach() - 0.01 * moved.grad, edges))
            before = float(rest_loop_length(moved.detach(), edges))
            assert abs(stepped - template) < abs(before - template), scale  # toward the template's length
    assert float(exact.rest_terms(uv)["opening_length"]) == 0
    lengths = fit_report.opening_lengths(objective, uv, uv)
    assert lengths["neck"]["template"] and lengths["neck"]["scan"] is None and lengths["neck"]["seen"] is None
    assert lengths["neck"]["most"] is None
    assert fit_report.opening_lengths(exact, uv, uv)["neck"]["most"] == pytest.approx(template, rel=1e-6)
    json.dumps(lengths, allow_nan=False)
    report = {"chamfer_final": 0.0, "boundary_chamfer_final": {}, "opening_lengths": lengths}
    coverage = {"sectors_seen": 4, "sectors": 8}
    assert not any("neck" in w for w in fit_report.scan_warnings(report, small, coverage))


def test_hems_the_floor_cut_off_are_held_at_the_starts_length():
    """Trousers piled on the floor show no hem; the set-up measured their legs above it and started the
    pattern there (`fit_design.floor_cut_hems`), and the fit holds those hems at the start's length, neither
    shorter nor longer, whatever ``opening_template_hold`` (unheld, a fit widened them 8.2 cm past it)."""
    from dataclasses import replace

    from helpers_fit import fit_config

    from torch_diffavatar.fit_config import LossWeights
    from torch_diffavatar.objective import FitObjective, ScanTarget
    from torch_diffavatar.pattern import load_template, mesh_pattern

    garment = mesh_pattern(load_template("pants"), spacing=0.08)
    cfg = fit_config(weights=replace(LossWeights(), opening_length=1000.0))
    assert cfg.opening_template_hold == "least"
    points = garment.sim_positions().double()
    cut = ("hem_left", "hem_right")
    held = FitObjective(garment, ScanTarget(points, {}, held_openings=cut), cfg, dtype=torch.float64)
    for name in cut:
        loop = next(lp for lp in garment.boundary_loops if lp.name == name)
        start = float(rest_loop_length(garment.vert_uv.double(), rest_loop_edges(garment, loop)))
        k = held.opening_names.index(name)
        assert float(held.opening_least[k]) == pytest.approx(start, rel=1e-9)
        assert float(held.opening_most[k]) == pytest.approx(start, rel=1e-9)
    free = FitObjective(garment, ScanTarget(points, {}), cfg, dtype=torch.float64)
    assert not set(cut) & set(free.opening_names)
