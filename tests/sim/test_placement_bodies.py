"""Placement on the random bodies of `make_draped_scan` (issue 7's suite), not only on the default body."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torch_diffavatar.body.frames import anny_to_world
from torch_diffavatar.pattern.library import load_template
from torch_diffavatar.pattern.mesher import mesh_pattern
from torch_diffavatar.sim.placement import body_landmarks, body_signed_distance, place_garment
from torch_diffavatar.synthetic_scans import DEFAULT_PHENOTYPE_RANGE


def _suite_body(anny_model, seed: int):
    """The body `make_draped_scan(seed=seed)` drapes on: (verts (Vb, 3) float64 [m], faces (Fb, 3))."""
    gen = torch.Generator().manual_seed(seed)
    lo, hi = DEFAULT_PHENOTYPE_RANGE
    phen = (lo + (hi - lo) * torch.rand(1, 6, generator=gen)).to(torch.float64)
    with torch.no_grad():
        verts = anny_to_world(anny_model(phenotype_kwargs=phen)["vertices"][0])
    verts = verts - verts.new_tensor([0.0, 1.0, 0.0]) * verts[:, 1].min()
    return verts, anny_model.faces


@pytest.mark.anny
@pytest.mark.parametrize("seed", [0, 6])
def test_ear_lobes_are_not_armpits(seed, anny_model):
    """On these bodies the ear lobes hang below 90 % of the height, as a separate loop either side of the
    head: the armpit was taken there (above the shoulders), the torso wrap then ended below the real
    shoulders, and every top failed to sew (strain blow-ups, 4-17 cm open shoulder seams)."""
    verts, faces = _suite_body(anny_model, seed)
    lm = body_landmarks(verts, faces)
    assert lm.crotch_y < lm.waist_y < lm.armpit_y < lm.shoulder_y < lm.neck_y
    for arm, sign in ((lm.arm_left, 1.0), (lm.arm_right, -1.0)):
        assert arm is not None
        assert arm[0, 1] < lm.shoulder_y  # the shoulder joint, below the acromion level
        assert sign * arm[-1, 0] > 0.3 and arm[-1, 1] < lm.armpit_y - 0.2  # the wrist: out and down
    # the arms are separate from the torso just below the armpit, and joined to it just above
    sec = lm._sections
    i = int(np.searchsorted(sec.heights, lm.armpit_y))
    assert all(sec.arms[i - 2]) and not all(sec.arms[i + 2])


@pytest.mark.anny
def test_tshirt_starts_over_the_shoulders_of_a_suite_body(anny_model):
    verts, faces = _suite_body(anny_model, 0)
    lm = body_landmarks(verts, faces)
    garment = mesh_pattern(load_template("tshirt"), spacing=0.03)
    pos = place_garment(garment, verts, faces, body_landmarks=lm).vert_pos.numpy()
    assert body_signed_distance(pos, verts, faces).min() >= 0.01 - 1e-6
    names, vp = garment.panel_names, garment.vert_panel.numpy()
    torso = np.array(["torso" in names[p] for p in vp])
    # the shoulder seams (the torso panels' tops) start above the shoulders, not down at chest level
    assert pos[torso, 1].max() > lm.shoulder_y + 0.02
    pairs = garment.stitch_pairs.numpy()
    shoulder = pairs[torso[pairs[:, 0]] & torso[pairs[:, 1]]]
    shoulder = shoulder[pos[shoulder[:, 0], 1] > lm.armpit_y]
    mid = 0.5 * (pos[shoulder[:, 0]] + pos[shoulder[:, 1]])
    assert len(mid) and body_signed_distance(mid, verts, faces).min() >= 0.015 - 1e-6
