"""Colour-aware segmentation (issue #29 item 3): `body.colour` and `segment_garment` with colours."""

from __future__ import annotations

import numpy as np
import pytest
from helpers_body import sampled_default_body

from torch_diffavatar.body.colour import GaussianMixture, graph_cut, knn_edges, rgb_to_lab

SKIN, SHIRT, TROUSERS = (222, 171, 140), (235, 235, 235), (30, 30, 36)


def test_rgb_to_lab_reference_values():
    lab = rgb_to_lab(np.array([[255, 255, 255], [0, 0, 0], [255, 0, 0]], np.uint8))
    np.testing.assert_allclose(lab[0], [100.0, 0.0, 0.0], atol=0.01)
    np.testing.assert_allclose(lab[1], [0.0, 0.0, 0.0], atol=0.01)
    np.testing.assert_allclose(lab[2], [53.24, 80.09, 67.20], atol=0.02)  # sRGB red, D65


def test_mixture_tells_two_colours_apart():
    rng = np.random.default_rng(0)
    a = rng.normal([50.0, 10.0, 10.0], 2.0, (400, 3))
    b = np.concatenate(
        [rng.normal([20.0, -5.0, 0.0], 2.0, (200, 3)), rng.normal([80.0, 0.0, 30.0], 2.0, (200, 3))]
    )
    ga, gb = GaussianMixture.fit(a), GaussianMixture.fit(b)
    assert (ga.log_density(a) > gb.log_density(a)).all() and (gb.log_density(b) > ga.log_density(b)).all()


def test_graph_cut_matches_brute_force_on_a_small_graph():
    rng = np.random.default_rng(3)
    n = 10
    nbr = np.stack([np.arange(n), (np.arange(n) + 1) % n, (np.arange(n) + 3) % n], 1)
    edge_i, edge_j = knn_edges(nbr, 2)
    for _ in range(5):
        evidence = rng.normal(0.0, 1.5, n).round(2)
        weight = rng.uniform(0.0, 1.0, len(edge_i)).round(2)
        allowed = rng.random(n) > 0.2
        best_cost = np.inf
        for code in range(2**n):
            lab = ((code >> np.arange(n)) & 1).astype(bool)
            if (lab & ~allowed).any():
                continue
            cost = np.where(lab, np.clip(-evidence, 0, None), np.clip(evidence, 0, None)).sum()
            cost += weight[lab[edge_i] != lab[edge_j]].sum()
            if cost < best_cost - 1e-9:
                best_cost = cost
        got = graph_cut(evidence, allowed, edge_i, edge_j, weight)
        got_cost = np.where(got, np.clip(-evidence, 0, None), np.clip(evidence, 0, None)).sum()
        got_cost += weight[got[edge_i] != got[edge_j]].sum()
        assert got_cost == pytest.approx(best_cost, abs=0.02)
        assert not (got & ~allowed).any()


@pytest.fixture(scope="module")
def outfit(anny_model):
    """A white T-shirt over dark trousers on the default body, sampled (20k points, 2 mm noise): the
    shirt 2 cm off the torso above the waist and over the upper arms, the trousers 1.5 cm off the hips,
    legs and torso below the waist; the rest is skin, and the hands stand 1 cm off the body (a body fit
    off there: geometry alone takes them for sleeve cloth). Returns the scan and the body."""
    sampled = sampled_default_body(anny_model)
    points, name, waist = sampled.points, sampled.name, sampled.waist
    torso = name == "torso"
    shirt = (torso & (points[:, 1] >= waist)) | np.isin(name, ["upperarm.L", "upperarm.R"])
    legs = np.isin(name, ["hips", "thigh.L", "thigh.R", "shin.L", "shin.R"])
    trousers = legs | (torso & (points[:, 1] < waist))
    hands = np.isin(name, ["hand.L", "hand.R", "forearm.L", "forearm.R"])
    offset = np.where(shirt, 0.02, np.where(trousers, 0.015, np.where(hands, 0.01, 0.0)))
    rng = np.random.default_rng(1)
    points = points + (offset + rng.normal(0.0, 0.002, len(points)))[:, None] * sampled.normals
    colors = np.where(shirt[:, None], SHIRT, np.where(trousers[:, None], TROUSERS, SKIN))
    colors = np.clip(colors + rng.normal(0.0, 4.0, colors.shape), 0, 255).astype(np.uint8)
    return dict(points=points, colors=colors, shirt=shirt, trousers=trousers, hands=hands,
                verts=sampled.verts, faces=sampled.faces, parts=sampled.parts, waist=waist)  # fmt: skip


def _segment(scan, garment, **kw):
    from torch_diffavatar.body.segment import segment_garment

    return segment_garment(
        scan["points"], garment, scan["verts"], scan["faces"], scan["parts"], support_top=scan["waist"], **kw
    )


def _precision_recall(pred, truth):
    tp = (pred & truth).sum()
    return tp / max(pred.sum(), 1), tp / max(truth.sum(), 1)


def test_colour_separates_a_shirt_from_trousers_and_hands_geometry_cannot(outfit):
    """Geometry alone takes the trousers and the forearms for T-shirt (both stand off the body within its
    region); the colour models learned from the shirt's torso and the rest tell them apart."""
    geometry = _segment(outfit, "tshirt", colors=outfit["colors"], use_colour=False).labels
    seg = _segment(outfit, "tshirt", colors=outfit["colors"])
    colour = seg.labels
    assert seg.colour_separability > 0.9
    precision, recall = _precision_recall(colour, outfit["shirt"])
    assert precision >= 0.95 and recall >= 0.95
    assert _precision_recall(geometry, outfit["shirt"])[0] < 0.8
    assert colour[outfit["hands"]].mean() < 0.02 < 0.5 < geometry[outfit["hands"]].mean()
    # the trousers, from their thighs, the same way
    precision, recall = _precision_recall(
        _segment(outfit, "pants", colors=outfit["colors"]).labels, outfit["trousers"]
    )
    assert precision >= 0.95 and recall >= 0.95


@pytest.mark.parametrize("same_as", ["skin", "trousers"])
def test_a_garment_the_colour_of_the_skin_or_the_trousers_is_segmented_as_without_colour(outfit, same_as):
    """Colours that do not tell the shirt apart fall back on geometry: the labels are those without
    colour (nothing worse than before)."""
    colors = outfit["colors"].copy()
    source = outfit["trousers"] if same_as == "trousers" else ~(outfit["shirt"] | outfit["trousers"])
    colors[outfit["shirt"]] = colors[source][: outfit["shirt"].sum()]
    seg = _segment(outfit, "tshirt", colors=colors)
    with_colour, without = seg.labels, _segment(outfit, "tshirt").labels
    if same_as == "skin":
        assert seg.colour_separability is None  # the colour models stood aside
        np.testing.assert_array_equal(with_colour, without)
    else:  # the trousers still differ from the skin: never worse than geometry
        truth = outfit["shirt"]
        assert sum(_precision_recall(with_colour, truth)) >= sum(_precision_recall(without, truth)) - 0.01
