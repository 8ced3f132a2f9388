"""Scan intake for real captures (issue #29): a scan file in, the person alone in our world frame out.

`intake_scan` loads a scan (`scan.load_scan`) and, in this order:

0. refuses what cannot be a scan of a person (`check_point_count`) and moves coordinates that lie so far
   from the origin that float32 (the fit's precision) would lose millimetres there to the origin, and says
   so (`recentre_far_points`);
1. infers its length unit from its height when none is given (`infer_units`), and says so; refuses a
   height no person has in the unit given (`check_height`);
2. with no up axis given, takes Y up, or Y down when the floor is found above the person, or Z or -Z when
   a floor is found under a standing person along it and along neither Y nor -Y (and says so;
   `_choose_up`);
3. finds the floor as a plane (`find_floor`: RANSAC among the lowest points, a tilt up to
   `MAX_FLOOR_TILT_DEG` allowed) and removes it (`remove_floor_plane`): every point less than a margin
   above the plane (3 robust sigmas of the floor's own scatter, at least `FLOOR_MARGIN_MIN`), and the
   points up to `FLOOR_BAND` above it that lie away from the legs' footprint (floor noise, the base of
   clutter); then shifts the scan vertically so that the floor lies at y = 0 under the person;
4. keeps the person as the largest connected cluster (`largest_cluster`: points closer than
   ``cluster_radius`` are connected), dropping stray points and clutter, then statistical outliers
   (`scan.remove_outliers`);
5. checks the frame (`scan.check_scan_frame`) and the shape (`check_person_shape`: a sphere or a box is
   refused) on what is left: a floor makes a scan wider than tall, so the checks must come after its
   removal;
6. estimates the coverage (`coverage`): which of 8 horizontal directions around the person hold points.

The frame: the intake converts units and axes and shifts vertically (floor at y = 0); it never rotates
(a tilted floor is reported, not levelled) nor shifts horizontally (but for coordinates far from the
origin, `recentre_far_points`), so a capture simulated in a frame (`capture.capture_scene`) comes back in
that same frame.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from torch_diffavatar.errors import ScanError
from torch_diffavatar.metrics import local_covariance
from torch_diffavatar.scan import (
    UNITS,
    UP_AXES,
    Scan,
    ScanWarning,
    check_scan_frame,
    load_scan,
    remove_outliers,
)

# Plausible standing heights [m] of a person, for `infer_units`.
HEIGHT_RANGE_M = (0.5, 2.6)
MAX_FLOOR_TILT_DEG = 15.0
FLOOR_MARGIN_MIN = 0.015  # [m] a floor point this close to the plane is always floor
FLOOR_BAND = 0.12  # [m] above the floor, only points under the legs' footprint are kept
FOOTPRINT_REACH = 0.2  # [m] horizontal reach of the feet beyond the shins (toes, heels)
# a floor has nothing under it: at most this share of the points off a candidate plane may lie more than
# `FLOOR_BELOW_MIN` (or 4 of its sigmas) below it (stray points, depth noise); the tops of two arms held
# forward at shoulder height, seen upside down, have the head and neck under them (~10 % of a body)
FLOOR_BELOW_SHARE = 0.01
FLOOR_BELOW_MIN = 0.05  # [m]
SECTORS = 8


@dataclass
class Floor:
    """A floor plane ``normal · p = offset`` (world frame, ``normal`` (3,) unit, pointing up).

    Attributes:
        normal: (3,) unit normal, y > 0. offset: [m]. inliers: points within the RANSAC threshold.
        sigma: robust scatter of the inliers about the plane [m] (1.4826 × median absolute distance).
        tilt_deg: angle of the normal to +Y [deg].
    """

    normal: np.ndarray
    offset: float
    inliers: int
    sigma: float
    tilt_deg: float

    def height(self, points: np.ndarray) -> np.ndarray:
        """(N,) signed distance [m] of (N, 3) points above the plane."""
        return points @ self.normal - self.offset


@dataclass
class IntakeReport:
    """What the intake did (`intake_scan`), for the command's summary.

    Attributes:
        units, up: the file's unit and up axis used; units_inferred: whether the height chose the unit.
        shift: what was subtracted from the file's coordinates (`recentre_far_points`), or None.
        floor: the removed `Floor` as a dict (None when there was none) with ``removed`` points.
        clutter_removed: points outside the person's cluster; outliers_removed: statistical outliers.
        coverage: `coverage` of the result. messages: what the intake decided, in words.
        warnings: `check_scan_frame` of the result.
    """

    units: str
    up: str
    units_inferred: bool = False
    floor: dict | None = None
    clutter_removed: int = 0
    shift: list[float] | None = None
    outliers_removed: int = 0
    coverage: dict = field(default_factory=dict)
    messages: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


# A height beyond this factor of `HEIGHT_RANGE_M` in the unit given is no person (strong evidence: refused);
# within it but outside the range, `scan.check_scan_frame` warns.
HEIGHT_REFUSE_FACTOR = 4.0
MIN_POINTS = 100  # a scan with fewer points cannot show a person (the intake's result needs as many)
# The shape of a standing person (`person_shape`): the smaller horizontal extent of the body between 20 %
# and 90 % of its height, over that height. Measured on 60 synthetic and simulated-capture scans (bare,
# skirt, dress, tshirt, pants; one camera or a ring): 0.15-0.26; a sphere or a ball of points: 0.97-0.98.
# Above `PERSON_DEPTH_WARN` a warning, above `PERSON_DEPTH_REFUSE` refused (a ball gown 1.2 m across on a
# 1.7 m person would be 0.7).
PERSON_DEPTH_WARN = 0.45
PERSON_DEPTH_REFUSE = 0.8
# float32 (the fit's precision) keeps at least this resolution, relative to the scan's size, at the
# coordinates of a scan that is not moved (`recentre_far_points`): 1e-4 of a 1.7 m person is 0.17 mm
FLOAT32_RESOLUTION = 1e-4


def check_point_count(points: np.ndarray, path) -> None:
    """ScanError when (N, 3) ``points`` are too few to show a person (`MIN_POINTS`)."""
    if len(points) < MIN_POINTS:
        raise ScanError(
            f"{path}: only {len(points)} points; a scan of a person needs at least {MIN_POINTS} "
            "(is this the right file?)"
        )


def recentre_far_points(points: np.ndarray, path) -> tuple[np.ndarray, np.ndarray | None]:
    """(N, 3) ``points`` moved to the origin when they lie so far from it, for their size, that float32
    would lose resolution there (coarser than `FLOAT32_RESOLUTION` of their extent: a person 1 km from the
    origin keeps 0.06 mm, at 1e9 m only 64 m), with the shift subtracted (None when not moved).

    Raises:
        ScanError: the file's own numbers have already lost the person there (most of its points share
            a height: coordinates stored in float32 far from the origin).
    """
    extent = float(np.max(np.quantile(points, 0.995, axis=0) - np.quantile(points, 0.005, axis=0)))
    far = float(np.abs(points).max())
    if np.spacing(np.float32(far)) <= FLOAT32_RESOLUTION * max(extent, 1e-12):
        return points, None
    shift = np.median(points, axis=0)
    if len(np.unique(points[:, 1])) < 0.1 * len(points):
        raise ScanError(
            f"{path}: the coordinates lie {far:.3g} from the origin, where the file's numbers keep only "
            f"about {np.spacing(np.float32(far)):.3g}: the person is lost; export the scan near the origin"
        )
    return points - shift, shift


def check_height(points: np.ndarray, units: str, path) -> None:
    """ScanError when (N, 3) Y-up ``points`` in the file's ``units`` make a person no person is
    (`HEIGHT_REFUSE_FACTOR` beyond `HEIGHT_RANGE_M`): a scan in mm read as m is 1,700 m tall."""
    height = robust_height(points) * UNITS[units]
    lo, hi = HEIGHT_RANGE_M[0] / HEIGHT_REFUSE_FACTOR, HEIGHT_RANGE_M[1] * HEIGHT_REFUSE_FACTOR
    if lo <= height <= hi:
        return
    fits = [
        u
        for u, scale in UNITS.items()
        if HEIGHT_RANGE_M[0] <= height / UNITS[units] * scale <= HEIGHT_RANGE_M[1]
    ]
    fix = f"is it in {fits[0]}? pass --units {fits[0]}" if fits else "check the file and its --up axis"
    raise ScanError(
        f"{path}: with --units {units} the person would be {height:.4g} m tall; {fix} "
        "(or leave --units out to infer it)"
    )


def person_shape(points: np.ndarray) -> float:
    """The smaller horizontal extent (2-98 % quantiles, along the horizontal principal axes) of (N, 3) Y-up
    ``points`` between 20 % and 90 % of their height (no floor, no feet), over that height: 0.15-0.26 for
    a standing person (`PERSON_DEPTH_WARN`), about 1 for a sphere; NaN for fewer than 20 points there."""
    height = max(robust_height(points), 1e-12)
    lo = float(np.quantile(points[:, 1], 0.005))
    middle = points[(points[:, 1] > lo + 0.2 * height) & (points[:, 1] < lo + 0.9 * height)][:, [0, 2]]
    if len(middle) < 20:
        return float("nan")
    middle = middle - middle.mean(0)
    flat = middle @ np.linalg.eigh(middle.T @ middle)[1]  # (k, 2): minor axis, major axis
    extent = np.quantile(flat, 0.98, axis=0) - np.quantile(flat, 0.02, axis=0)
    return float(extent.min() / height)


def check_person_shape(points: np.ndarray, path) -> list[str]:
    """Whether (N, 3) Y-up points [m] have a standing person's shape (`person_shape`): a ScanError when
    they clearly do not (a sphere, a box, a person lying down), a warning (in the list) when doubtful."""
    depth = person_shape(points)
    if depth > PERSON_DEPTH_REFUSE:
        raise ScanError(
            f"{path}: this does not look like a standing person: its middle is {depth:.2f} times as deep as "
            f"it is tall (a person: under {PERSON_DEPTH_WARN}); a sphere or a box, or a person lying down "
            "(then pass --up z or --up -z)"
        )
    if depth > PERSON_DEPTH_WARN:
        return [
            f"the scan is unusually deep for a person ({depth:.2f} of its height; a person: under "
            f"{PERSON_DEPTH_WARN}): is it a person, standing, with --up right?"
        ]
    return []


# points a scan is thinned to before the clean-up (`intake_scan`): 2M points on a person are one every
# ~1.5 mm, finer than any capture's noise
MAX_POINTS = 2_000_000


def robust_height(points: np.ndarray) -> float:
    """Vertical extent [file units] of (N, 3) Y-up points between their 0.5 % and 99.5 % quantiles."""
    lo, hi = np.quantile(points[:, 1], [0.005, 0.995])
    return float(hi - lo)


def infer_units(points: np.ndarray) -> str:
    """The unit ("m", "cm" or "mm") in which (N, 3) Y-up points of a standing person have a plausible
    height (`HEIGHT_RANGE_M`). Raises ScanError when none does."""
    height = robust_height(points)
    for unit, scale in UNITS.items():
        if HEIGHT_RANGE_M[0] <= height * scale <= HEIGHT_RANGE_M[1]:
            return unit
    raise ScanError(
        f"cannot infer the units from a height of {height:.4g} (a person is {HEIGHT_RANGE_M[0]}-"
        f"{HEIGHT_RANGE_M[1]} m tall): pass --units m, cm or mm, or --up if the person is not along Y"
    )


def _plane(p: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Plane (unit normal with y >= 0, offset) through three points (3, 3), None when degenerate."""
    n = np.cross(p[1] - p[0], p[2] - p[0])
    norm = np.linalg.norm(n)
    if norm < 1e-12:
        return None
    n = n / norm * (1.0 if n[1] >= 0 else -1.0)
    return n, float(n @ p[0])


def find_floor(
    points: np.ndarray,
    *,
    search_height: float = 0.35,
    threshold: float = 0.02,
    iterations: int = 300,
    min_span: float = 0.6,
    rng: np.random.Generator | None = None,
) -> Floor | None:
    """The floor under a standing person, as a plane, or None when the scan shows none.

    RANSAC among the points in the lowest ``search_height`` [m]: planes through three random points
    tilted at most `MAX_FLOOR_TILT_DEG`, scored by their points within ``threshold`` [m], then refined
    by least squares on those. A plane counts as a floor when its points reach farther than ``min_span``
    [m] along their principal horizontal axis and half that across it (the soles of a person are flat
    too, but only ~30 cm long; arms held out level are long but narrow) and number at least 200, and when
    hardly any point lies under it (`FLOOR_BELOW_SHARE`: not the top of arms held forward, upside down).

    Args:
        points: (N, 3) [m], Y up.
        rng: the random source (default: seeded 0, for a repeatable result).
    """
    rng = np.random.default_rng(0) if rng is None else rng
    y0 = float(np.quantile(points[:, 1], 0.001))
    low = points[points[:, 1] < y0 + search_height]
    if len(low) < 200:
        return None
    if len(low) > 20000:
        low = low[rng.choice(len(low), 20000, replace=False)]
    best, best_count = None, 0
    min_cos = math.cos(math.radians(MAX_FLOOR_TILT_DEG))
    for _ in range(iterations):
        plane = _plane(low[rng.choice(len(low), 3, replace=False)])
        if plane is None or plane[0][1] < min_cos:
            continue
        count = int((np.abs(low @ plane[0] - plane[1]) < threshold).sum())
        if count > best_count:
            best, best_count = plane, count
    if best is None:
        return None
    inl = low[np.abs(low @ best[0] - best[1]) < threshold]
    centre = inl.mean(0)
    normal = np.linalg.svd(inl - centre, full_matrices=False)[2][2]  # least-squares plane
    normal = normal * (1.0 if normal[1] >= 0 else -1.0)
    dist = (inl - centre) @ normal
    # spans along the inliers' own horizontal axes: a floor is wide both ways, arms held out are not
    flat = inl[:, [0, 2]] - inl[:, [0, 2]].mean(0)
    flat = flat @ np.linalg.eigh(flat.T @ flat)[1]  # (k, 2): minor axis, major axis
    span = np.quantile(flat, 0.98, axis=0) - np.quantile(flat, 0.02, axis=0)
    if len(inl) < 200 or span[1] < min_span or span[0] < 0.5 * min_span or normal[1] < min_cos:
        return None
    sigma = float(1.4826 * np.median(np.abs(dist - np.median(dist))))
    height = points @ normal - float(normal @ centre)  # of every point, not only the lowest
    below = int((height < -max(FLOOR_BELOW_MIN, 4.0 * sigma)).sum())
    if below > FLOOR_BELOW_SHARE * int((np.abs(height) >= threshold).sum()):
        return None  # points under it: the top of something, such as arms held forward seen upside down
    return Floor(
        normal=normal,
        offset=float(normal @ centre),
        inliers=int(len(inl)),
        sigma=sigma,
        tilt_deg=float(math.degrees(math.acos(min(1.0, normal[1])))),
    )


def floor_margin(sigma: float) -> float:
    """How far above the floor [m] `remove_floor_plane` takes every point with it: 3 robust sigmas of the
    floor's own scatter (``sigma`` [m]; the intake report's ``floor["sigma_m"]``), at least
    `FLOOR_MARGIN_MIN`. Cloth lying on the floor within it (trousers piled there) goes too."""
    return max(3.0 * sigma, FLOOR_MARGIN_MIN)


def remove_floor_plane(scan: Scan, floor: Floor) -> tuple[Scan, int]:
    """Remove ``floor`` from ``scan`` and put it at y = 0 under the person (see the module docstring).

    A point is floor when it lies below the plane or less than max(3 sigma, `FLOOR_MARGIN_MIN`) above it,
    or less than `FLOOR_BAND` above it and more than `FOOTPRINT_REACH` horizontally from every point of
    the legs (12–40 cm above the floor): floor noise and the base of clutter, never a foot.

    Returns:
        (the scan without the floor, shifted vertically; the number of points removed).
    """
    above = floor.height(scan.points)
    margin = floor_margin(floor.sigma)
    keep = above > margin
    band = keep & (above < FLOOR_BAND)
    legs = scan.points[(above >= FLOOR_BAND) & (above < 0.4)][:, [0, 2]]
    if band.any() and len(legs):
        near, _ = cKDTree(legs).query(scan.points[band][:, [0, 2]], distance_upper_bound=FOOTPRINT_REACH)
        keep[np.flatnonzero(band)[~np.isfinite(near)]] = False
    out = scan.subset(keep)
    if out.point_count:
        centre = np.median(out.points, axis=0)
        # the floor's height under the person's centre: n · (cx, y, cz) = offset
        level = (floor.offset - floor.normal[0] * centre[0] - floor.normal[2] * centre[2]) / floor.normal[1]
        out = replace(out, points=out.points - np.array([0.0, level, 0.0]))
    return out, int((~keep).sum())


def largest_cluster(
    scan: Scan, radius: float = 0.05, *, attach: float = 0.25, min_share: float = 0.005
) -> tuple[Scan, int]:
    """Keep the person: the largest connected cluster of points (two points closer than ``radius`` [m]
    connect), with the pieces a hole cut off it.

    Points are binned in cubes of ``radius`` / 2 and the occupied cubes whose centres lie within
    ``radius`` connect (so gaps up to about ``radius`` / 2 always join, never gaps beyond 1.5 ``radius``):
    a few thousand cubes on a person, fast at any point count. A cluster of at least ``min_share`` of the
    points that comes within ``attach`` [m] of what is kept is kept too (repeatedly): a hole across a
    forearm or an ankle cuts a hand or a foot off the body (measured: 3,288 of 60,691 points, a hand and a
    foot, on our synthetic dress scan with its 10 % of holes), and the body fit needs them. Why 25 cm: the
    scan generator's holes are up to 16 cm across, a piece smaller than ``min_share`` between does not
    bridge, and the distance is taken between the cubes' centres (up to 4.3 cm more than the points'): on
    our trousers 312 a forearm and hand of 1,941 points lay 18 cm from the body beyond a 99-point piece,
    and the body fit without them ended 7.7 cm from the scan (2.1 cm with them). Clutter farther away, or
    too small to be a body part, goes.

    Returns:
        (the scan restricted to the kept clusters, the number of points removed).
    """
    if scan.point_count == 0:
        return scan, 0
    cell = 0.5 * radius
    keys, cube = np.unique(np.floor(scan.points / cell).astype(np.int64), axis=0, return_inverse=True)
    cube = cube.reshape(-1)
    centres = keys.astype(np.float64)
    pairs = cKDTree(centres).query_pairs(radius / cell + 1e-9, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(keys), len(keys)))
    _, comp = connected_components(graph, directed=False)
    comp_points = np.bincount(comp[cube])
    kept = {int(np.argmax(comp_points))}
    candidates = set(np.flatnonzero(comp_points >= min_share * scan.point_count).tolist()) - kept
    while candidates:
        tree = cKDTree(centres[np.isin(comp, list(kept))])
        near = {
            c
            for c in candidates
            if np.isfinite(tree.query(centres[comp == c], distance_upper_bound=attach / cell)[0]).any()
        }
        if not near:
            break
        kept |= near
        candidates -= near
    keep = np.isin(comp[cube], list(kept))
    return scan.subset(keep), int((~keep).sum())


def coverage(
    points: np.ndarray, normals: np.ndarray | None = None, sectors: int = SECTORS, min_share: float = 0.25
) -> dict:
    """Which horizontal directions the scanned surface faces: the sides of the person the scan sees.

    With ``normals`` (N, 3) from the file (a depth capture's, towards its sensor), each point whose normal
    is within 45° of horizontal votes for one of ``sectors`` equal sectors of its horizontal direction
    (sector 0 centred on +Z, counter-clockwise seen from above); a sector is seen when it holds at least
    ``min_share`` of an even share. Measured on simulated captures of a tshirt scan: 5 of 8 sides seen from
    one camera 3 or 4 (seeds 11-13), a ring of 4 all 8.

    Without normals they are estimated, less reliably: the points are averaged in 2 cm cubes (the depth
    noise exceeds the raw spacing), each cube's normal is the smallest principal axis of its 12 nearest
    cubes, turned away from the centre of its 10 cm height slab, and only cubes whose normal points
    clearly away from that centre (cos > 0.5) vote. Measured: a column seen by one camera 5 of 8 sides, by
    a ring of 2 to 4 all 8; but a person seen from the front 8 of 8 (arms and flanks vote for sides never
    seen), so a scan without normals may overstate its coverage.

    Args:
        points: (N, 3) [m], Y up. normals: (N, 3) unit normals, or None.

    Returns:
        ``{"sectors_seen": k, "sectors": n, "fraction": k / n, "seen": [bool] * n}``.
    """
    if normals is not None:
        return _sectors(normals, sectors, min_share)
    # 2 cm cube means first: the raw points' depth noise (8 mm at 2 m) exceeds their spacing, which
    # would make the normals of raw neighbourhoods random
    keys, cube = np.unique(np.floor(points / 0.02).astype(np.int64), axis=0, return_inverse=True)
    cube = cube.reshape(-1)
    points = np.stack([np.bincount(cube, points[:, a]) for a in range(3)], 1) / np.bincount(cube)[:, None]
    normal = np.linalg.eigh(local_covariance(points, min(12, len(points))))[1][:, :, 0]  # (N, 3)
    slab = np.floor(points[:, 1] / 0.1).astype(np.int64)  # 10 cm height slabs, each with its own centre
    slab_of = np.unique(slab, return_inverse=True)[1].reshape(-1)
    centre = np.stack([np.bincount(slab_of, points[:, a]) for a in (0, 2)], 1) / np.bincount(slab_of)[:, None]
    outward = points[:, [0, 2]] - centre[slab_of]
    outward /= np.maximum(np.linalg.norm(outward, axis=1, keepdims=True), 1e-9)
    flat = normal[:, [0, 2]] / np.maximum(np.linalg.norm(normal[:, [0, 2]], axis=1, keepdims=True), 1e-9)
    cos = (flat * outward).sum(1)
    normal *= np.where(cos < 0, -1.0, 1.0)[:, None]
    # only where the outward direction decides the side (not on the front of an arm held out sideways)
    side = np.abs(cos) > 0.5
    return _sectors(normal[side], sectors, min_share)


def side_sector(normal: np.ndarray, sectors: int = SECTORS) -> np.ndarray:
    """(N,) int64: the side of the person each unit normal (N, 3) faces, one of ``sectors`` equal sectors
    of its horizontal direction (sector 0 centred on +Z, the next toward +X), or -1 for a normal within
    45° of vertical (a shoulder top or a sole faces no side)."""
    angle = np.arctan2(normal[:, 0], normal[:, 2])  # 0 along +Z, +90° along +X
    index = np.floor((angle / (2 * math.pi) + 0.5 / sectors) * sectors).astype(np.int64) % sectors
    return np.where(np.abs(normal[:, 1]) < math.sqrt(0.5), index, -1)


def _sectors(normal: np.ndarray, sectors: int, min_share: float) -> dict:
    """`coverage` from oriented normals (N, 3): the votes of those within 45° of horizontal."""
    index = side_sector(normal, sectors)
    index = index[index >= 0]
    counts = np.bincount(index, minlength=sectors)
    seen = counts >= min_share * max(len(index), 1) / sectors
    return {
        "sectors_seen": int(seen.sum()),
        "sectors": sectors,
        "fraction": float(seen.mean()),
        "seen": seen.tolist(),
    }


def intake_scan(
    path: str | Path,
    *,
    units: str | None = None,
    up: str | None = None,
    clean: bool = True,
    cluster_radius: float = 0.05,
    max_points: int = MAX_POINTS,
    **load_kw,
) -> tuple[Scan, IntakeReport]:
    """Load a scan and bring the person alone into our world frame (see the module docstring).

    Args:
        path: the scan file (`scan.load_scan`).
        units: the file's unit (`scan.UNITS`), or None to infer it from the height.
        up: the file's up axis (`scan.UP_AXES`), or None: "y", or "-y" when the floor lies above the person,
            or "z" / "-z" when the floor lies under a standing person along it (`_choose_up`).
        clean: remove the floor, clutter and outliers (else only convert the frame).
        cluster_radius: the `largest_cluster` radius [m].
        max_points: a scan with more points is thinned to a seeded random subset this large first (said in
            the report): the clean-up's neighbour searches grow with it (a 50M-point scan asked for
            6.3 GiB), and a fit uses a few thousand of them. A PLY is thinned as it is read
            (`scan.load_scan`), so that the whole file is never in memory.
        load_kw: passed to `scan.load_scan` (``labels``, ``label_property``).

    Returns:
        (the `Scan` [m], Y up, the floor at y = 0 when there was one; an `IntakeReport`).

    Raises:
        ScanError: unreadable file, too few points, the person lost to far coordinates, units not
            inferable, a height no person has in the given ``units``, not a person's shape.
    """
    if units is not None and units not in UNITS:
        raise ScanError(f"unknown units {units!r}; use one of {sorted(UNITS)}")
    if up is not None and up not in UP_AXES:
        raise ScanError(f"unknown up axis {up!r}; use one of {sorted(UP_AXES)}")
    if not MIN_POINTS <= max_points:
        raise ScanError(f"--max-points must be at least {MIN_POINTS}, got {max_points}")
    scan = load_scan(path, units="m", up=up or "y", check=False, max_points=max_points, **load_kw)
    report = IntakeReport(units=units or "m", up=up or "y")
    check_point_count(scan.points, path)
    file_count = scan.file_point_count or scan.point_count
    if scan.point_count > max_points:  # a file read whole (not a PLY that streams)
        keep = np.zeros(scan.point_count, bool)
        keep[np.random.default_rng(0).choice(scan.point_count, max_points, replace=False)] = True
        scan = scan.subset(keep)
    if file_count > scan.point_count:
        report.messages.append(
            f"{file_count:,} points: more than the {max_points:,} used (--max-points N); a random "
            f"{scan.point_count:,} kept"
        )
    scan = _recentre(scan, report, path)
    if up is None:
        scan = _choose_up(scan, report)
    if units is None:
        report.units, report.units_inferred = infer_units(scan.points), True
        report.messages.append(
            f"units: {report.units} (inferred from the height, {robust_height(scan.points):.4g}; "
            "pass --units to override)"
        )
    else:
        check_height(scan.points, units, path)
    scan = replace(scan, points=scan.points * UNITS[report.units])
    if clean:
        scan = _clean(scan, report, cluster_radius)
    if scan.point_count < MIN_POINTS:
        raise ScanError(f"{path}: only {scan.point_count} points left after the intake; need >= {MIN_POINTS}")
    report.warnings = check_scan_frame(scan.points) + check_person_shape(scan.points, path)
    scan.warnings = list(report.warnings)
    for message in report.warnings:
        warnings.warn(f"{path}: {message}", ScanWarning, stacklevel=2)
    report.coverage = coverage(scan.points, scan.normals)
    return scan, report


def _recentre(scan: Scan, report: IntakeReport, path) -> Scan:
    """``scan`` moved to the origin when its coordinates are too far for float32 (`recentre_far_points`);
    the shift and a message go into ``report``."""
    points, shift = recentre_far_points(scan.points, path)
    if shift is None:
        return scan
    report.shift = shift.tolist()
    report.messages.append(
        f"coordinates up to {np.abs(scan.points).max():.3g} from the origin, too far for float32: moved "
        f"by {np.round(-shift, 3).tolist()} (the outputs are in the moved frame)"
    )
    return replace(scan, points=points)


def _choose_up(scan: Scan, report: IntakeReport) -> Scan:
    """With no up axis given: the first of Y, -Y (and, where the points are no standing person's shape
    along Y, Z, -Z) along which a floor lies under a standing person's shape (`person_shape` within
    `PERSON_DEPTH_WARN` above the floor); a capture saved Z up, as Blender and many photogrammetry tools
    save them, is found so. Where none does, Y, or -Y when a floor lies above the person along Y and none
    below; a person lying along Z is then refused by `check_person_shape`, which names --up z (with no
    floor, nothing tells up from down)."""
    floors: dict[str, Floor | None] = {}  # the floor under the points along each axis tried

    def standing(axis: str) -> bool:
        turned = _as_tall_as_a_person(scan.points @ UP_AXES[axis].T)
        floor = floors[axis] = find_floor(turned)
        return floor is not None and person_shape(turned[floor.height(turned) > 0.05]) <= PERSON_DEPTH_WARN

    # Z only where the scan is no standing person along Y: a person holding something out in front has a
    # floor-like plane and a standing person's shape along Z too
    standing_along_y = person_shape(scan.points) <= PERSON_DEPTH_WARN  # a ratio: whatever the unit
    axes = ("y", "-y") if standing_along_y else ("y", "-y", "z", "-z")
    axis = next((a for a in axes if standing(a)), None)
    if axis is None:  # every axis tried: no floor under a standing person
        axis = "-y" if floors["y"] is None and floors["-y"] is not None else "y"
    if axis == "y":
        return scan
    where = "above the person" if axis == "-y" else f"under a standing person along {axis.upper()}"
    report.up = axis
    report.messages.append(f"up axis: {axis} (the floor lies {where}; pass --up to override)")
    turn = UP_AXES[axis].T
    return replace(
        scan, points=scan.points @ turn, normals=None if scan.normals is None else scan.normals @ turn
    )


def _as_tall_as_a_person(points: np.ndarray) -> np.ndarray:
    """(N, 3) Y-up ``points`` scaled to a robust height of 1.7 m: a scale-free look, whatever the unit."""
    return points / max(robust_height(points), 1e-9) * 1.7


def _clean(scan: Scan, report: IntakeReport, cluster_radius: float) -> Scan:
    """Floor, clutter and outlier removal of a scan in metres, Y up; fills ``report``."""
    floor = find_floor(scan.points)
    if floor is not None:
        scan, removed = remove_floor_plane(scan, floor)
        report.floor = {
            "normal": floor.normal.tolist(),
            "tilt_deg": round(floor.tilt_deg, 2),
            "sigma_m": floor.sigma,
            "removed": removed,
        }
        report.messages.append(f"floor: {removed} points removed (tilt {floor.tilt_deg:.1f}°)")
    scan, report.clutter_removed = largest_cluster(scan, cluster_radius)
    scan, report.outliers_removed = remove_outliers(scan)
    if report.clutter_removed:
        report.messages.append(f"clutter: {report.clutter_removed} points outside the person removed")
    return scan
