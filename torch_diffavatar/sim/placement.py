"""Initial 3D placement of a meshed sewing pattern around any body (issue #3, item 6).

GarmentCode places its panels flat around *its own* mean body (1.72 m, waist level 108.8 cm,
``/work/shared/garmentcode/body/mean_all.yaml``), with gaps and at heights that suit that body only.
On another body (the default Anny body is 1.625 m) flat panels start inside the body or across it,
and sewing then pulls cloth through the body. `place_garment` instead *wraps* the panels around the
body at hand (only the initial 3D positions ``vert_pos`` change; the 2D rest shape is untouched); see
the steps below. `place_from_drape` places a mesh where another meshing of the same pattern lies draped
(already sewn, in that drape's fold state).

1. **Landmarks** (`body_landmarks`): horizontal cross-sections of the body mesh (exact plane
   intersections, split into connected loops) give the floor, crotch, waist, hip, armpit, shoulder
   (acromion) and neck-base heights, and each arm's axis as a polyline (slice centroids below the
   armpit, the upper-arm line extended up to the shoulder) with its radius. Given the arms' joints
   (``arm_joints``, e.g. of a posed Anny body), an axis that misses them (a bent elbow, a level upper
   arm: horizontal sections lose the forearm) is taken along the joints, from sections across them.
2. **Vertical map**: GarmentCode heights are mapped to the body through matching landmarks (floor,
   crotch, waist, shoulder, neck base, top of the head), anchored at the waist, with the slope clamped
   to [0.9, 1.1] so that panels are moved, not squashed.
3. **Wrap**: torso panels are laid *by arc length* on an elliptic tube whose cross-section at each
   height encloses the body's torso (both legs below the crotch; the arms cut off above the armpits)
   with a clearance, is widened when the front + back panels are wider (so side seams meet), is kept
   narrower than the gap to the arms (deeper instead), and changes with height at a bounded slope (so
   the wrap stays close to an isometry of the flat panels). Front panels start at the front centre,
   back panels at the back centre. Trouser panels wrap the same way around one leg (one half of the
   hips above the crotch). Sleeves wrap around a tube along the arm's smoothed axis polyline (long
   sleeves follow the bent elbows of Anny's A-pose) and slide outward until their caps clear the
   shoulder. Panels sewn on another panel rather than around the body (collars, and any panel whose
   GarmentCode placement is not flat facing front or back) are laid on their partner through the 2D map
   of their shared seam (`_attachments`): a seam whose edges run the same way (a collar turned down over
   the bodice) folds the panel over its partner, just outside it, with the same surface orientation. A
   collar laid standing up instead is pulled through a half turn by sewing and ends folded against
   itself at the V-neck's point (flipped triangles).
4. **Clearance**: tops are lifted until their shoulder seams clear the shoulders, torso / leg tubes are
   widened until no vertex is too close, and what remains is pushed out along the body normal with
   smooth bumps, until every panel vertex is ``vertex_clearance`` and the midpoint of every stitched
   pair ``stitch_clearance`` outside the body (signed distance to the closest point of the body mesh).
   A push that would tear triangles (`_untear`: GarmentCode's jumpsuit's sleeve-cap corners) is spread
   over the push radius instead.

Limitations: assumes our world frame (Y up, metres, facing +Z), a roughly symmetric GarmentCode-style
layout (front panels at +Z, back panels at −Z, centred on x = 0) and a standing body with arms away from
the torso below the armpits (near the A-pose; elbows bent or upper arms level need ``arm_joints``; arms
held lower are dressed in the A-pose and then posed, `a_pose_route`). Without
separable arms or joints, sleeves fall back to GarmentCode's arm line scaled to the body. The wrap is not
an exact isometry: on the bundled templates 95 % of the triangles start within a Green strain of 0.35 of
their rest shape, but a handful near the armpits (where the clearance pushes act) start more distorted;
sewing relaxes them.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from torch_diffavatar.geometry import closest_point_on_triangles, green_strain, yaw_rotation
from torch_diffavatar.pattern.garment_mesh import GarmentMesh
from torch_diffavatar.pattern.garmentcode import GC_BODY
from torch_diffavatar.sim.forward_drape import PoseRoute

__all__ = [
    "GC_BODY",
    "BodyLandmarks",
    "body_landmarks",
    "body_signed_distance",
    "place_from_drape",
    "place_garment",
]

_SLICE_STEP = 0.005  # [m] spacing of the horizontal cross-sections
_SMOOTH_WINDOW = 0.03  # [m] each cross-section encloses the body within ± this height
_CENTRE_WINDOW = 0.08  # [m] cross-section centres are averaged over ± this height
_ARM_GAP = 0.015  # [m] free space kept between the torso wrap and the arms
_SLEEVE_SEAM_MARGIN = 0.01  # [m] sleeve panels start at least this far from the top / bottom of the arm
_CUFF_MARGIN = 0.01  # [m] a sleeve longer than the arm starts with its cuff this far before the axis end
_ARM_STEP = 0.01  # [m] sample spacing of an arm axis along its joints (`_arm_axis_along`)
# an arm axis from horizontal sections that misses the body's elbow or wrist joint by more than this, or
# starts farther than the other from its shoulder joint, is taken along the joints instead. On the A-pose
# (10 bodies) they miss by 0.6-1.2 cm and 2.4-3.0 cm; posed (`random_pose`), 13 of 20 arms missed by
# 3.9-28.5 cm and 5.4-19.2 cm, or had no axis.
_ARM_JOINT_TOL = 0.03
_ARM_ROOT_TOL = 0.05
_MAX_SLOPE = 0.3  # largest change of a wrap radius per metre along the body / arm (near-isometric)
# a torso wrap narrowed to pass between the arms may get at most this factor deeper than the body's enclosing
# ellipse: an ellipse barely wider than the body must be arbitrarily deep to enclose it (2.3 m was seen)
_MAX_NARROW_DEPTH = 1.5


@dataclass
class BodyLandmarks:
    """Heights and arm axes of a standing body in the world frame (Y up, facing +Z). Units: metres.

    Attributes:
        floor_y, top_y: lowest and highest body point.
        crotch_y: where the legs join.
        hip_y: widest torso girth between crotch and waist.
        waist_y: narrowest torso girth between crotch and armpit.
        armpit_y: where the arms join the torso.
        shoulder_y: acromion level (top of the shoulders at their outer end).
        neck_y: base of the neck.
        arm_left, arm_right: (K, 3) float64 arm axis polylines from the shoulder joint outward (left = +X),
            or None when the arms cannot be separated from the torso.
        arm_left_radius, arm_right_radius: (K,) float64 arm radius at each polyline point.
    """

    floor_y: float
    top_y: float
    crotch_y: float
    hip_y: float
    waist_y: float
    armpit_y: float
    shoulder_y: float
    neck_y: float
    arm_left: np.ndarray | None = None
    arm_right: np.ndarray | None = None
    arm_left_radius: np.ndarray | None = None
    arm_right_radius: np.ndarray | None = None
    _sections: object = field(default=None, repr=False, compare=False)

    @property
    def height(self) -> float:
        """Body height [m]."""
        return self.top_y - self.floor_y


# ------------------------------------------------------------------------------------------------------
# body cross-sections


class _Slicer:
    """Connected loops of plane sections (horizontal, or any plane) of a closed triangle mesh."""

    def __init__(self, verts: np.ndarray, faces: np.ndarray):
        self.verts = verts
        edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
        self.edges, inv = np.unique(edges, axis=0, return_inverse=True)
        self.face_edges = inv.reshape(3, -1).T  # (F, 3) edge ids

    def components(self, h: float) -> list[np.ndarray]:
        """Cross-section loops at height ``h``: list of (n, 3) points on the mesh edges."""
        y = self.verts[:, 1]
        ea, eb = self.edges[:, 0], self.edges[:, 1]
        cross = (y[ea] - h) * (y[eb] - h) < 0
        crossing = np.nonzero(cross)[0]
        if len(crossing) == 0:
            return []
        t = (h - y[ea[crossing]]) / (y[eb[crossing]] - y[ea[crossing]])
        return self._loops(cross, crossing, t)

    def plane_components(self, origin: np.ndarray, normal: np.ndarray) -> list[np.ndarray]:
        """Cross-section loops by the plane through ``origin`` (3,) [m] with unit ``normal`` (3,)."""
        s = (self.verts - origin) @ normal
        ea, eb = self.edges[:, 0], self.edges[:, 1]
        cross = s[ea] * s[eb] < 0
        crossing = np.nonzero(cross)[0]
        if len(crossing) == 0:
            return []
        t = s[ea[crossing]] / (s[ea[crossing]] - s[eb[crossing]])
        return self._loops(cross, crossing, t)

    def _loops(self, cross: np.ndarray, crossing: np.ndarray, t: np.ndarray) -> list[np.ndarray]:
        """Split the crossing points (edge ids ``crossing``, at fraction ``t`` along them) into loops."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        ea, eb = self.edges[:, 0], self.edges[:, 1]
        fi, k = np.nonzero(cross[self.face_edges])
        eid = self.face_edges[fi, k]
        order = np.argsort(fi, kind="stable")
        fi, eid = fi[order], eid[order]
        # a face crossing the plane has exactly two crossing edges: link them
        first = np.ones(len(fi), dtype=bool)
        first[1:] = fi[1:] != fi[:-1]
        a, b = eid[first], eid[np.nonzero(first)[0] + 1]
        n = len(self.edges)
        _, label = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n)), directed=False)
        pts = self.verts[ea[crossing]] + t[:, None] * (self.verts[eb[crossing]] - self.verts[ea[crossing]])
        lab = label[crossing]
        return [pts[lab == l] for l in np.unique(lab)]


def _girth(points: np.ndarray) -> float:
    """Convex-hull perimeter [m] of (n, 3) section points in the x–z plane."""
    from scipy.spatial import ConvexHull

    xz = points[:, [0, 2]]
    if len(xz) < 3:
        return 0.0
    try:
        hull = xz[ConvexHull(xz).vertices]
    except Exception:  # degenerate (collinear) section
        return float(2 * np.ptp(xz, axis=0).sum())
    return float(np.linalg.norm(hull - np.roll(hull, 1, axis=0), axis=1).sum())


@dataclass
class _Sections:
    """Per-height cross-sections: (S,) heights and, per height, the torso / leg loops."""

    heights: np.ndarray
    central: list[np.ndarray | None]  # loop containing x = 0 (torso, neck, head)
    legs: list[tuple[np.ndarray | None, np.ndarray | None]]  # (left, right) below the crotch
    arms: list[tuple[list[np.ndarray], list[np.ndarray]]]  # (left, right) non-central loops
    slicer: _Slicer | None = None  # for sections by other planes (`_arm_axis_along`)


def _sections(verts: np.ndarray, faces: np.ndarray) -> _Sections:
    slicer = _Slicer(verts, faces)
    lo, hi = verts[:, 1].min(), verts[:, 1].max()
    heights = np.arange(lo + _SLICE_STEP / 2, hi, _SLICE_STEP)
    central, legs, arms = [], [], []
    for h in heights:
        comps = [c for c in slicer.components(h) if len(c) >= 3]
        cen = [c for c in comps if c[:, 0].min() <= 0.0 <= c[:, 0].max()]
        c0 = max(cen, key=len) if cen else None
        # inner loops (mouth, nostrils) lie inside the central loop's x-range: keep only outer ones
        others = [c for c in comps if c0 is None or not (c is c0 or _inside_range(c, c0))]
        left = [c for c in others if c[:, 0].mean() > 0]
        right = [c for c in others if c[:, 0].mean() < 0]
        central.append(c0)
        if c0 is None:
            legs.append((_nearest_to_midplane(left), _nearest_to_midplane(right)))
        else:
            legs.append((None, None))
        arms.append((left, right))
    return _Sections(heights, central, legs, arms, slicer)


def _nearest_to_midplane(loops: list[np.ndarray]) -> np.ndarray | None:
    return min(loops, key=lambda c: abs(c[:, 0].mean())) if loops else None


def _inside_range(c: np.ndarray, outer: np.ndarray) -> bool:
    return bool(
        c[:, 0].min() >= outer[:, 0].min()
        and c[:, 0].max() <= outer[:, 0].max()
        and c[:, 2].min() >= outer[:, 2].min()
        and c[:, 2].max() <= outer[:, 2].max()
    )


def _check_body(verts, faces) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(verts, torch.Tensor):
        verts = verts.detach().cpu().numpy()
    if isinstance(faces, torch.Tensor):
        faces = faces.detach().cpu().numpy()
    verts, faces = np.asarray(verts, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    if verts.ndim != 2 or verts.shape[1] != 3 or len(verts) < 4:
        raise ValueError(f"body_verts must be (Vb, 3) with Vb >= 4, got {verts.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError(f"body_faces must be (Fb, 3), got {faces.shape}")
    if faces.min() < 0 or faces.max() >= len(verts):
        raise ValueError(f"body_faces index out of range [0, {len(verts)})")
    if not np.all(np.isfinite(verts)):
        raise ValueError("body_verts contain NaN or inf")
    height = np.ptp(verts[:, 1])
    if not 0.5 < height < 2.8:
        raise ValueError(
            f"body is {height:.3f} m tall along +Y: expected a standing body in metres, Y up "
            "(convert units/axes before placing garments)"
        )
    return verts, faces


def body_landmarks(verts, faces, arm_joints: dict | None = None) -> BodyLandmarks:
    """Landmarks of a standing body mesh from its horizontal cross-sections.

    Args:
        verts: (Vb, 3) body vertices [m], world frame (Y up, facing +Z), numpy or torch.
        faces: (Fb, 3) int triangles of a closed mesh.
        arm_joints: optional ``{"left": (J, 3), "right": (J, 3)}`` joint positions [m] of each arm from
            the shoulder joint through the elbow and the wrist into the hand (J >= 3; left = +X), e.g.
            `BodyModel.arm_joints`. Horizontal sections lose an arm whose elbow is bent or whose upper
            arm is nearly level; an arm axis that misses these joints (`_strays_from`) is taken along them.
    """
    verts, faces = _check_body(verts, faces)
    return _landmarks_from_sections(_sections(verts, faces), verts, arm_joints)


def _landmarks_from_sections(
    sec: _Sections, verts: np.ndarray, arm_joints: dict | None = None
) -> BodyLandmarks:
    hs = sec.heights
    floor, top = float(verts[:, 1].min()), float(verts[:, 1].max())
    height = top - floor
    rel = (hs - floor) / height
    has_c = np.array([c is not None for c in sec.central])
    # crotch: lowest height from which the torso section exists continuously up to 70 % of the height
    band = (rel > 0.3) & (rel < 0.7)
    idx = np.nonzero(band)[0]
    crotch_i = idx[0]
    for i in idx[::-1]:
        if not has_c[i]:
            crotch_i = i + 1
            break
    crotch_y = float(hs[min(crotch_i, len(hs) - 1)])
    # armpit: top of the longest band of heights (below 90 %) where both arms are separate loops. Not
    # simply the highest such height: on some bodies the ear lobes hang below 90 % of the height and
    # are separate loops either side of the head, which put the "armpit" above the shoulders.
    both = np.array([bool(l) and bool(r) for l, r in sec.arms]) & (hs > crotch_y) & (rel < 0.9)
    if both.any():
        idx = np.nonzero(both)[0]
        runs = np.split(idx, np.nonzero(np.diff(idx) > 1)[0] + 1)
        armpit_y = float(hs[max(runs, key=len)[-1]])
    else:
        armpit_y = floor + 0.75 * height
    # shoulder / neck: central width collapses above the armpit
    width = np.array([np.ptp(c[:, 0]) if c is not None else 0.0 for c in sec.central])
    above = np.nonzero((hs > armpit_y) & (rel < 0.95))[0]
    wmax = width[above].max() if len(above) else 0.0
    shoulder_y = neck_y = None
    for i in above:
        if shoulder_y is None and hs[i] > hs[above[np.argmax(width[above])]] and width[i] < 0.7 * wmax:
            shoulder_y = float(hs[i])
        if width[i] < 0.45 * wmax and hs[i] > hs[above[np.argmax(width[above])]]:
            neck_y = float(hs[i])
            break
    if neck_y is None:
        neck_y = floor + 0.847 * height
    if shoulder_y is None or shoulder_y >= neck_y:
        shoulder_y = neck_y - 0.02 * height
    # waist / hip from the torso girth
    girth = np.array([_girth(c) if c is not None else np.nan for c in sec.central])
    span = armpit_y - crotch_y
    wband = np.nonzero((hs > crotch_y + 0.25 * span) & (hs < armpit_y - 0.2 * span) & has_c)[0]
    waist_y = float(hs[wband[np.nanargmin(girth[wband])]]) if len(wband) else crotch_y + 0.6 * span
    hband = np.nonzero((hs >= crotch_y) & (hs <= waist_y) & has_c)[0]
    hip_y = float(hs[hband[np.nanargmax(girth[hband])]]) if len(hband) else 0.5 * (crotch_y + waist_y)
    lm = BodyLandmarks(floor, top, crotch_y, hip_y, waist_y, armpit_y, shoulder_y, neck_y, _sections=sec)
    for side, name in ((0, "left"), (1, "right")):
        axis = _arm_axis(sec, side, armpit_y, shoulder_y, crotch_y, height)
        chain = None if arm_joints is None else np.asarray(arm_joints[name], dtype=np.float64)
        if chain is not None and (chain.ndim != 2 or chain.shape[0] < 3 or chain.shape[1] != 3):
            raise ValueError(f"arm_joints[{name!r}] must be (J >= 3, 3) [m], got shape {chain.shape}")
        if chain is not None and (axis is None or _strays_from(axis[0], chain)):
            axis = _arm_axis_along(sec.slicer, chain)
        if axis is not None:
            setattr(lm, f"arm_{name}", axis[0])
            setattr(lm, f"arm_{name}_radius", axis[1])
    return lm


def _arm_axis(sec: _Sections, side: int, armpit_y, shoulder_y, crotch_y, height):
    """(K, 3) arm axis polyline from the shoulder joint outward and (K,) radii, or None."""
    cents, loops = [], []
    for i in range(len(sec.heights) - 1, -1, -1):
        h = sec.heights[i]
        if h > armpit_y or h < crotch_y:
            continue
        loops_here = sec.arms[i][side]
        if len(loops_here) != 1:
            if cents:  # fingers (several loops) or the end of the arm
                break
            continue
        c = loops_here[0]
        cents.append(c.mean(0))
        loops.append(c)
    if len(cents) < 6:
        return None
    cents = np.array(cents)
    # upper arm: line through the centroids 2–10 % of the height below the armpit
    sel = (cents[:, 1] < armpit_y - 0.012 * height) & (cents[:, 1] > armpit_y - 0.06 * height)
    if sel.sum() < 3:
        sel = np.arange(len(cents)) < max(3, len(cents) // 3)
    pts = cents[sel]
    mean = pts.mean(0)
    direction = np.linalg.svd(pts - mean)[2][0]
    if direction[1] > 0:
        direction = -direction  # pointing down the arm
    root_y = 0.5 * (armpit_y + shoulder_y)
    root = mean + direction * (root_y - mean[1]) / direction[1]
    keep = cents[:, 1] < armpit_y - 0.012 * height
    poly = np.concatenate([root[None], cents[keep]])
    # smooth the centroid chain (3-point moving average, ends fixed)
    if len(poly) > 3:
        poly[1:-1] = (poly[:-2] + poly[1:-1] + poly[2:]) / 3.0
    # radius: largest distance of each loop to the local axis line
    loops = [loops[i] for i in np.nonzero(keep)[0]]
    tang = np.gradient(poly, axis=0)
    tang /= np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-12)
    radii = np.empty(len(poly))
    for k, loop in enumerate(loops, start=1):
        d = loop - poly[k]
        d -= (d @ tang[k])[:, None] * tang[k]
        radii[k] = np.linalg.norm(d, axis=1).max()
    radii[0] = 1.25 * radii[1]  # the shoulder is thicker than the arm below the armpit
    return poly, radii


def _strays_from(poly: np.ndarray, chain: np.ndarray) -> bool:
    """True if the arm axis ``poly`` (K, 3) misses the joints of ``chain`` (J >= 3, shoulder, elbow, wrist,
    ...) by more than `_ARM_JOINT_TOL` (elbow, wrist) or `_ARM_ROOT_TOL` (its root from the shoulder)."""
    a, ab = poly[:-1], np.diff(poly, axis=0)

    def off(p):
        t = np.clip(((p - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-12), 0.0, 1.0)
        return float(np.linalg.norm(a + t[:, None] * ab - p, axis=1).min())

    return bool(
        np.linalg.norm(poly[0] - chain[0]) > _ARM_ROOT_TOL
        or max(off(chain[1]), off(chain[2])) > _ARM_JOINT_TOL
    )


def _arm_axis_along(slicer: _Slicer, chain: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, 3) arm axis and (K,) radii [m] along a joint chain (J, 3) from the shoulder joint to the hand.

    The chain is resampled about every `_ARM_STEP`; at each sample the section by the plane across the chain
    (direction over ±2 samples, which rounds the elbow) gives the loop nearest the sample, whose centre is
    the axis point and whose largest distance from it the radius (the same as the horizontal sections'
    axis). Near the shoulder that plane also cuts the torso, in one loop: samples whose loop lies far off
    or is more than twice the median radius keep the chain point and an interpolated radius.
    """
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(chain, axis=0), axis=1))])
    s = np.linspace(0.0, arc[-1], max(2, round(arc[-1] / _ARM_STEP) + 1))
    pts = np.stack([np.interp(s, arc, chain[:, i]) for i in range(3)], axis=1)
    n = len(pts)
    ahead, behind = np.minimum(np.arange(n) + 2, n - 1), np.maximum(np.arange(n) - 2, 0)
    tang = pts[ahead] - pts[behind]
    tang /= np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-12)
    axis, radii = pts.copy(), np.full(n, np.nan)
    for k in range(n):
        loops = [c for c in slicer.plane_components(pts[k], tang[k]) if len(c) >= 3]
        if not loops:
            continue
        loop = min(loops, key=lambda c: np.linalg.norm(c.mean(0) - pts[k]))
        centre = loop.mean(0)
        if np.linalg.norm(centre - pts[k]) > _ARM_JOINT_TOL:
            continue
        d = loop - centre
        d -= (d @ tang[k])[:, None] * tang[k]
        axis[k], radii[k] = centre, np.linalg.norm(d, axis=1).max()
    good = np.isfinite(radii)
    if good.sum() < 2:
        raise ValueError("the arm's joint chain does not run inside the body mesh")
    good &= radii < 2.0 * np.median(radii[good])
    axis[~good] = pts[~good]
    radii = np.interp(s, s[good], radii[good])
    radii[0] = 1.25 * radii[1]  # the shoulder is thicker than the arm below it (as `_arm_axis`)
    return axis, radii


# ------------------------------------------------------------------------------------------------------
# signed distance to the body


class _BodyDistance:
    """Signed distance to a closed body mesh (> 0 outside).

    The closest point is searched exactly among the ``k`` triangles whose centroids are nearest (exact
    for the fine, even triangulations of body models); its side comes from the interpolated vertex normal.
    """

    def __init__(self, verts: np.ndarray, faces: np.ndarray, k: int = 16):
        from scipy.spatial import cKDTree

        self.verts, self.faces = verts, faces
        fn = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]])
        vn = np.zeros_like(verts)
        for j in range(3):
            np.add.at(vn, faces[:, j], fn)
        self.vnormals = vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-20)
        self.tree = cKDTree(verts[faces].mean(1))
        self.k = min(k, len(faces))

    def __call__(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """points (N, 3) -> signed distance (N,) [m] and outward unit normal (N, 3) at the closest point."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(points) == 0:
            return np.zeros(0), np.zeros((0, 3))
        _, cand = self.tree.query(points, k=self.k)
        cand = cand.reshape(len(points), self.k)
        tri = self.verts[self.faces[cand]]  # (N, k, 3, 3)
        p = np.broadcast_to(points[:, None], (len(points), self.k, 3))
        corners = (torch.from_numpy(np.ascontiguousarray(c)) for c in (p, *tri.transpose(2, 0, 1, 3)))
        bary = closest_point_on_triangles(*corners).numpy()
        q = (bary[..., None] * tri).sum(2)  # (N, k, 3)
        d = np.linalg.norm(p - q, axis=-1)
        best = d.argmin(1)
        rows = np.arange(len(points))
        q, bary, f = q[rows, best], bary[rows, best], cand[rows, best]
        n = (bary[:, :, None] * self.vnormals[self.faces[f]]).sum(1)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)
        sign = np.where(((points - q) * n).sum(1) < 0, -1.0, 1.0)
        return sign * d[rows, best], n


def body_signed_distance(points, body_verts, body_faces) -> np.ndarray:
    """Signed distance [m] of (N, 3) points to a closed body mesh: > 0 outside, < 0 inside. (N,) float64."""
    verts, faces = _check_body(body_verts, body_faces)
    if isinstance(points, torch.Tensor):
        points = points.detach().cpu().numpy()
    return _BodyDistance(verts, faces)(np.asarray(points, dtype=np.float64))[0]


# ------------------------------------------------------------------------------------------------------
# wrapping


def _ellipse_arc_point(s: np.ndarray, ax: np.ndarray, az: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Point at signed arc length ``s`` from the +z pole of ellipses (ax, az), toward +x.

    All inputs (N,); returns (x, z) offsets from the centre. |s| is clamped to half the perimeter.
    """
    t = np.linspace(0.0, math.pi, 257)  # (T,) parameter from the +z pole to the −z pole
    dx = ax[:, None] * np.cos(t)[None]  # d/dt of ax sin t
    dz = -az[:, None] * np.sin(t)[None]
    speed = np.hypot(dx, dz)
    arc = np.concatenate(
        [np.zeros((len(s), 1)), np.cumsum(0.5 * (speed[:, 1:] + speed[:, :-1]) * np.diff(t), 1)], 1
    )
    a = np.minimum(np.abs(s), arc[:, -1])
    k = np.clip((arc < a[:, None]).sum(1), 1, len(t) - 1)
    a0, a1 = arc[np.arange(len(s)), k - 1], arc[np.arange(len(s)), k]
    tt = t[k - 1] + (a - a0) / np.maximum(a1 - a0, 1e-15) * (t[k] - t[k - 1])
    return np.sign(s) * ax * np.sin(tt), az * np.cos(tt)


def _perimeter(ax, az):
    """Ramanujan's ellipse perimeter."""
    h = ((ax - az) / (ax + az)) ** 2
    return math.pi * (ax + az) * (1 + 3 * h / (10 + np.sqrt(4 - 3 * h)))


def _depth_for_perimeter(ax: np.ndarray, perimeter: np.ndarray) -> np.ndarray:
    """Semi-axis az (N,) such that the ellipse (ax, az) has the given perimeter (at least 1 mm)."""
    lo, hi = np.full_like(ax, 1e-3), np.full_like(ax, 5.0)
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        small = _perimeter(ax, mid) < perimeter
        lo, hi = np.where(small, mid, lo), np.where(small, hi, mid)
    return hi


def _moving_average(values: np.ndarray, half: int) -> np.ndarray:
    """Moving average over ±``half`` samples (shrinking window at the ends). values: (S,) or (S, k)."""
    c = np.concatenate([np.zeros((1,) + values.shape[1:]), np.cumsum(values, axis=0)])
    i = np.arange(len(values))
    lo, hi = np.maximum(i - half, 0), np.minimum(i + half + 1, len(values))
    shape = (-1,) + (1,) * (values.ndim - 1)
    return (c[hi] - c[lo]) / (hi - lo).reshape(shape)


def _slope_envelope(t: np.ndarray, f: np.ndarray, slope: float) -> np.ndarray:
    """Smallest function >= f whose slope along t is at most ``slope``: max_j f_j − slope·|t − t_j|."""
    return (f[None, :] - slope * np.abs(t[:, None] - t[None, :])).max(1)


class _RegionSections:
    """Smooth enclosing ellipses (cx, cz, ax, az) of one body region along the height grid.

    Centres are averaged over ±``_CENTRE_WINDOW``; each ellipse (about its smoothed centre, with the
    aspect of the local extents) encloses the region's cross-sections within ±``_SMOOTH_WINDOW``.
    """

    def __init__(self, heights: np.ndarray, loops: list[np.ndarray | None]):
        self.room = None  # (S,) largest half-width [m] allowed per height (arms beside the torso), or None
        self.window = []  # per height: (dx, dz) of the enclosed section points about the centre
        ok = np.array([lp is not None and len(lp) >= 3 for lp in loops])
        self.heights = heights[ok]
        loops = [lp for lp, k in zip(loops, ok) if k]
        if not len(loops):
            self.rows = np.zeros((0, 4))
            return
        bbox_c = np.array([0.5 * (lp.min(0) + lp.max(0))[[0, 2]] for lp in loops])
        centre = _moving_average(bbox_c, int(round(_CENTRE_WINDOW / _SLICE_STEP)))
        half = int(round(_SMOOTH_WINDOW / _SLICE_STEP))
        rows = []
        for i in range(len(loops)):
            pts = np.concatenate(loops[max(0, i - half) : i + half + 1])
            dx, dz = pts[:, 0] - centre[i, 0], pts[:, 2] - centre[i, 1]
            ax, az = max(np.abs(dx).max(), 1e-3), max(np.abs(dz).max(), 1e-3)
            k = np.sqrt((dx / ax) ** 2 + (dz / az) ** 2).max()
            rows.append((centre[i, 0], centre[i, 1], ax * k, az * k))
            self.window.append((dx, dz))
        self.rows = np.array(rows)

    def depth_for_width(self, i: int, ax: float) -> float:
        """Smallest az of an ellipse with semi-axis ``ax`` around height i's centre enclosing its window
        (inf when ``ax`` is narrower than the body there)."""
        dx, dz = self.window[i]
        if np.abs(dx).max() >= ax:
            return np.inf
        return float((np.abs(dz) / np.sqrt(1.0 - (dx / ax) ** 2)).max())

    def width_for_depth(self, i: int, az: float) -> float:
        """Smallest semi-axis ax of an ellipse with semi-axis ``az`` around height i's centre enclosing its
        window (the inverse of `depth_for_width`, which falls as the width grows)."""
        dx, dz = self.window[i]
        if np.abs(dz).max() >= az:
            return np.inf
        return float((np.abs(dx) / np.sqrt(1.0 - (dz / az) ** 2)).max())

    def at(self, y: np.ndarray) -> np.ndarray:
        """(N,) heights -> (N, 4) (cx, cz, ax, az), clamped to the region's height range."""
        return np.stack([np.interp(y, self.heights, self.rows[:, k]) for k in range(4)], axis=1)


def _vertical_map(lm: BodyLandmarks, slope_range: tuple[float, float] = (0.9, 1.1)):
    """GarmentCode height [m] -> body height [m]: through matching landmarks (floor, crotch, waist,
    shoulder, neck base, top of the head), with the slope clamped to ``slope_range`` (panels are only
    moved, never squashed by more than 10 %), anchored at the waist."""
    gc = np.array(
        [0.0, GC_BODY["crotch"], GC_BODY["waist"], GC_BODY["shoulder"], GC_BODY["neck"], GC_BODY["height"]]
    )
    body = np.array([lm.floor_y, lm.crotch_y, lm.waist_y, lm.shoulder_y, lm.neck_y, lm.top_y])
    grid = np.arange(-0.5, 2.5, 0.005)
    slope = np.clip(np.gradient(np.interp(grid, gc, body), grid), *slope_range)
    slope = np.where(
        (grid < gc[0]) | (grid > gc[-1]), np.clip(lm.height / GC_BODY["height"], *slope_range), slope
    )
    integral = np.concatenate([[0.0], np.cumsum(0.5 * (slope[1:] + slope[:-1]) * np.diff(grid))])
    integral += lm.waist_y - np.interp(GC_BODY["waist"], grid, integral)

    def vmap(y):
        return np.interp(np.asarray(y, dtype=np.float64), grid, integral)

    return vmap


def _lateral_profile(key: np.ndarray, lat: np.ndarray, bin_size: float = 0.01):
    """Lateral extent of a panel set along ``key`` (height or arm coordinate).

    Args:
        key, lat: (n,) coordinates of the set's vertices along and across [m].

    Returns:
        centres (B,) of the occupied bins, lo (B,), hi (B,) lateral min / max per bin (each bin also
        covers its neighbours so that narrow bins on curved outlines do not jump).
    """
    b = np.floor(key / bin_size).astype(np.int64)
    ub, inv = np.unique(b, return_inverse=True)
    lo = np.full(len(ub), np.inf)
    hi = np.full(len(ub), -np.inf)
    np.minimum.at(lo, inv, lat)
    np.maximum.at(hi, inv, lat)
    lo_s, hi_s = lo.copy(), hi.copy()
    for k in range(len(ub)):
        near = np.abs(ub - ub[k]) <= 1
        lo_s[k], hi_s[k] = lo[near].min(), hi[near].max()
    return (ub + 0.5) * bin_size, lo_s, hi_s


def _width_on(grid: np.ndarray, centres: np.ndarray, width: np.ndarray, bin_size: float = 0.01) -> np.ndarray:
    """A profile's width sampled on ``grid`` (0 farther than one bin outside the profile)."""
    if len(centres) == 0:
        return np.zeros(len(grid))
    w = np.interp(grid, centres, width)
    outside = (grid < centres[0] - bin_size) | (grid > centres[-1] + bin_size)
    return np.where(outside, 0.0, w)


def _panel_kinds(garment: GarmentMesh, gc_pos: np.ndarray) -> list[str]:
    """Per panel: 'arm_left', 'arm_right', 'leg_left', 'leg_right', 'torso' or 'rigid'."""
    kinds = []
    vert_panel = garment.vert_panel.cpu().numpy()
    for p, name in enumerate(garment.panel_names):
        pos = gc_pos[vert_panel == p]
        if len(pos) < 3:
            kinds.append("rigid")
            continue
        centered = pos - pos.mean(0)
        normal = np.linalg.svd(centered, full_matrices=False)[2][2]
        cx = pos[:, 0].mean()
        sleeve_like = "sleeve" in name.lower() or (
            abs(cx) > 0.16
            and pos[:, 1].mean() > GC_BODY["waist"]
            and np.ptp(pos[:, 1]) < 0.9 * GC_BODY["height"] / 2
        )
        if abs(normal[2]) < 0.7:
            kinds.append("rigid")
        elif sleeve_like and abs(cx) > 0.1:
            kinds.append("arm_left" if cx > 0 else "arm_right")
        elif pos[:, 1].min() < GC_BODY["crotch"] - 0.05 and (
            pos[:, 0].max() < 0.02 or pos[:, 0].min() > -0.02
        ):
            one_side = pos[:, 0].max() < 0.02
            kinds.append("leg_right" if one_side else "leg_left")
        else:
            kinds.append("torso")
    return kinds


@dataclass
class _Context:
    garment: GarmentMesh
    gc_pos: np.ndarray  # (V, 3) GarmentCode placement [m]
    vert_panel: np.ndarray
    kinds: list[str]
    front: np.ndarray  # (P,) bool: panel in front of the body (GarmentCode frame)
    lm: BodyLandmarks
    sec: _Sections
    vmap: object
    clearance: dict  # kind -> [m]
    regions: dict = field(default_factory=dict)
    attached: dict = field(default_factory=dict)  # panel -> _Attachment


def _region_sections(sec: _Sections, lm: BodyLandmarks, kind: str) -> _RegionSections:
    """Cross-sections of the torso (both legs below the crotch; arms cut off above the armpits) or of one
    leg (one half of the hips above the crotch)."""
    if kind == "torso":
        below = [c for c, h in zip(sec.central, sec.heights) if c is not None and h < lm.armpit_y]
        cap = np.abs(below[-1][:, 0]).max() if below else np.inf  # torso half-width under the armpits
        loops = []
        for c, (l, r), h in zip(sec.central, sec.legs, sec.heights):
            if c is None:
                loops.append(_union(l, r))
            elif h > lm.armpit_y:
                loops.append(c[np.abs(c[:, 0]) <= cap])
            else:
                loops.append(c)
        region = _RegionSections(sec.heights, loops)
        # half-width room between the torso's centre line and the arms' inner edges (side seams must not
        # start inside an arm); under the armpit it stays at the armpit's value up to the shoulders
        room = np.full(len(sec.heights), np.inf)
        for i, (h, c, (al, ar)) in enumerate(zip(sec.heights, sec.central, sec.arms)):
            if c is not None and h < lm.armpit_y and al and ar:
                room[i] = min(min(a[:, 0].min() for a in al), min(-a[:, 0].max() for a in ar))
        ok = np.isfinite(room)
        if ok.any():
            top = sec.heights[ok].max()
            band = (sec.heights > top) & (sec.heights < lm.shoulder_y + 0.05)
            room[band] = room[np.nonzero(ok)[0][-1]]
        region.room = np.interp(region.heights, sec.heights, room) if len(region.heights) else room[:0]
        return region
    else:
        side = 0 if kind == "leg_left" else 1
        sign = 1.0 if side == 0 else -1.0
        loops = []
        for c, lr in zip(sec.central, sec.legs):
            loops.append(lr[side] if c is None else c[sign * c[:, 0] >= 0])
    return _RegionSections(sec.heights, loops)


def _side_sets(ctx: _Context, panels: list[int]) -> list[np.ndarray]:
    """Vertex ids of the front and of the back panels among ``panels``."""
    out = []
    for is_front in (True, False):
        sel = [p for p in panels if ctx.front[p] == is_front]
        out.append(np.nonzero(np.isin(ctx.vert_panel, sel))[0])
    return out


def _wrap_torso_like(ctx: _Context, kind: str, lift: float, out: np.ndarray) -> None:
    """Wrap the panels of ``kind`` ('torso', 'leg_left', 'leg_right') around a smooth elliptic tube.

    Each height's ellipse encloses the body region with ``clearance``, grows (uniformly) to the front +
    back panel width at that height, and changes with height at a bounded slope so that the wrap stays
    close to an isometry of the flat panels.
    """
    panels = [p for p, k in enumerate(ctx.kinds) if k == kind]
    if not panels:
        return
    if kind not in ctx.regions:
        ctx.regions[kind] = _region_sections(ctx.sec, ctx.lm, kind)
    region = ctx.regions[kind]
    if len(region.heights) == 0:
        return
    sets = _side_sets(ctx, panels)
    grid = region.heights
    cx, cz, ax0, az0 = region.rows.T
    ax0, az0 = ax0 + ctx.clearance[kind], az0 + ctx.clearance[kind]
    profiles, need = [], np.zeros(len(grid))
    for verts in sets:
        if len(verts) == 0:
            profiles.append(None)
            continue
        c, lo, hi = _lateral_profile(ctx.gc_pos[verts, 1], ctx.gc_pos[verts, 0])
        if kind == "torso":  # garments are centred on x = 0
            half = np.maximum(np.abs(lo), np.abs(hi))
            lo, hi = -half, half
        c_body = ctx.vmap(c) + lift
        profiles.append((c_body, lo, hi))
        need += _width_on(grid, c_body, hi - lo)
    scale = np.maximum(need / _perimeter(ax0, az0), 1.0)
    ax = _slope_envelope(grid, ax0 * scale, _MAX_SLOPE)
    az = _slope_envelope(grid, az0 * scale, _MAX_SLOPE)
    if region.room is not None:
        # no wider than the room beside the arms: the ellipse gets narrower and deeper (still enclosing
        # the body with the clearance), and the missing perimeter goes into the depth
        limit = region.room - np.abs(cx) - _ARM_GAP
        capped = np.nonzero(ax > limit)[0]
        if len(capped):
            c = ctx.clearance[kind]
            depth = az.copy()
            for i in capped:
                inner = max(limit[i] - c, 0.0)
                deepest = _MAX_NARROW_DEPTH * az0[i] - c
                need_az = region.depth_for_width(i, inner)
                if not np.isfinite(need_az):  # no room: as wide as the body needs
                    ax[i] = min(ax[i], ax0[i])
                    continue
                if need_az > deepest:  # too deep that narrow: the narrowest width whose depth is bounded
                    inner = region.width_for_depth(i, deepest)
                    need_az = region.depth_for_width(i, inner)
                ax[i], depth[i] = min(ax[i], inner + c), max(az[i], need_az + c)
            target = np.maximum(need, _perimeter(ax0, az0))
            az = _slope_envelope(grid, np.maximum(depth, _depth_for_perimeter(ax, target)), _MAX_SLOPE)
    for g, verts in enumerate(sets):
        if len(verts) == 0:
            continue
        y = ctx.vmap(ctx.gc_pos[verts, 1]) + lift
        if kind == "torso":
            mid = np.zeros(len(verts))
        else:
            c_body, lo, hi = profiles[g]
            mid_profile = _moving_average(0.5 * (lo + hi), int(round(_CENTRE_WINDOW / 0.01)))
            mid = np.interp(y, c_body, mid_profile)
        e_cx, e_cz = np.interp(y, grid, cx), np.interp(y, grid, cz)
        e_ax, e_az = np.interp(y, grid, ax), np.interp(y, grid, az)
        dx, dz = _ellipse_arc_point(ctx.gc_pos[verts, 0] - mid, e_ax, e_az)
        out[verts, 0] = e_cx + dx
        out[verts, 1] = y
        out[verts, 2] = e_cz + (dz if g == 0 else -dz)


def _union(a, b):
    parts = [p for p in (a, b) if p is not None]
    return np.concatenate(parts) if parts else None


def _smooth_polyline(poly: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """Resample a polyline every 5 mm and smooth it over ``length`` [m] (ends kept); returns it and its
    cumulative arc length."""
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.arange(0.0, arc[-1] + 1e-9, 0.005)
    res = np.stack([np.interp(t, arc, poly[:, k]) for k in range(3)], axis=1)
    half = max(1, int(round(0.5 * length / 0.005)))
    pad = np.concatenate([2 * res[:1] - res[half:0:-1], res, 2 * res[-1:] - res[-2 : -half - 2 : -1]])
    smooth = _moving_average(pad, half)[half : half + len(res)]
    seg = np.linalg.norm(np.diff(smooth, axis=0), axis=1)
    return smooth, np.concatenate([[0.0], np.cumsum(seg)])


def _rotation_minimizing_frames(poly: np.ndarray):
    """Tangents (K, 3) and two normals e1 ('up' at the root), e2 ('front') along a polyline."""
    tang = np.gradient(poly, axis=0)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    up = np.array([0.0, 1.0, 0.0])
    e1 = up - (up @ tang[0]) * tang[0]
    e1 /= np.linalg.norm(e1)
    e1s = [e1]
    for k in range(1, len(poly)):
        e = e1s[-1] - (e1s[-1] @ tang[k]) * tang[k]
        e1s.append(e / np.linalg.norm(e))
    e1s = np.array(e1s)
    e2s = np.cross(tang, e1s)
    if e2s[0, 2] < 0:
        e2s = -e2s
    return tang, e1s, e2s


def _wrap_arm(ctx: _Context, kind: str, out: np.ndarray, shift: float = 0.0) -> None:
    """Wrap sleeve panels around a tube along the arm axis (front panels over the front of the arm)."""
    panels = [p for p, k in enumerate(ctx.kinds) if k == kind]
    if not panels:
        return
    side = 1.0 if kind == "arm_left" else -1.0
    pos = ctx.gc_pos[np.nonzero(np.isin(ctx.vert_panel, panels))[0]]
    root_gc, d_gc, n_gc = _garmentcode_arm_line(ctx, panels, side, pos)
    axis = _ArmAxis.of(ctx, side, root_gc, d_gc)
    arc = axis.arc
    sets = _side_sets(ctx, panels)
    # a sleeve longer than the arm's axis polyline (which ends inside the hand, where the fingers part) is
    # compressed along the arm to end before it, instead of being laid straight on past the hand with its
    # front and back panels far apart around it. Sewing lets the compressed sleeve relax.
    along = (pos - root_gc) @ d_gc + shift
    end = arc[-1] - _CUFF_MARGIN
    squeeze = min(1.0, end / along.max()) if along.max() > end else 1.0

    def arm_coord(p):
        a = (p - root_gc) @ d_gc + shift
        return np.where(a > 0, a * squeeze, a)

    profiles = []
    grid = np.arange(-0.3, arc[-1] + 0.5, 0.005)
    need = np.zeros(len(grid))
    for verts in sets:
        if len(verts) == 0:
            profiles.append(None)
            continue
        rel = ctx.gc_pos[verts] - root_gc
        c, lo, hi = _lateral_profile(arm_coord(ctx.gc_pos[verts]), rel @ n_gc)
        profiles.append((c, lo, hi))
        need += _width_on(grid, c, hi - lo)
    # the tube follows the arm's measured radius to the axis end (the palm). Inflating it to the shoulder's
    # radius over the hand made a cuff narrower than that tube start with its front and back panels ~10 cm
    # apart around the forearm; sewing them shut folded the longsleeve's front panel through itself.
    r_body = np.interp(grid, arc, axis.radii)
    r = _slope_envelope(grid, np.maximum(r_body + ctx.clearance[kind], need / (2 * math.pi)), _MAX_SLOPE)
    for g, verts in enumerate(sets):
        if len(verts) == 0:
            continue
        a, lat = arm_coord(ctx.gc_pos[verts]), (ctx.gc_pos[verts] - root_gc) @ n_gc
        mid = np.interp(a, profiles[g][0], _sleeve_centre(*profiles[g], grid, r))
        point, e1, e2 = axis.frame_at(a)
        rv = np.interp(a, grid, r)
        dx, dz = _ellipse_arc_point(lat - mid, rv, rv)
        front = 1.0 if g == 0 else -1.0
        out[verts] = point + dx[:, None] * e1 + front * dz[:, None] * e2


def _garmentcode_arm_line(ctx: _Context, panels: list[int], side: float, pos: np.ndarray):
    """GarmentCode's arm line of a sleeve: (root (3,), direction d (3,), in-plane normal n (3,)) [m].

    The direction follows the sleeve panels' rotation, the line runs through their centroid, and the root
    is where ``|x|`` equals GarmentCode's shoulder half width. ``pos``: (N, 3) the panels' vertices.
    """
    alpha = math.radians(GC_BODY["arm_angle_deg"])
    d_gc = np.array([side * math.cos(alpha), -math.sin(alpha), 0.0])
    rot = _panel_rotation_angle(ctx.garment, panels[0])
    if rot is not None and 10.0 < abs(math.degrees(rot)) < 80.0:
        d = np.array([math.cos(rot), math.sin(rot), 0.0])
        d_gc = d if d[0] * side > 0 else -d
    if d_gc[1] > 0:  # the arm points down
        d_gc = np.array([d_gc[0], -d_gc[1], 0.0])
    n_gc = np.array([-d_gc[1], d_gc[0], 0.0])
    if n_gc[1] < 0:
        n_gc = -n_gc
    c0 = pos.mean(0)
    root_gc = c0 + (side * GC_BODY["shoulder_half_width"] - c0[0]) / d_gc[0] * d_gc
    return root_gc, d_gc, n_gc


@dataclass(frozen=True)
class _ArmAxis:
    """The body's arm axis for a sleeve: smoothed polyline (K, 3), its arc lengths (K,) [m], the arm's
    radii there (K,) [m] and rotation-minimising frames (tangents, e1 'up', e2 'front', (K, 3) each)."""

    poly: np.ndarray
    arc: np.ndarray
    radii: np.ndarray
    tang: np.ndarray
    e1s: np.ndarray
    e2s: np.ndarray

    @staticmethod
    def of(ctx: _Context, side: float, root_gc: np.ndarray, d_gc: np.ndarray) -> _ArmAxis:
        lm = ctx.lm
        poly = lm.arm_left if side > 0 else lm.arm_right
        radii = lm.arm_left_radius if side > 0 else lm.arm_right_radius
        if poly is None:  # no separable arms: GarmentCode's line mapped to the body's heights
            root = np.array([side * GC_BODY["shoulder_half_width"], float(ctx.vmap(root_gc[1])), 0.0])
            poly = np.stack([root, root + 0.6 * d_gc])
            radii = np.array([0.05, 0.04])
        seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
        raw_arc = np.concatenate([[0.0], np.cumsum(seg)])
        poly, arc = _smooth_polyline(poly, 0.15)
        radii = np.interp(arc * raw_arc[-1] / max(arc[-1], 1e-9), raw_arc, radii)
        return _ArmAxis(poly, arc, radii, *_rotation_minimizing_frames(poly))

    def frame_at(self, a: np.ndarray):
        """Axis point and unit e1, e2 at arc lengths ``a`` (N,) [m] (straight extension beyond the ends)."""
        arc, poly = self.arc, self.poly
        k = np.clip(np.searchsorted(arc, a) - 1, 0, len(arc) - 2)
        f = np.clip((a - arc[k]) / np.maximum(arc[k + 1] - arc[k], 1e-12), 0.0, 1.0)
        point = poly[k] + f[:, None] * (poly[k + 1] - poly[k])
        point += (
            np.minimum(a, 0.0)[:, None] * self.tang[0] + np.maximum(a - arc[-1], 0.0)[:, None] * self.tang[-1]
        )
        e1 = self.e1s[k] + f[:, None] * (self.e1s[k + 1] - self.e1s[k])
        e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
        e2 = self.e2s[k] + f[:, None] * (self.e2s[k + 1] - self.e2s[k])
        e2 /= np.linalg.norm(e2, axis=1, keepdims=True)
        return point, e1, e2


def _sleeve_centre(c, lo, hi, grid, r) -> np.ndarray:
    """A sleeve panel's lateral centre at each of its profile's arm positions ``c`` [m].

    Smoothed, like the leg wraps, so that front and back panels meet on top of the arm and underneath it
    all along the sleeve. One centre line for the whole panel (the exact isometry) puts the cap off-centre
    on long tapered sleeves: their cap's underarm corner then wraps past the bottom of the arm onto the
    other side, the front and back panels cross under the arm, and sewing them to the armhole pulls cloth
    through the arm. The smoothed centre moves slowly along the sleeve (a small shear, not a stretch).
    The smoothing must not push the wide cap past the top or the bottom of the arm: each bin's centre is
    clamped so that the panel stays within its half of the tube (radius ``r`` on ``grid``), with a margin.
    """
    mid_profile = _moving_average(0.5 * (lo + hi), int(round(_CENTRE_WINDOW / 0.01)))
    quarter = 0.5 * math.pi * np.interp(c, grid, r) - _SLEEVE_SEAM_MARGIN
    low, high = hi - quarter, lo + quarter
    return np.where(low <= high, np.clip(mid_profile, low, high), 0.5 * (lo + hi))


def _panel_rotation_angle(garment: GarmentMesh, panel: int) -> float | None:
    """In-plane (about Z) rotation [rad] taking the panel's 2D frame to its GarmentCode placement."""
    sel = garment.vert_panel == panel
    uv = garment.vert_uv[sel].cpu().numpy()
    pos = garment.vert_pos[sel].cpu().numpy()[:, :2]
    if len(uv) < 3:
        return None
    a, b = uv - uv.mean(0), pos - pos.mean(0)
    u, _, vt = np.linalg.svd(a.T @ b)
    r = (u @ vt).T
    return math.atan2(r[1, 0], r[0, 0])


def _uv_orientation(garment: GarmentMesh) -> np.ndarray:
    """(P,) +1 / −1: the sign of each panel's triangle areas in its own 2D frame (the mesher orients
    triangles so that their 3D normals point out of the garment, so back panels run clockwise)."""
    t = garment.tri_vertices.cpu().numpy()
    uv = garment.vert_uv.detach().cpu().numpy()
    a, b = uv[t[:, 1]] - uv[t[:, 0]], uv[t[:, 2]] - uv[t[:, 0]]
    area = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    vp = garment.vert_panel.cpu().numpy()[t[:, 0]]
    total = np.bincount(vp, weights=area, minlength=len(garment.panel_names))
    return np.where(total < 0, -1.0, 1.0)


def _seam_map(src: np.ndarray, dst: np.ndarray, reflect: bool) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares 2D rigid map u -> R u + t taking (n, 2) ``src`` onto ``dst``; R is a rotation, or a
    reflection when ``reflect`` (Kabsch with the determinant fixed)."""
    cs, cd = src.mean(0), dst.mean(0)
    u, _, vt = np.linalg.svd((src - cs).T @ (dst - cd))
    proper = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, -proper if reflect else proper]) @ u.T
    return r, cd - r @ cs


class _PanelSurface:
    """One panel's triangles in its 2D frame: locates 2D points on it and maps them to 3D."""

    def __init__(self, garment: GarmentMesh, panel: int):
        from scipy.spatial import cKDTree

        t = garment.tri_vertices.cpu().numpy()
        vp = garment.vert_panel.cpu().numpy()
        self.tris = t[vp[t[:, 0]] == panel]
        self.uv = garment.vert_uv.detach().cpu().numpy()
        self.tree = cKDTree(self.uv[self.tris].mean(1))
        self.k = min(8, len(self.tris))

    def locate(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, 2) points -> triangle rows (n,) and barycentrics (n, 3) (negative outside the panel: the
        nearest triangle's affine extension)."""
        _, cand = self.tree.query(q, k=self.k)
        cand = cand.reshape(len(q), self.k)
        tri = self.uv[self.tris[cand]]  # (n, k, 3, 2)
        e1, e2 = tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0]
        rel = q[:, None] - tri[:, :, 0]
        det = e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0]
        b1 = (rel[..., 0] * e2[..., 1] - rel[..., 1] * e2[..., 0]) / det
        b2 = (e1[..., 0] * rel[..., 1] - e1[..., 1] * rel[..., 0]) / det
        bary = np.stack([1.0 - b1 - b2, b1, b2], -1)
        best = bary.min(-1).argmax(1)
        rows = np.arange(len(q))
        return cand[rows, best], bary[rows, best]

    def to_3d(self, q: np.ndarray, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, 2) points -> (n, 3) points on (or extending) the placed panel and its (n, 3) unit normals
        (right-hand normal of the panel's triangles in its 2D orientation)."""
        row, bary = self.locate(q)
        corners = pos[self.tris[row]]  # (n, 3, 3)
        n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)
        return (bary[:, :, None] * corners).sum(1), n


@dataclass
class _Attachment:
    """A panel laid on a partner panel through the 2D map of their shared seam (collars, cuffs ...)."""

    partner: int
    rot: np.ndarray  # (2, 2) own 2D frame -> the partner's 2D frame
    shift: np.ndarray  # (2,)
    seam: np.ndarray  # own panel vertices stitched to the partner


def _attachments(garment: GarmentMesh, kinds: list[str]) -> dict[int, _Attachment]:
    """Panels to lay on a stitch partner instead of wrapping them: every 'rigid' panel, and every panel
    whose seam to a larger panel folds it over onto that panel.

    The seam's 2D rigid map (own frame -> partner frame; a reflection between panels of opposite 2D
    orientation) keeps the sewn surface consistently oriented. For an ordinary seam it lays the panel
    beyond the partner's edge (the surface continues); for a seam whose two edges run the same way
    (GarmentCode's ``right_wrong``, e.g. a collar turned down over the bodice) it lays the panel over the
    partner: such a panel cannot be wrapped in line with the body like the panels it is sewn to.
    """
    pairs = garment.stitch_pairs.cpu().numpy()
    if len(pairs) == 0:
        return {}
    vp = garment.vert_panel.cpu().numpy()
    uv = garment.vert_uv.detach().cpu().numpy()
    orient = _uv_orientation(garment)
    area = np.zeros(len(kinds))
    t = garment.tri_vertices.cpu().numpy()
    a, b = uv[t[:, 1]] - uv[t[:, 0]], uv[t[:, 2]] - uv[t[:, 0]]
    np.add.at(area, vp[t[:, 0]], 0.5 * np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
    out = {}
    for p in range(len(kinds)):
        own_verts = np.nonzero(vp == p)[0]
        loop_pos = np.full(len(vp), -1)
        loop = garment.panel_boundary[p].cpu().numpy()
        loop_pos[loop] = np.arange(len(loop))
        best = None
        for own, other, q in _seams_of(pairs, vp, p, loop_pos, len(loop)):
            if len(own) < 2 or np.ptp(uv[own], axis=0).max() < 1e-6:
                continue
            rot, shift = _seam_map(uv[own], uv[other], orient[p] != orient[q])
            mapped = uv[own_verts] @ rot.T + shift
            _, bary = _PanelSurface(garment, q).locate(mapped)
            folded = (bary.min(1) > -1e-6).mean() > 0.5 and area[p] < area[q]
            if (kinds[p] == "rigid" or folded) and (best is None or len(own) > len(best.seam)):
                best = _Attachment(q, rot, shift, np.unique(own))
        if best is not None:
            out[p] = best
    return out


def _seams_of(pairs: np.ndarray, vp: np.ndarray, p: int, loop_pos: np.ndarray, loop_len: int):
    """Seams of panel ``p`` to other panels: (own vertices, partner vertices, partner panel) per run of
    consecutive outline vertices stitched to the same partner (a two-panel tube has two seams)."""
    for q in np.unique(vp[pairs[(vp[pairs[:, 0]] == p) | (vp[pairs[:, 1]] == p)]]):
        if q == p:
            continue
        rows, rows_r = (
            (vp[pairs[:, 0]] == p) & (vp[pairs[:, 1]] == q),
            (vp[pairs[:, 1]] == p) & (vp[pairs[:, 0]] == q),
        )
        own = np.concatenate([pairs[rows, 0], pairs[rows_r, 1]])
        other = np.concatenate([pairs[rows, 1], pairs[rows_r, 0]])
        pos = loop_pos[own]
        if (pos < 0).any():  # not on the outline (should not happen): one seam
            yield own, other, int(q)
            continue
        order = np.argsort(pos)
        own, other, pos = own[order], other[order], pos[order]
        breaks = np.nonzero(np.diff(pos) > 1)[0] + 1
        runs = np.split(np.arange(len(own)), breaks)
        if len(runs) > 1 and pos[0] == 0 and pos[-1] == loop_len - 1:  # a run across the loop's start
            runs = [np.concatenate([runs[-1], runs[0]])] + runs[1:-1]
        for run in runs:
            yield own[run], other[run], int(q)


def _place_attached(ctx: _Context, out: np.ndarray, placed: np.ndarray, dist, offset: float) -> None:
    """Lay each attached panel on its (placed) partner through their seam map, ``offset`` outside it.

    The offset (away from the body) grows from 0 at the seam to ``offset`` one ``offset`` away from it,
    so that a panel folded over its partner starts as a layer just outside it, joined along the seam.
    Panels whose partner is an attached panel wait for it; a panel whose partner never gets placed moves
    rigidly to its stitch partners (`_place_rigid`).
    """
    from scipy.spatial import cKDTree

    uv = ctx.garment.vert_uv.detach().cpu().numpy()
    pending = dict(ctx.attached)
    while pending:
        ready = [p for p, att in pending.items() if placed[ctx.vert_panel == att.partner].all()]
        if not ready:
            break
        for p in ready:
            att = pending.pop(p)
            verts = np.nonzero(ctx.vert_panel == p)[0]
            q2d = uv[verts] @ att.rot.T + att.shift
            point, normal = _PanelSurface(ctx.garment, att.partner).to_3d(q2d, out)
            _, n_body = dist(point)
            normal = np.where(((normal * n_body).sum(1) < 0)[:, None], -normal, normal)
            d_seam = cKDTree(uv[att.seam]).query(uv[verts])[0]
            out[verts] = point + (offset * np.minimum(1.0, d_seam / offset))[:, None] * normal
            placed[verts] = True
    leftover = [p for p in pending]
    if leftover:
        _place_rigid(ctx, out, placed, leftover)


def _place_rigid(ctx: _Context, out: np.ndarray, placed: np.ndarray, panels: list[int]) -> None:
    """Move ``panels`` rigidly so their stitched vertices' centroid meets their placed partners'.

    Panels of ``panels`` stitched to one another move together, by one shift: GarmentCode already lays
    them out around the body relative to each other (the two halves of a hood either side of the head).
    Moving them one by one pulled the second half halfway onto the first, through the head (their shared
    seam spans the head: its pairs lie ~0.2 m apart).
    """
    pairs = ctx.garment.stitch_pairs.cpu().numpy()
    panels = list(panels)
    group = np.arange(len(panels))  # group label per panel: stitched panels share one
    pp = ctx.vert_panel[pairs]
    for i, p in enumerate(panels):
        for j, q in enumerate(panels[:i]):
            if (((pp[:, 0] == p) & (pp[:, 1] == q)) | ((pp[:, 0] == q) & (pp[:, 1] == p))).any():
                group[group == group[i]] = group[j]
    for g in np.unique(group):
        verts = np.nonzero(np.isin(ctx.vert_panel, [panels[i] for i in np.nonzero(group == g)[0]]))[0]
        mine = np.isin(pairs, verts)
        rows = np.nonzero(mine.any(1) & ~mine.all(1))[0]
        own = np.where(mine[rows, 0], pairs[rows, 0], pairs[rows, 1])
        partner = np.where(mine[rows, 0], pairs[rows, 1], pairs[rows, 0])
        ok = placed[partner]
        if ok.any():
            shift = out[partner[ok]].mean(0) - ctx.gc_pos[own[ok]].mean(0)
        else:
            c = ctx.gc_pos[verts].mean(0)
            shift = np.array([0.0, ctx.vmap(c[1]) - c[1], 0.0])
        out[verts] = ctx.gc_pos[verts] + shift
        placed[verts] = True


# A push that stretches a triangle past this Green strain [-] tears it. The bundled templates' pushes reach
# 5.4 at most (near the armpits: sewing relaxes those, and they are left as they are); GarmentCode's
# jumpsuit reached 12.9 (tiny triangles at its sleeve caps' corners), beyond what the solver takes (3).
_TEAR_STRAIN = 8.0
# once a push tears, it is spread until it strains no triangle past this [-] (or past its strain before)
_RELAX_STRAIN = 1.0


def _rest_inverse(garment: GarmentMesh) -> np.ndarray:
    """(F, 2, 2) inverse of each triangle's 2D rest edge matrix [1/m] (columns: edges to corner 2)."""
    t = garment.tri_vertices.cpu().numpy()
    uv = garment.vert_uv.detach().cpu().numpy().astype(np.float64)
    rest = np.stack([uv[t[:, 0]] - uv[t[:, 2]], uv[t[:, 1]] - uv[t[:, 2]]], -1)
    return np.linalg.inv(rest)


def _max_strain(pos: np.ndarray, tris: np.ndarray, rest_inv: np.ndarray) -> np.ndarray:
    """(F,) largest |Green strain| component of each triangle at ``pos`` (V, 3) against its rest shape."""
    strain = green_strain(*(torch.from_numpy(np.ascontiguousarray(a)) for a in (pos, tris, rest_inv)))
    return strain.abs().amax(1).numpy()


def _untear(
    pos: np.ndarray, disp: np.ndarray, tris: np.ndarray, rest_inv: np.ndarray, radius: float, rounds: int = 8
) -> np.ndarray:
    """``pos + disp`` with pushes that tear triangles (past `_TEAR_STRAIN`) spread over a ball.

    A vertex too close takes its full push while the field around it may be diluted; at the sleeve-cap
    corners of GarmentCode's jumpsuit, stitched vertices 6-9 mm apart took pushes of 28 and 7 mm (the
    midpoints of their pairs lie at different depths in the shoulder). Where that tears, each vertex within
    ``radius`` of a strained triangle's vertex is pushed at least that vertex's push faded by the field's
    bump, (1 - (d / radius)^2)^2 of it (never less far: the clearance holds), until no triangle is
    strained past `_RELAX_STRAIN` (or past its strain before the push). A push that tears nothing is
    applied unchanged: the bundled templates' placements do not depend on this.

    Args:
        pos, disp: (V, 3) positions and displacements [m]; tris: (F, 3); rest_inv: (F, 2, 2) from
            `_rest_inverse`; radius: [m] the push field's radius.
    """
    from scipy.spatial import cKDTree

    s0 = _max_strain(pos, tris, rest_inv)
    if not (_max_strain(pos + disp, tris, rest_inv) > np.maximum(_TEAR_STRAIN, s0)).any():
        return pos + disp
    disp = disp.copy()
    tree = cKDTree(pos)
    for _ in range(rounds):
        strained = _max_strain(pos + disp, tris, rest_inv) > np.maximum(_RELAX_STRAIN, s0)
        if not strained.any():
            break
        src = np.unique(tris[strained])
        mag = np.linalg.norm(disp, axis=1)
        near = cKDTree(pos[src]).sparse_distance_matrix(tree, radius, output_type="ndarray")
        si, vj, d = src[near["i"]], near["j"], near["v"]
        lack = (1.0 - (d / radius) ** 2) ** 2 * mag[si] - mag[vj]
        ok = lack > 0
        si, vj, lack = si[ok], vj[ok], lack[ok]
        # each vertex makes up its largest shortfall, along the shortfall-weighted mean direction of the
        # pushes it falls short of (continuous where two sources' bumps meet)
        need = np.zeros(len(pos))
        np.maximum.at(need, vj, lack)
        direction = np.zeros_like(disp)
        np.add.at(direction, vj, lack[:, None] * disp[si] / np.maximum(mag[si], 1e-20)[:, None])
        direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-20)
        disp += need[:, None] * direction
    return pos + disp


def _vertex_neighbours(garment: GarmentMesh) -> tuple[np.ndarray, np.ndarray]:
    tris = garment.tri_vertices.cpu().numpy()
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    e = np.concatenate([e, e[:, ::-1]])
    return e[:, 0], e[:, 1]


def place_garment(
    garment: GarmentMesh,
    body_verts,
    body_faces,
    *,
    body_landmarks: BodyLandmarks | None = None,
    clearance: float = 0.02,
    vertex_clearance: float = 0.01,
    stitch_clearance: float = 0.015,
    max_lift: float = 0.2,
    push_radius: float = 0.08,
    arm_joints: dict | None = None,
) -> GarmentMesh:
    """Wrap a meshed pattern around a body (see the module docstring); only ``vert_pos`` changes.

    Args:
        garment: the mesher's output, whose ``vert_pos`` is GarmentCode's flat placement [m].
        body_verts: (Vb, 3) body vertices [m], world frame (Y up, facing +Z, feet on the floor).
        body_faces: (Fb, 3) int triangles of a closed body mesh.
        body_landmarks: precomputed `body_landmarks(body_verts, body_faces)` (saves ~1 s).
        arm_joints: the arms' joints, for a body not in the A-pose (see `body_landmarks`; ignored when
            ``body_landmarks`` is given).
        clearance: [m] gap between the body and the cylinders the panels are wrapped on.
        vertex_clearance: [m] every panel vertex ends at least this far outside the body.
        stitch_clearance: [m] the midpoint of every stitched pair ends at least this far outside.
        max_lift: [m] largest upward shift tried to clear the shoulders.
        push_radius: [m] radius over which a local push out of the body fades (smooth bump).

    Returns:
        a copy of ``garment`` with new ``vert_pos`` (V, 3) (same dtype/device), everything else shared.
    """
    if not isinstance(garment, GarmentMesh):
        raise TypeError(f"garment must be a GarmentMesh, got {type(garment).__name__}")
    verts, faces = _check_body(body_verts, body_faces)
    ctx = _placement_context(garment, verts, faces, body_landmarks, arm_joints, clearance)
    fit = _Clearances(
        _BodyDistance(verts, faces), garment.stitch_pairs.cpu().numpy(), vertex_clearance, stitch_clearance
    )
    arm_shift = _arm_shifts(ctx, fit)
    pos = _lift_and_widen(ctx, fit, arm_shift, clearance, max_lift)
    pos = _push_out(garment, fit, pos, push_radius)
    new_pos = torch.as_tensor(pos, dtype=garment.vert_pos.dtype, device=garment.vert_pos.device)
    return replace(garment, vert_pos=new_pos)


# A body turned less than this from +Z is placed as it stands (the placement's frame); beyond it,
# `place_garment_turned` turns it to face +Z first (issue #29: a body facing 52° got its t-shirt 32 cm low).
TURNED_BODY_DEG = 20.0


def place_garment_turned(
    garment: GarmentMesh, body_verts, body_faces, yaw_deg: float, *, arm_joints: dict | None = None, **kw
) -> GarmentMesh:
    """`place_garment` for a body facing ``yaw_deg`` [deg] about +Y (0: facing +Z, 90: facing +X).

    `place_garment` assumes a body facing +Z. Beyond `TURNED_BODY_DEG` the body (and ``arm_joints``) is
    turned about the vertical axis through the origin to face +Z, the garment placed on it, and the placed
    garment turned back with it; nearer +Z it is `place_garment` itself.

    Args:
        body_verts: (Vb, 3) [m]; body_faces: (Fb, 3); arm_joints: as for `place_garment`, in the same frame.
        kw: passed to `place_garment`.
    """
    if abs(yaw_deg) <= TURNED_BODY_DEG:
        return place_garment(garment, body_verts, body_faces, arm_joints=arm_joints, **kw)
    turn = yaw_rotation(yaw_deg)  # +Z -> the body's facing
    verts = torch.as_tensor(body_verts)
    back = verts @ verts.new_tensor(turn)  # (Vb, 3) rows turned by turn^T: facing +Z
    arms = None if arm_joints is None else {k: np.asarray(v) @ turn for k, v in arm_joints.items()}
    placed = place_garment(garment, back, body_faces, arm_joints=arms, **kw)
    return replace(placed, vert_pos=placed.vert_pos @ placed.vert_pos.new_tensor(turn).T)


def _placement_context(garment, verts, faces, body_landmarks, arm_joints, clearance: float) -> _Context:
    """The body's sections and landmarks, the panels' kinds and sides, and the wraps' clearances."""
    if body_landmarks is not None and body_landmarks._sections is not None:
        lm, sec = body_landmarks, body_landmarks._sections
    else:
        sec = _sections(verts, faces)
        lm = (
            body_landmarks if body_landmarks is not None else _landmarks_from_sections(sec, verts, arm_joints)
        )
    gc_pos = garment.vert_pos.detach().cpu().numpy().astype(np.float64)
    vert_panel = garment.vert_panel.cpu().numpy()
    kinds = _panel_kinds(garment, gc_pos)
    attached = _attachments(garment, kinds)
    kinds = ["attached" if p in attached else k for p, k in enumerate(kinds)]
    # front/back by the side of the GarmentCode layout's mid-plane
    z_mid = 0.5 * (gc_pos[:, 2].min() + gc_pos[:, 2].max())
    front = np.array([gc_pos[vert_panel == p, 2].mean() > z_mid for p in range(len(garment.panel_names))])
    kind_names = ("torso", "leg_left", "leg_right", "arm_left", "arm_right")
    return _Context(
        garment,
        gc_pos,
        vert_panel,
        kinds,
        front,
        lm,
        sec,
        _vertical_map(lm),
        dict.fromkeys(kind_names, clearance),
        attached=attached,
    )


@dataclass
class _Clearances:
    """The placement's targets: every vertex ``vertex_clearance`` [m] and every stitched pair's midpoint
    ``stitch_clearance`` [m] outside the body (``dist``: signed distance and normal to it); ``pairs``:
    (S, 2) the garment's stitch pairs."""

    dist: _BodyDistance
    pairs: np.ndarray
    vertex_clearance: float
    stitch_clearance: float

    def deficits(self, pos: np.ndarray):
        """(vertex shortfalls (V,) [m], their body normals (V, 3), midpoint shortfalls (S,) [m], their
        normals (S, 3), the midpoints (S, 3)) at positions ``pos`` (V, 3)."""
        pairs = self.pairs
        sd_v, n_v = self.dist(pos)
        mids = 0.5 * (pos[pairs[:, 0]] + pos[pairs[:, 1]]) if len(pairs) else np.zeros((0, 3))
        sd_m, n_m = self.dist(mids)
        return self.vertex_clearance - sd_v, n_v, self.stitch_clearance - sd_m, n_m, mids


def _arm_shifts(ctx: _Context, fit: _Clearances) -> dict:
    """{arm kind: shift [m]}: sleeves slide out along the arm until they clear the shoulder (their caps
    start beyond it), by the smallest shift that clears or, failing that, the best one."""
    arm_shift = {}
    for kind in ("arm_left", "arm_right"):
        verts_k = np.nonzero(np.array([k == kind for k in ctx.kinds], dtype=bool)[ctx.vert_panel])[0]
        if len(verts_k) == 0:
            continue
        best = (-np.inf, 0.0)
        for shift in np.arange(0.0, 0.151, 0.01):
            trial = ctx.gc_pos.copy()
            _wrap_arm(ctx, kind, trial, shift)
            worst = fit.dist(trial[verts_k])[0].min()
            if worst > best[0] + 1e-4:
                best = (worst, shift)
            if worst >= fit.vertex_clearance:
                break
        arm_shift[kind] = best[1]
    return arm_shift


def _wrap_all(ctx: _Context, fit: _Clearances, arm_shift: dict, lift: float) -> np.ndarray:
    """(V, 3) every panel placed: torso and legs wrapped (tops lifted by ``lift`` [m]), sleeves wrapped,
    attached panels hung from their partners, the remaining panels moved rigidly."""
    kinds, vert_panel = ctx.kinds, ctx.vert_panel
    out = ctx.gc_pos.copy()
    placed = np.zeros(len(out), dtype=bool)
    for kind in ("torso", "leg_left", "leg_right"):
        _wrap_torso_like(ctx, kind, lift, out)
    for kind, shift in arm_shift.items():
        _wrap_arm(ctx, kind, out, shift)
    placed[:] = [k not in ("rigid", "attached") for k in np.array(kinds)[vert_panel]]
    _place_attached(ctx, out, placed, fit.dist, fit.vertex_clearance)
    _place_rigid(
        ctx,
        out,
        placed,
        [p for p, k in enumerate(kinds) if k == "rigid" and not placed[vert_panel == p].any()],
    )
    return out


def _lift_and_widen(ctx: _Context, fit: _Clearances, arm_shift: dict, clearance: float, max_lift: float):
    """Step 1 of the placement: lift tops until nothing of the torso above the armpits is too close (the
    shoulders), and widen the torso / leg wraps (``ctx.clearance``) until no vertex below is too close.
    Returns the positions (V, 3) [m]."""
    pairs = fit.pairs
    vert_kind = np.array(ctx.kinds)[ctx.vert_panel]
    pair_kind = np.where(vert_kind[pairs[:, 0]] == vert_kind[pairs[:, 1]], vert_kind[pairs[:, 0]], "")
    upper_body = ctx.lm.armpit_y
    lift, pos = 0.0, _wrap_all(ctx, fit, arm_shift, 0.0)
    for _ in range(12):
        dv, _, dm, _, mids = fit.deficits(pos)
        changed = False
        high_v, high_m = pos[:, 1] > upper_body, mids[:, 1] > upper_body
        high = max(
            dv[(vert_kind == "torso") & high_v].max(initial=0.0),
            dm[(pair_kind == "torso") & high_m].max(initial=0.0),
        )
        if high > 0 and lift < max_lift:
            lift = min(lift + max(high, 0.01), max_lift)
            changed = True
        for kind in ("torso", "leg_left", "leg_right"):
            # only vertices: widening a wrap opens its seams further (their midpoints go deeper)
            low_v = ~high_v if kind == "torso" else True
            need = dv[(vert_kind == kind) & low_v].max(initial=0.0)
            if need > 0 and ctx.clearance[kind] < clearance + 0.1:
                ctx.clearance[kind] += max(need, 0.005)
                changed = True
        if not changed:
            break
        pos = _wrap_all(ctx, fit, arm_shift, lift)
    return pos


def _push_out(garment: GarmentMesh, fit: _Clearances, pos: np.ndarray, push_radius: float) -> np.ndarray:
    """Step 2 of the placement: local pushes along the body normal, spread smoothly over a ball of
    ``push_radius`` [m] (no spikes), until every vertex and stitch midpoint clears (a warning after 40
    rounds). Returns the positions (V, 3) [m]."""
    from scipy.spatial import cKDTree

    pairs = fit.pairs
    tris = garment.tri_vertices.cpu().numpy()
    rest_inv = _rest_inverse(garment)
    for attempt in range(41):
        dv, nv, dm, nm, _ = fit.deficits(pos)
        if dv.max(initial=0) <= 0 and dm.max(initial=0) <= 0:
            break
        if attempt == 40:
            warnings.warn(
                f"place_garment: {int((dv > 0).sum())} vertices and {int((dm > 0).sum())} stitch midpoints "
                "are still closer to the body than asked (largest shortfall "
                f"{100 * max(dv.max(initial=0), dm.max(initial=0)):.1f} cm)",
                stacklevel=3,
            )
            break
        bad_v = np.nonzero(dv > 0)[0]
        bad_m = np.nonzero(dm > 0)[0]
        # a seam midpoint too close moves both of its vertices along the body normal at the midpoint
        push_m = (dm[bad_m] + 0.003)[:, None] * nm[bad_m]
        centres = np.concatenate([pos[bad_v], pos[pairs[bad_m, 0]], pos[pairs[bad_m, 1]]])
        push = np.concatenate([(dv[bad_v] + 0.003)[:, None] * nv[bad_v], push_m, push_m])
        pairs_near = cKDTree(centres).sparse_distance_matrix(cKDTree(pos), push_radius, output_type="ndarray")
        ci, vj, d = pairs_near["i"], pairs_near["j"], pairs_near["v"]
        w = (1.0 - (d / push_radius) ** 2) ** 2
        # weighted mean of the pushes reaching each vertex: a smooth displacement field
        disp = np.zeros_like(pos)
        np.add.at(disp, vj, w[:, None] * push[ci])
        total = np.bincount(vj, weights=w, minlength=len(pos))
        disp /= np.maximum(total, 1.0)[:, None]
        # a vertex that is itself too close takes its own full push (the mean could dilute it)
        own = np.concatenate([bad_v, pairs[bad_m, 0], pairs[bad_m, 1]])
        disp[own] = push
        pos = _untear(pos, disp, tris, rest_inv, push_radius)
    return pos


def a_pose_route(garment: GarmentMesh, body, yaw_deg: float = 0.0, **place_kwargs) -> PoseRoute | None:
    """The `PoseRoute` of ``garment`` onto a posed body: placed on the body's A-pose, which the
    templates are made for, to be sewn there and carried along the body's path to its pose.

    `sew_and_drape` takes it as its ``fallback``: arms held low or against the torso leave the placement
    no room to wrap a sleeve or the torso's sides on the posed body itself (a long sleeve with the upper
    arms turned 0.3 rad down from the A-pose), while the A-pose has it.

    Args:
        garment: the mesher's output (as for `place_garment`).
        body: a `torch_diffavatar.body.model.BodyModel` (its first body of the batch).
        yaw_deg: the body's facing [deg] (`place_garment_turned`).
        place_kwargs: passed to `place_garment`.

    Returns:
        the `PoseRoute`, or None when the body is in the A-pose (`BodyModel.pose_path`).
    """
    path = body.pose_path()
    if path is None:
        return None
    a_pose = path.vertices[0].detach()
    arms = body.arm_joints(path.joints[0])
    placed = place_garment_turned(
        garment, a_pose.double(), body.faces, yaw_deg, arm_joints=arms, **place_kwargs
    )
    return PoseRoute(vert_pos=placed.vert_pos, body_path=path.vertices.detach())


def place_from_drape(garment: GarmentMesh, source: GarmentMesh, source_x) -> GarmentMesh:
    """Place ``garment`` where ``source``, another meshing of the same pattern, lies draped.

    Each panel vertex of ``garment`` is located in the same-named panel of ``source`` by its 2D rest
    coordinate and takes the barycentric blend of the draped positions of that source triangle (points
    just outside a curved outline take the nearest triangle's affine extension). A garment meshed at
    another spacing then starts in the source's fold state, already sewn, instead of being wrapped and
    sewn anew: a drape is path dependent, and sewing again can end in another equilibrium.

    Args:
        garment: the mesh to place (its ``vert_uv`` in the same panel frames as ``source``'s).
        source: a meshed pattern whose panel names include all of ``garment``'s.
        source_x: (Vs, 3) draped sim-vertex positions of ``source`` [m].

    Returns:
        a copy of ``garment`` with new ``vert_pos`` (V, 3) (dtype/device of ``garment.vert_pos``); the
        panel vertices of a seam get (nearly) equal positions, so `sew` closes it at once.

    Raises:
        ValueError: a panel of ``garment`` is missing from ``source``, or ``source_x`` has the wrong shape.
    """
    missing = sorted(set(garment.panel_names) - set(source.panel_names))
    if missing:
        raise ValueError(f"place_from_drape: panels {missing} are not in the source garment")
    x = torch.as_tensor(source_x).detach().cpu().double().numpy()
    if x.shape != (source.sim_vert_count, 3):
        raise ValueError(f"source_x must be ({source.sim_vert_count}, 3), got {tuple(x.shape)}")
    panel_pos = x[source.vert_to_sim.cpu().numpy()]
    uv = garment.vert_uv.detach().cpu().numpy().astype(np.float64)
    vert_panel = garment.vert_panel.cpu().numpy()
    out = np.zeros((garment.vert_count, 3))
    for p, name in enumerate(garment.panel_names):
        mine = np.nonzero(vert_panel == p)[0]
        out[mine] = _PanelSurface(source, source.panel_names.index(name)).to_3d(uv[mine], panel_pos)[0]
    new_pos = torch.as_tensor(out, dtype=garment.vert_pos.dtype, device=garment.vert_pos.device)
    return replace(garment, vert_pos=new_pos)
