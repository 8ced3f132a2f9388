"""Garment measurements of sewing patterns (`pattern.measurements`): known answers, rigid motions, a
changed hem, and every shipped template."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from torch_diffavatar.errors import PatternError
from torch_diffavatar.pattern import list_templates, load_template
from torch_diffavatar.pattern.measurements import measure_pattern, pattern_openings
from torch_diffavatar.pattern.spec import Edge, EdgeRef, Panel, Pattern, Stitch

WIDTH, HEIGHT = 0.4, 0.6  # [m] each panel of the rectangle skirt


def _rectangle_skirt() -> Pattern:
    """Two 0.4 × 0.6 m rectangles sewn at the sides: waist and hem 2 × 0.4 m, 0.6 m long."""
    front = Panel(
        "front",
        np.array([[0.0, 0.0], [WIDTH, 0.0], [WIDTH, HEIGHT], [0.0, HEIGHT]]),
        [Edge(0, 1), Edge(1, 2), Edge(2, 3, label="lower_interface"), Edge(3, 0)],
        translation=np.array([-WIDTH / 2, 0.4, 0.15]),
    )
    # the back runs clockwise in its frame (its outside faces -Z), like GarmentCode's back panels
    back = Panel(
        "back",
        np.array([[0.0, 0.0], [0.0, HEIGHT], [WIDTH, HEIGHT], [WIDTH, 0.0]]),
        [Edge(0, 1), Edge(1, 2, label="lower_interface"), Edge(2, 3), Edge(3, 0)],
        translation=np.array([-WIDTH / 2, 0.4, -0.15]),
    )
    stitches = [
        Stitch(EdgeRef("front", 1), EdgeRef("back", 2)),
        Stitch(EdgeRef("front", 3), EdgeRef("back", 0)),
    ]
    return Pattern(panels={"front": front, "back": back}, stitches=stitches, garment_type="skirt")


def _moved(pattern: Pattern, panel: str, degrees: float, shift) -> Pattern:
    """A copy with ``panel`` rotated by ``degrees`` about its origin and shifted by ``shift`` [m] in its
    2D frame, its 3D placement moved too (a rigid motion of the whole panel)."""
    out = copy.deepcopy(pattern)
    a = math.radians(degrees)
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    p = out.panels[panel]
    p.vertices = p.vertices @ rot.T + np.asarray(shift)
    p.translation = p.translation + np.array([0.03, -0.02, 0.01])
    return out


def test_rectangle_skirt_has_known_measurements():
    m = measure_pattern(_rectangle_skirt())
    expected = {
        "waist_circumference": 2 * WIDTH,
        "hem_circumference": 2 * WIDTH,
        "garment_length": HEIGHT,
        "length_back": HEIGHT,
        "length_front": HEIGHT,
        "hem_width_back": WIDTH,
        "hem_width_front": WIDTH,
    }
    assert list(m.lengths) == list(expected)  # circumferences, garment length, per-panel lengths, widths
    for name, value in expected.items():
        assert m.lengths[name] == pytest.approx(value, abs=1e-12), name
    assert m.area == pytest.approx(2 * WIDTH * HEIGHT, abs=1e-12)


@pytest.mark.parametrize(
    "template, panel", [("rect", "front"), ("skirt", "skirt_front"), ("tshirt", "right_ftorso")]
)
def test_measurements_ignore_a_rigid_motion_of_a_panel(template, panel):
    pattern = _rectangle_skirt() if template == "rect" else load_template(template)
    before = measure_pattern(pattern)
    moved = _moved(pattern, panel, 25.0, (0.3, -0.1))
    for openings in (None, pattern_openings(pattern)):  # its own openings, or the unmoved pattern's
        after = measure_pattern(moved, openings)
        assert after.lengths.keys() == before.lengths.keys()
        for name, value in before.lengths.items():
            assert after.lengths[name] == pytest.approx(value, abs=2e-4), name  # curves: 64 samples
        assert after.area == pytest.approx(before.area, rel=1e-6)


@pytest.mark.parametrize("template", ["skirt", "tshirt", "pants"])
def test_a_raised_widened_hem_changes_length_and_hem_by_the_expected_amounts(template):
    """`changed_pattern` moves each panel's hem corners up 10 cm and 20 % away from their mean: the
    templates' hems are straight, so each hem grows by 20 % and each length shrinks by 10 cm."""
    from torch_diffavatar.pattern.design import changed_pattern

    pattern = load_template(template)
    openings = pattern_openings(pattern)
    before = measure_pattern(pattern, openings)
    after = measure_pattern(changed_pattern(pattern, hem_up=0.1, hem_widen=0.2), openings)
    for name, value in before.lengths.items():
        if name.startswith("hem") and (name.endswith("_circumference") or name.startswith("hem_width")):
            assert after.lengths[name] == pytest.approx(1.2 * value, rel=1e-9), name
        elif name.startswith("length_") or name == "garment_length":
            assert after.lengths[name] == pytest.approx(value - 0.1, abs=1e-9), name
        else:  # waist, neck, cuffs and sleeves stay
            assert after.lengths[name] == pytest.approx(value, abs=1e-9), name


def test_a_dress_is_its_skirt_and_its_bodice_long():
    """The dress's skirt joins its bodice at `lower_interface` seams: the garment length is the skirt's
    (waist to hem) plus the bodice's (waist to the high shoulder point), both straight in the template."""
    pattern = load_template("dress")
    m = measure_pattern(pattern)
    skirt = np.ptp(pattern.panels["skirt_front"].vertices[:, 1])
    bodice = np.ptp(pattern.panels["left_ftorso"].vertices[:, 1])
    assert m.lengths["garment_length"] == pytest.approx(skirt + bodice, abs=1e-9)
    assert "sleeve_length_left" not in m.lengths  # sleeveless: its "cuffs" are armholes


@pytest.mark.parametrize("template", list_templates())
def test_every_template_is_measured(template):
    pattern = load_template(template)
    openings = pattern_openings(pattern)
    m = measure_pattern(pattern, openings)
    sewn = {s.a for s in pattern.stitches} | {s.b for s in pattern.stitches}
    free = [EdgeRef(n, k) for n, p in pattern.panels.items() for k in range(len(p.edges))]
    free = [r for r in free if r not in sewn]
    key = lambda r: (r.panel, r.edge)  # noqa: E731
    in_openings = sorted((r for refs in openings.values() for r in refs), key=key)
    assert in_openings == sorted(free, key=key)  # every free edge in exactly one opening
    for name, refs in openings.items():
        assert refs and m.lengths[f"{name}_circumference"] > 0.1, name
    assert 0.3 < m.lengths["garment_length"] < 1.3
    if any(p.label == "arm" for p in pattern.panels.values()):
        assert 0.15 < m.lengths["sleeve_length_left"] == pytest.approx(m.lengths["sleeve_length_right"])
    assert all(math.isfinite(v) and v > 0 for v in m.lengths.values())
    assert 0.3 < m.area < 1.5


def test_openings_of_another_pattern_are_refused():
    openings = {"hem": [EdgeRef("front", 7)]}
    with pytest.raises(PatternError, match=r"edge 7 of panel 'front' \(the panel has 4 edges\)"):
        measure_pattern(_rectangle_skirt(), openings)
    with pytest.raises(PatternError, match="'nope' .no such panel"):
        measure_pattern(_rectangle_skirt(), {"hem": [EdgeRef("nope", 0)]})
