"""`segment._grow_on_support`: garment labels grow over the k-NN graph into connected open points only."""

from __future__ import annotations

import numpy as np
from helpers_body import sampled_default_body
from scipy.spatial import cKDTree

from torch_diffavatar.body.segment import _grow_on_support


def _grid(n: int = 40, spacing: float = 0.01) -> np.ndarray:
    """(n², 3) points of a flat n × n grid in the x-y plane [m]."""
    x, y = np.meshgrid(np.arange(n) * spacing, np.arange(n) * spacing, indexing="ij")
    return np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], axis=1)


def _nbr(points: np.ndarray, k: int = 9) -> np.ndarray:
    return cKDTree(points).query(points, k=k)[1]


def test_growth_fills_the_open_points_the_labels_touch_and_stops_at_the_rest():
    p = _grid()
    x, y = p[:, 0], p[:, 1]
    labels = x < 0.1  # the confident garment: a strip on the left
    open_touching = (x >= 0.1) & (x < 0.2)  # continues the strip (a bodice within the threshold)
    closed = (x >= 0.2) & (x < 0.25)  # skin: a rim the growth must not cross
    open_beyond = x >= 0.25  # open again, but reachable only across the skin
    grown = _grow_on_support(labels, open_touching | open_beyond, _nbr(p))
    assert grown[labels].all() and grown[open_touching].all()
    assert not grown[closed].any() and not grown[open_beyond].any()
    # an open island not touching the labels stays out; no labels: nothing grows
    island = (x > 0.3) & (y > 0.3)
    assert not _grow_on_support(labels, island, _nbr(p))[island].any()
    assert not _grow_on_support(np.zeros(len(p), bool), np.ones(len(p), bool), _nbr(p)).any()


def test_trousers_waistband_on_the_torso_is_garment_below_the_waist_only(anny_model):
    """Trousers tight from the hips to a waistband on the torso (3 mm off the skin, under the 5 mm
    offset threshold), loose on the legs: with the body's waist height (`support_top`) the labels grow
    from the legs over the hips and up the torso to the waistband, not onto the bare torso above it;
    without it they stop where Anny's hips part ends."""
    from torch_diffavatar.body.segment import segment_garment

    sampled = sampled_default_body(anny_model)
    points, name, waist = sampled.points, sampled.name, sampled.waist
    verts, faces, parts = sampled.verts, sampled.faces, sampled.parts
    legs = np.isin(name, ["thigh.L", "thigh.R", "shin.L", "shin.R"])
    band = (name == "torso") & (points[:, 1] < waist - 0.03)  # the waistband and what lies under it
    tight = (name == "hips") | band
    offset = np.where(legs, 0.02, np.where(tight, 0.003, 0.0))
    points = points + offset[:, None] * sampled.normals
    bare_torso = (name == "torso") & (points[:, 1] > waist)
    without = segment_garment(points, "pants", verts, faces, parts).labels
    with_waist = segment_garment(points, "pants", verts, faces, parts, support_top=waist).labels
    assert with_waist[legs].mean() > 0.95 and without[legs].mean() > 0.95
    assert with_waist[band].mean() > 0.8 > 0.2 > without[band].mean()
    assert with_waist[bare_torso].mean() < 0.02
