"""The rim helpers of the segmentation on synthetic garments: `_lower_rim` (a skirt's hem as its lower
envelope), `_distal_rim` (a sleeve's cuff as its far end along the arm), `_neck_rim` (a neckline as the
top edge around the neck), `_neck_opening` (a neckline, or a hood's upright face opening) and
`_edge_points` (the points on an opening's edge)."""

from __future__ import annotations

import numpy as np
import pytest

from torch_diffavatar.body.segment import (
    _distal_rim,
    _edge_points,
    _lower_rim,
    _neck_opening,
    _neck_rim,
    _sector_envelope,
)

RADIUS, Y0, Y1 = 0.25, 0.5, 1.0  # the skirt: an open cylinder about the y axis [m]
BAND = 0.015  # `_lower_rim`'s default band [m]
NOISE = 0.001  # [m]
SECTORS = 36
# The band is measured from each angular sector's lowest point, which at this density (~550 points per
# sector) lies up to a few mm above the hem, and the points carry 1 mm noise: so the highest rim point
# may lie up to 1 cm above ``Y0 + BAND`` (measured: 0.517–0.522 m over six seeds), the hole's upper
# edge (0.6 m) far above.
TOP = Y0 + BAND + 0.01


def _skirt(seed: int = 0, count: int = 20000, centre=(0.03, -0.02)) -> np.ndarray:
    """(count, 3) points on the cylinder, uniform by area, with 1 mm Gaussian noise."""
    rng = np.random.default_rng(seed)
    theta = rng.uniform(-np.pi, np.pi, count)
    y = rng.uniform(Y0, Y1, count)
    p = np.stack([centre[0] + RADIUS * np.cos(theta), y, centre[1] + RADIUS * np.sin(theta)], axis=1)
    return p + rng.normal(0.0, NOISE, p.shape)


def _angle(points: np.ndarray, centre=(0.03, -0.02)) -> np.ndarray:
    return np.arctan2(points[:, 2] - centre[1], points[:, 0] - centre[0])


def _sectors_hit(angles: np.ndarray, sectors: int = SECTORS) -> np.ndarray:
    """(sectors,) bool: some angle falls in each of ``sectors`` equal sectors of [−π, π)."""
    k = np.minimum(((angles + np.pi) / (2 * np.pi) * sectors).astype(int), sectors - 1)
    return np.bincount(k, minlength=sectors) > 0


def test_lower_rim_of_a_skirt_is_its_hem():
    g = _skirt()
    sel = np.flatnonzero(g[:, 1] < 0.7)  # what the body's loop finds: the whole lower part
    rim = _lower_rim(g, sel)
    assert 0 < len(rim) < len(sel)
    p = g[rim]
    assert float(p[:, 1].max()) <= TOP
    assert _sectors_hit(_angle(p)).all()  # all the way round
    # and every point of the hem's lowest centimetre is in it
    hem = np.flatnonzero(g[:, 1] < Y0 + 0.01)
    assert np.isin(hem, rim).mean() > 0.99


@pytest.mark.parametrize("others", [None, np.zeros((0, 3))])
@pytest.mark.parametrize("half_width_deg, height", [(20.0, 0.10), (30.0, 0.08)])
def test_lower_rim_skips_a_hole_in_the_hem(half_width_deg, height, others):
    """A hole over the hem, 40° wide and 10 cm high, or 60° and 8 cm (a plateau five sectors wide, as two
    holes side by side on the suite's skirts: a rule that let the hem rise 0.8 of the length along the rim
    from any other sector took its middle for hem)."""
    g = _skirt(seed=1)
    angle = _angle(g)
    hole = (np.abs(angle - 1.0) < np.deg2rad(half_width_deg)) & (g[:, 1] < Y0 + height)
    g = g[~hole]
    angle = angle[~hole]
    sel = np.flatnonzero(g[:, 1] < 0.7)
    rim = _lower_rim(g, sel, others=others)  # with ``others``: the hole's upper edge is no lifted hem
    p, a = g[rim], angle[rim]
    # none from the hole's upper edge: the hem only
    assert float(p[:, 1].max()) <= TOP
    inside = np.abs(a - 1.0) < np.deg2rad(half_width_deg - 3.0)  # a margin for the sector boundaries
    assert not inside.any()
    # the rim in every sector away from the hole
    centres = np.linspace(-np.pi, np.pi, SECTORS, endpoint=False) + np.pi / SECTORS
    away = np.abs(np.angle(np.exp(1j * (centres - 1.0)))) > np.deg2rad(half_width_deg + 10.0)
    assert away.sum() >= 24
    assert _sectors_hit(a)[away].all()


def test_lower_rim_keeps_a_hem_raised_at_the_front():
    """A hem lifted gradually, 8 cm at its middle over 90° (2.2 cm from one 10° sector to the next, as a
    belly lifts a T-shirt's front), is the rim all the way round, not a hole."""
    g = _skirt(seed=2)
    angle = _angle(g)
    lift = 0.08 * np.clip(1.0 - np.abs(angle - 1.0) / np.deg2rad(45.0), 0.0, None)
    g = g[g[:, 1] >= Y0 + lift]
    angle = _angle(g)
    sel = np.flatnonzero(g[:, 1] < 0.7)
    rim = _lower_rim(g, sel)
    assert _sectors_hit(angle[rim]).all()
    raised = np.abs(angle - 1.0) < np.deg2rad(10.0)
    hem = raised & (g[:, 1] < Y0 + 0.07)  # near the raised hem's top (8 cm) …
    assert hem.any() and np.isin(np.flatnonzero(hem), rim).all()  # … whose lowest points are in the rim
    # the rule before (a sector 5 cm above the median sector's is a hole) left the raised front out
    cand = g[:, 1] < 0.7
    before = _sector_envelope(-g[cand, 1], angle[cand], SECTORS, BAND, 0.05)
    assert not _sectors_hit(angle[cand][before])[22:26].all()


def _lifted_flap(points: np.ndarray, at: float = 1.0, half_width_deg: float = 45.0, fold: float = 0.58):
    """The skirt's points with the cloth below ``fold`` [m] turned outward and up within ``half_width_deg``
    of the angle ``at`` (fading to nothing at its ends), as a hand lifts a T-shirt's hem: the cloth rises
    outward from the fold and droops at its end, the hem's edge up to 12 cm out and 3.2 cm above the fold,
    which is the lowest cloth of its sectors (the captured tops' lifted hems: 14-15 cm from the body, 2-4
    cm above their sectors' lowest cloth, facing down)."""
    a = _angle(points)
    fade = np.clip(1.0 - np.abs(np.angle(np.exp(1j * (a - at)))) / np.deg2rad(half_width_deg), 0.0, None)
    below = np.clip(fold - points[:, 1], 0.0, None) * np.sin(0.5 * np.pi * fade) ** 2
    out = points.copy()
    out[:, 1] += 2.2 * below - 10.0 * below**2  # height above the fold 1.2 b - 10 b², b below it before
    centre = np.array([0.03, -0.02])
    radial = (points[:, [0, 2]] - centre) / np.linalg.norm(points[:, [0, 2]] - centre, axis=1, keepdims=True)
    out[:, [0, 2]] += 1.5 * below[:, None] * radial
    return out


def test_lower_rim_takes_a_hem_lifted_outward():
    """A hem lifted outward over 90° (`_lifted_flap`): the lower envelope keeps the fold, not the hem's
    edge beyond it, and traces the hem short; with the scan's other points given (here none: nothing
    but the air ahead of the edge), the lifted edge is the rim too, and the trace longer."""
    from torch_diffavatar.opening_lengths import scan_loop_length

    g = _skirt(seed=5)
    edge = g[:, 1] < Y0 + 0.006  # the hem's edge before the lift
    theta = np.linspace(-np.pi, np.pi, 4000, endpoint=False)
    true_edge = _lifted_flap(
        np.stack(
            [0.03 + RADIUS * np.cos(theta), np.full_like(theta, Y0), -0.02 + RADIUS * np.sin(theta)], axis=1
        )
    )
    true_length = float(np.linalg.norm(np.roll(true_edge, -1, 0) - true_edge, axis=1).sum())
    g = _lifted_flap(g)
    lifted = edge & (g[:, 1] > Y0 + 0.095)  # the edge's points lifted out of any sector's band
    sel = np.flatnonzero(g[:, 1] < 0.7)
    envelope = _lower_rim(g, sel)
    rim = _lower_rim(g, sel, others=np.zeros((0, 3)))
    assert lifted.sum() > 10 and not np.isin(np.flatnonzero(lifted), envelope).any()
    assert np.isin(np.flatnonzero(lifted), rim).mean() > 0.5
    assert np.isin(envelope, rim).all()
    # the added points are the lifted edge (a point of the fold's sharp flank may look like an edge too)
    added = np.setdiff1d(rim, envelope)
    near_edge = np.min(np.linalg.norm(g[added][:, None] - true_edge[None, ::4], axis=2), axis=1)
    assert len(added) >= lifted.sum() and np.mean(near_edge < 0.015) > 0.9
    short, _ = scan_loop_length(g[envelope])
    traced, _ = scan_loop_length(g[rim])
    # The envelope's trace is 9.6 cm short; with the lifted edge, 4.8: the trace's bins take the median of
    # the edge's points and of the fold's beside them (on the captured tops, whose fold is a few points in
    # a sector, the trace came within 1.1 cm of the true hem on 10 of 13 hems traced with a gap).
    assert true_length - short > 0.08
    assert true_length - traced < 0.6 * (true_length - short) and traced < true_length


@pytest.mark.parametrize("yaw_deg", [0.0, 90.0, -135.0])
@pytest.mark.parametrize("side", [".L", ".R"])
def test_lower_rim_of_one_trouser_side(side, yaw_deg):
    """One side of the body's own left-right axis (``lateral``; +x when facing +Z): a captured person
    turned 90° had each trouser leg's hem made of half of both legs."""
    yaw = np.deg2rad(yaw_deg)
    lateral = np.array([np.cos(yaw), 0.0, -np.sin(yaw)])  # +x turned by the yaw about +y
    g = _skirt(seed=2)
    sel = np.flatnonzero(g[:, 1] < 0.7)
    rim = _lower_rim(g, sel, side=side, lateral=None if yaw_deg == 0.0 else lateral)
    p = g[rim]
    across = g @ lateral
    centre = np.median(across)
    assert len(rim) > 50
    if side == ".L":
        assert bool((p @ lateral > centre).all())
    else:
        assert bool((p @ lateral < centre).all())
    assert float(p[:, 1].max()) <= TOP
    # the whole half of the hem: its points below 1 cm on that side are all kept
    half = (g[:, 1] < Y0 + 0.01) & ((across > centre) if side == ".L" else (across < centre))
    assert np.isin(np.flatnonzero(half), rim).mean() > 0.99


def test_lower_rim_leaves_out_what_is_excluded():
    """Points ``exclude``d (a long sleeve's cuff by the hem: on the arm) are never the hem's."""
    g = _skirt(seed=3)
    sel = np.flatnonzero(g[:, 1] < 0.7)
    cuff = np.random.default_rng(4).normal([0.31, Y0 - 0.02, -0.02], 0.02, (300, 3))  # by the hem
    g = np.concatenate([g, cuff])
    exclude = np.zeros(len(g), dtype=bool)
    exclude[-len(cuff) :] = True
    assert (_lower_rim(g, sel) >= len(g) - len(cuff)).any()  # the cuff hangs lowest in its sectors
    rim = _lower_rim(g, sel, exclude=exclude)
    assert not (rim >= len(g) - len(cuff)).any()
    assert _sectors_hit(_angle(g[rim])).all()


def test_edge_points_of_a_disc_are_its_rim():
    rng = np.random.default_rng(3)
    R, spacing = 0.2, 0.01  # [m]
    ticks = np.arange(-R, R + 1e-9, spacing)
    xy = np.stack(np.meshgrid(ticks, ticks), axis=-1).reshape(-1, 2)
    xy = xy + rng.uniform(-0.3, 0.3, xy.shape) * spacing  # a jittered grid
    xy = xy[np.linalg.norm(xy, axis=1) <= R]
    # tilted out of the horizontal, 1 mm noise across it
    tilt = np.deg2rad(35.0)
    g = np.stack([xy[:, 0], xy[:, 1] * np.sin(tilt), xy[:, 1] * np.cos(tilt)], axis=1) + [0.1, 1.0, 0.0]
    normal = np.array([0.0, np.cos(tilt), -np.sin(tilt)])
    g = g + rng.normal(0.0, NOISE, (len(g), 1)) * normal
    r = np.linalg.norm(xy, axis=1)
    sel = np.arange(len(g))
    edge = _edge_points(g, sel)
    assert len(edge) < len(sel)  # not the fallback
    assert float(r[edge].min()) >= R - 0.015  # on the rim, none from the interior
    # and the rim is found all the way round
    rim_angles = np.arctan2(xy[edge, 1], xy[edge, 0])
    assert _sectors_hit(rim_angles, 24).all()
    # from a band near the edge too (what the body's loop gives)
    band = np.flatnonzero(r > R - 0.04)
    edge_band = _edge_points(g, band)
    assert len(edge_band) < len(band) and float(r[edge_band].min()) >= R - 0.015


def test_edge_points_of_a_randomly_sampled_disc_are_its_rim():
    rng = np.random.default_rng(0)
    R, count = 0.2, 1250  # [m]; about the demo scan's density (~1 point/cm²)
    r = R * np.sqrt(rng.uniform(0.0, 1.0, count))  # uniform by area
    theta = rng.uniform(0.0, 2 * np.pi, count)
    g = np.stack([r * np.cos(theta), r * np.sin(theta), rng.normal(0.0, NOISE, count)], axis=1)
    edge = _edge_points(g, np.arange(count))
    assert len(edge) < count  # not the fallback
    assert np.mean(r[edge] >= R - 0.015) >= 0.9


def test_lower_rim_leaves_out_a_sleeve_hanging_beside_the_hem():
    # A long sleeve hangs beside the shirt and ends below its hem (issue #7: the hem took the cuffs).
    rng = np.random.default_rng(4)
    shirt = _skirt(seed=4)
    theta = rng.uniform(-np.pi, np.pi, 3000)
    y = rng.uniform(0.3, 0.8, 3000)  # the cuff at y = 0.3, 20 cm below the hem
    sleeve = np.stack([0.45 + 0.06 * np.cos(theta), y, 0.06 * np.sin(theta)], axis=1)
    g = np.concatenate([shirt, sleeve + rng.normal(0.0, NOISE, sleeve.shape)])
    on_sleeve = np.arange(len(g)) >= len(shirt)
    sel = np.flatnonzero(~on_sleeve & (g[:, 1] < 0.7))
    assert on_sleeve[_lower_rim(g, sel)].any()  # the envelope alone dips to the cuff
    rim = _lower_rim(g, sel, link=0.03)
    assert not on_sleeve[rim].any()
    assert float(g[rim, 1].max()) <= TOP and _sectors_hit(_angle(g[rim])).all()


def test_opening_rim_tells_a_hole_from_an_opening():
    """A flat garment (40 cm square, 1 cm jittered grid) with a 6 cm hole in it, and skin beyond its
    right edge: the hole's rim is no opening; the right edge is (with skin right ahead); the other
    edges, with nothing ahead, are weak openings."""
    from torch_diffavatar.body.segment import _opening_rim

    rng = np.random.default_rng(5)
    ticks = np.arange(-0.2, 0.2 + 1e-9, 0.01)
    xy = np.stack(np.meshgrid(ticks, ticks), axis=-1).reshape(-1, 2)
    xy = xy + rng.uniform(-0.3, 0.3, xy.shape) * 0.01
    r = np.linalg.norm(xy, axis=1)
    xy = xy[r > 0.06]
    r = r[r > 0.06]
    g = np.concatenate([xy, rng.normal(0.0, NOISE, (len(xy), 1))], axis=1)
    sx, sy = np.meshgrid(np.arange(0.215, 0.3, 0.01), ticks)
    skin = np.stack([sx.ravel(), sy.ravel(), np.zeros(sx.size)], axis=1)
    kind = _opening_rim(g, skin, np.arange(len(g)))
    hole_rim = r < 0.075
    side = np.abs(xy[:, 1]) < 0.15  # the outermost column of the grid on each side, corners left out
    right, left = side & (xy[:, 0] > 0.197), side & (xy[:, 0] < -0.197)
    assert hole_rim.sum() > 20 and not (kind[hole_rim] > 0).any()
    assert np.mean(kind[right] == 2) > 0.8
    assert np.mean(kind[left] == 1) > 0.8
    interior = (np.abs(xy) < 0.17).all(1) & (r > 0.09)
    assert not (kind[interior] > 0).any()


def _arm(direction=(0.7, -0.7, 0.0)) -> list[np.ndarray]:
    """Upper arm, forearm and hand as point clouds along a straight arm from the shoulder at the origin."""
    d = np.asarray(direction) / np.linalg.norm(direction)
    return [np.outer(np.linspace(a, b, 50), d) for a, b in ((0.0, 0.3), (0.3, 0.55), (0.55, 0.7))]


def _ring(centre_t: float, count: int, rng, direction=(0.7, -0.7, 0.0), radius=0.06) -> np.ndarray:
    """``count`` points of a ring across the arm at ``centre_t`` [m] along it, with 2 mm noise."""
    d = np.asarray(direction) / np.linalg.norm(direction)
    u = np.cross(d, [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u)
    v = np.cross(d, u)
    a = rng.uniform(-np.pi, np.pi, count)
    p = centre_t * d + radius * (np.cos(a)[:, None] * u + np.sin(a)[:, None] * v)
    return p + rng.normal(0.0, 0.002, p.shape)


def test_distal_rim_keeps_the_cuff_and_drops_a_shoulder_patch():
    """A T-shirt's unlabelled scan: tight cloth on the shoulder taken for skin left a bare patch whose
    rim was taken into the cuff's (the suite's T-shirt then ended 16.2 mm from its scan, started at 12.0).
    Only the points at the sleeve's end stay, all the way round."""
    rng = np.random.default_rng(0)
    cuff = _ring(0.22, 60, rng)
    patch = _ring(0.06, 40, rng, radius=0.03) + np.array([0.0, 0.05, 0.0])  # on top of the shoulder
    points = np.concatenate([cuff, patch])
    kept = _distal_rim(points, np.arange(len(points)), _arm())
    assert set(kept.tolist()) == set(range(len(cuff)))


def test_distal_rim_keeps_a_cuff_with_a_hole_and_falls_back_when_too_few():
    rng = np.random.default_rng(1)
    cuff = _ring(0.22, 60, rng)
    # a scan hole took a sector of the cuff; the sleeve's edge around the hole lies 8 cm up the arm
    d = np.array([0.7, -0.7, 0.0]) / np.sqrt(0.98)
    hole_rim = cuff[:5] - 0.08 * d
    points = np.concatenate([cuff[5:], hole_rim])
    kept = _distal_rim(points, np.arange(len(points)), _arm())
    assert set(kept.tolist()) == set(range(len(cuff) - 5))
    # fewer points than ``min_count``: all are kept
    few = np.arange(10)
    np.testing.assert_array_equal(_distal_rim(points, few, _arm()), few)


def _neckline(count: int, rng) -> np.ndarray:
    """(count, 3) a scoop neckline about the y axis: 7 cm out, 1.45 m high at the back (−z), dipping to
    1.33 m at the front (+z), with 2 mm noise."""
    a = rng.uniform(-np.pi, np.pi, count)
    y = 1.45 - 0.06 * (1.0 + np.sin(a))
    p = np.stack([0.07 * np.cos(a), y, 0.07 * np.sin(a)], axis=1)
    return p + rng.normal(0.0, 0.002, p.shape)


def _trunk():
    """(head, torso) stand-in body vertices: the neck axis is the y axis."""
    ring = np.stack([np.cos(np.linspace(0, 6, 12)), np.zeros(12), np.sin(np.linspace(0, 6, 12))], axis=1)
    return ring * 0.08 + [0.0, 1.6, 0.0], ring * 0.15 + [0.0, 1.2, 0.0]


def test_neck_rim_keeps_the_neckline_and_drops_a_bare_patch_below_it():
    """A T-shirt's unlabelled scan: tight cloth on the upper back taken for skin left a bare patch whose
    rim the body names after the head, like the neckline's (the suite's T-shirt: 41 of 130 neck points
    2-10 cm down the back and front). The patch's rim lies below the neckline in its sectors and goes;
    the whole neckline stays, its low front too."""
    rng = np.random.default_rng(0)
    neck = _neckline(120, rng)
    a = rng.uniform(-np.pi + 0.3, -0.3, 40)  # behind the neck, 3-8 cm below it, 8-15 cm out
    r, drop = rng.uniform(0.08, 0.15, 40), rng.uniform(0.03, 0.08, 40)
    patch = np.stack([r * np.cos(a), 1.45 - 0.06 * (1.0 + np.sin(a)) - drop, r * np.sin(a)], axis=1)
    points = np.concatenate([neck, patch])
    kept = _neck_rim(points, np.arange(len(points)), *_trunk())
    assert set(kept.tolist()) == set(range(len(neck)))
    # fewer points than ``min_count``: all are kept
    few = np.arange(10)
    np.testing.assert_array_equal(_neck_rim(points, few, *_trunk()), few)


def _face_opening(count: int, rng) -> np.ndarray:
    """(count, 3) a hood's face opening: upright in the plane z = 0.11 m in front of the head, 30 cm wide
    and 28 cm high (1.37-1.65 m), with 2 mm noise (GarmentCode's hoody: 31 cm wide)."""
    a = rng.uniform(-np.pi, np.pi, count)
    p = np.stack([0.15 * np.cos(a), 1.51 + 0.14 * np.sin(a), np.full(count, 0.11)], axis=1)
    return p + rng.normal(0.0, 0.002, p.shape)


def test_neck_opening_of_a_hood_is_its_whole_face_opening():
    """Under a hood the bare skin's boundary runs around the face, upright. The hood's face opening
    stands in front of the face, its sides 7 cm and more off it: only its top and its bottom lie near
    that boundary (``near``). The whole opening is kept, and the rims of holes in the hood behind it
    (skin seen through them) go."""
    rng = np.random.default_rng(0)
    face = _face_opening(240, rng)
    a = rng.uniform(0.3, np.pi - 0.3, 30)  # hole rims on the hood's sides and back, 12 cm about the head
    holes = np.stack([0.12 * np.cos(a), rng.uniform(1.45, 1.7, 30), -0.12 * np.sin(a) + 0.02], axis=1)
    points = np.concatenate([face, holes])
    rim = np.arange(len(points))
    near = np.flatnonzero(np.abs(points[:, 0]) < 0.05)  # the top and the bottom of the opening
    face_loop = _face_opening(40, rng) * [0.5, 1.0, 1.0] + [0.0, 0.0, -0.02]
    forward = np.array([0.0, 0.0, 1.0])
    kept = _neck_opening(points, rim, near, face_loop, *_trunk(), forward)
    assert set(kept.tolist()) == set(range(len(face)))
    # the same points about a bare neck: the neckline's rule
    np.testing.assert_array_equal(
        _neck_opening(points, rim, near, _neckline(40, rng), *_trunk(), forward),
        _neck_rim(points, near, *_trunk()),
    )


def test_neck_opening_of_a_neckline_is_its_neck_rim():
    """A neckline's skin loop lies across the torso→head axis: the opening is `_neck_rim` of the points
    near it (its bare patches' rims farther out go, as `_neck_rim` drops them)."""
    rng = np.random.default_rng(1)
    neck = _neckline(120, rng)
    a = rng.uniform(-np.pi + 0.3, -0.3, 40)  # a bare patch behind the neck, 3-8 cm below it, 8-15 cm out
    r, drop = rng.uniform(0.08, 0.15, 40), rng.uniform(0.03, 0.08, 40)
    patch = np.stack([r * np.cos(a), 1.45 - 0.06 * (1.0 + np.sin(a)) - drop, r * np.sin(a)], axis=1)
    points = np.concatenate([neck, patch])
    near = np.arange(len(points))
    kept = _neck_opening(points, near, near, _neckline(40, rng), *_trunk(), np.array([0.0, 0.0, 1.0]))
    assert set(kept.tolist()) == set(range(len(neck)))
