"""Sewing's stall rule: a seam held open just beyond the snap distance gets snapped shut."""

from __future__ import annotations

import torch

from torch_diffavatar.sim.forward_drape import DrapeConfig, max_stitch_gap, sew
from torch_diffavatar.sim.model import ClothModelBuilder
from torch_diffavatar.sim.solver import XPBDConfig
from torch_diffavatar.sim.testing import tube_garment


def _sew(**overrides):
    # no bounded pull at all: only the snap can close a gap (like a seam pair that a pleat holds open)
    g = tube_garment(nx=4, ny=4, width=0.2, height=0.2, gap=0.02, y0=1.0)
    model = ClothModelBuilder().add_garment(g, merge_seams=False).finalize(dtype=torch.float64)
    config = DrapeConfig(
        sew_xpbd=XPBDConfig(substeps=2, iterations=1, stitch_max_speed=0.0),
        sew_ramp_steps=5,
        sew_max_steps=60,
        **overrides,
    )
    start = max_stitch_gap(model, model.vert_init_pos)
    return start, sew(model, g.vert_uv, config=config)


def test_a_stalled_gap_beyond_the_snap_distance_is_snapped():
    start, sewn = _sew(sew_stall_steps=10)
    assert 0.015 < start < 0.03  # open wider than the finishing snap (15 mm), so it stalls first
    assert sewn.diagnostics["max_stitch_gap_m"] < 1e-3 and sewn.converged
    assert 0.015 < sewn.diagnostics["sew_snap_m"] <= 0.04


def test_the_stall_rule_is_bounded():
    # with the growth capped at the finishing snap the same seam stays open
    start, sewn = _sew(sew_stall_steps=10, sew_stall_snap_max=0.015)
    assert sewn.diagnostics["max_stitch_gap_m"] > 0.5 * start and not sewn.converged
    assert sewn.diagnostics["sew_snap_m"] == 0.015
