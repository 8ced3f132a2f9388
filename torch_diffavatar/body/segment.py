"""Garment segmentation of an unlabelled scan using the fitted body, and the garment's open boundaries.

Per scan point we use (1) the body part of its nearest body vertex (parts from skinning weights), which
limits where a garment of the requested type may be; (2) its signed distance to the body surface (exact
closest point, positive outside), averaged over its scan neighbours (cloth lies outside the skin); (3) its
colour, when present: colour models of the garment and of the rest learned from confident points, combined
with the offset and smoothed by a graph cut over the scan's neighbour graph (`body.colour`); where the
colours do not tell the garment apart, a two-class colour model re-estimated from the current labels,
smoothed by a neighbour majority vote. Where the garment hangs from the body (a bodice on the shoulders, a
waistband on the hips and the torso below the waist: `GARMENT_SUPPORT`, `WAIST_SUPPORT`) the cloth lies
within the offset threshold, often within a millimetre of a fitted body that swelled into it: there the
labels grow over the scan's k-NN graph into the connected points whose offset is still positive (beyond
``grow_sigmas`` noise standard deviations, and 0.5 mm), which the skin beside them (neck, arms) is not.
Last, "skin" that no opening shows (patches enclosed by the garment on the body) joins the garment. Measured
without colour on simulated scans (`synthetic_scans.make_draped_scan`, 3 cm drape spacing; 2.5 cm for the
T-shirt), recall without → with the growth, precision ≥ 0.99 both: dress seeds 0–4 0.91–0.94 → 0.97–0.99,
T-shirt seeds 0–1 0.81 / 0.88 → 0.95 / 0.96, skirt 0.90 → 0.93, trousers 0.95 → 0.95; trousers with the
torso below the waist (2 cm scans, docs/BENCHMARKS.md "Unlabelled trousers and skirts"): 0.77–1.00 →
0.94–1.00.

Boundaries (hem, cuffs, neck, waist) are found on the body, not in the noisy scan: every body vertex takes
the label of its nearest scan point (so holes in the scan inherit their rim's label), the covered faces'
boundary edges are chained into loops, each boundary vertex is named by the extremity (head, hand, foot)
nearest to it over uncovered skin (neck, cuff or armhole, hem, trouser leg, waist), and the
garment points near it are returned in loop order.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from torch_diffavatar.body.colour import colour_labels
from torch_diffavatar.body.parts import PART_NAMES
from torch_diffavatar.errors import InputError

# Body parts a garment of each type may cover (a dilated region: where the garment ends inside it is
# decided by offset and colour). A long sleeve's cuff lies over the wrist, whose nearest body vertices
# belong to the hand: without the hands its last centimetres were skin and the cuffs' targets moved up
# the sleeve (docs/BENCHMARKS.md, "Scans without labels: long sleeves' cuffs, and necklines").
_ARMS = ("upperarm.L", "upperarm.R", "forearm.L", "forearm.R", "hand.L", "hand.R")
_LEGS = ("thigh.L", "thigh.R", "shin.L", "shin.R", "foot.L", "foot.R")
GARMENT_REGIONS: dict[str, tuple[str, ...]] = {
    "dress": ("torso", "hips", "thigh.L", "thigh.R", "shin.L", "shin.R", "upperarm.L", "upperarm.R"),
    "shirt": (
        "torso",
        "hips",
        "upperarm.L",
        "upperarm.R",
        "forearm.L",
        "forearm.R",
        "hand.L",
        "hand.R",
        "thigh.L",
        "thigh.R",
    ),
    "tshirt": ("torso", "hips", "upperarm.L", "upperarm.R", "forearm.L", "forearm.R", "thigh.L", "thigh.R"),
    "polo": ("torso", "hips", "upperarm.L", "upperarm.R", "forearm.L", "forearm.R", "thigh.L", "thigh.R"),
    "skirt": ("torso", "hips", "thigh.L", "thigh.R", "shin.L", "shin.R"),
    "pants": ("torso", "hips", "thigh.L", "thigh.R", "shin.L", "shin.R", "foot.L", "foot.R"),
    # a jumpsuit: a top and trousers in one (GarmentCode's js_mean_all), with or without sleeves
    "jumpsuit": ("torso", "hips", *_ARMS, *_LEGS),
    "jumpsuit_sleeveless": ("torso", "hips", "upperarm.L", "upperarm.R", *_LEGS),
}
# Body parts each garment type hangs from or grips (tops: the shoulders and upper arms, long sleeves
# their forearms too; a dress also its hips, never bare under it; skirts and trousers: the hips; a
# jumpsuit from its shoulders, as a top, for its waist is sewn, not gripping the hips). There
# the cloth lies on the skin, within the offset threshold, and the garment labels grow across them (see
# `_grow_on_support`).
GARMENT_SUPPORT: dict[str, tuple[str, ...]] = {
    "dress": ("torso", "hips"),
    "shirt": ("torso", "upperarm.L", "upperarm.R", "forearm.L", "forearm.R"),
    "tshirt": ("torso", "upperarm.L", "upperarm.R"),
    "polo": ("torso", "upperarm.L", "upperarm.R"),
    "skirt": ("hips",),
    "pants": ("hips",),
    "jumpsuit": ("torso", "upperarm.L", "upperarm.R"),
    "jumpsuit_sleeveless": ("torso",),
}
# Trousers grip the hips, but on Anny's parts their waistband lies on the torso, 15-17 cm above where the
# hips part ends: given `segment_garment`'s ``support_top`` (the body's waist height) the labels also grow
# over the torso below it. Only below it: uncapped, on a heavy body fitted thinner than its scan, bare skin
# stood off the body like tight cloth and the labels climbed the torso. Skirts found more of their cloth
# this way too, but their fits ended farther from the scans (docs/BENCHMARKS.md, "Unlabelled trousers
# and skirts").
WAIST_SUPPORT: dict[str, tuple[str, ...]] = {"pants": ("torso",)}
# Where each garment type's colour is learned (`colour.colour_labels`' seeds): the points standing off
# the body over these parts, which no other garment of an outfit covers (a top's torso above the waist,
# not its hem over the trousers; trousers' and skirts' thighs, not a waistband under a top). The torso
# counts above the body's waist only, when `segment_garment` is given it (``support_top``).
GARMENT_CORE: dict[str, tuple[str, ...]] = {
    "dress": ("torso",),
    "shirt": ("torso",),
    "tshirt": ("torso",),
    "polo": ("torso",),
    "skirt": ("thigh.L", "thigh.R"),
    "pants": ("thigh.L", "thigh.R"),
    "jumpsuit": ("torso",),
    "jumpsuit_sleeveless": ("torso",),
}
GARMENT_ALIASES = {"t-shirt": "tshirt", "tee": "tshirt", "trousers": "pants", "shirt-long": "shirt"}
GARMENT_TYPES = tuple(GARMENT_REGIONS)
_SLEEVED = ("shirt", "tshirt", "polo", "jumpsuit")
_ARM_PARTS = ("upperarm", "forearm", "hand")


def garment_type(name: str) -> str:
    """Canonical garment type for ``name`` (case-insensitive, aliases accepted); InputError if unknown."""
    key = GARMENT_ALIASES.get(name.lower(), name.lower())
    if key not in GARMENT_REGIONS:
        raise InputError(f"unknown garment type {name!r}; use one of {', '.join(GARMENT_TYPES)}")
    return key


@dataclass
class ScanOpening:
    """An open boundary of the garment in a scan, named as the garment mesh names its openings
    (`pattern.garment_mesh.BoundaryLoop`), so that the two match by name.

    Attributes:
        name: "neck", "waist", "hem" (a top's or a skirt's), "cuff_left"/"cuff_right" (sleeve ends, and a
            sleeveless top's armholes), "hem_left"/"hem_right" (trouser legs); left is the body's left (+x).
        point_indices: (M,) int64 indices into the garment points, ordered around the loop.
        body_vertices: (K,) int64 body vertices along the loop, in order (one cycle of boundary edges).
    """

    name: str
    point_indices: np.ndarray
    body_vertices: np.ndarray


@dataclass
class Segmentation:
    """Result of `segment_garment`.

    Attributes:
        labels: (N,) bool, True for the garment's scan points.
        garment_indices: (G,) int64 indices of the garment points in the scan.
        loops: the garment's open boundaries (indices into the garment points).
        offsets: (N,) smoothed signed offset of each scan point from the body [m].
        colour_separability: how well the colour models told the garment apart (`colour.ColourLabels`)
            when they labelled it; None when they did not (no colours, or colours that do not separate).
    """

    labels: np.ndarray
    garment_indices: np.ndarray
    loops: list[ScanOpening]
    offsets: np.ndarray
    colour_separability: float | None = None


def _surface_offsets(
    points: np.ndarray, verts: np.ndarray, faces: np.ndarray, max_dist: float = 0.3
) -> np.ndarray:
    """(N,) signed distance [m] from each point (N, 3) to the closest point of the body surface
    (verts (Vb, 3), faces (Fb, 3)), positive outside (along that triangle's outward normal); points
    farther than ``max_dist`` [m] get ``max_dist``. Exact point-to-triangle: the nearest vertex's
    offset is noisier and biased on coarse triangles (measured: recall 0.94 vs 0.96 on a fitted body)."""
    import torch

    from torch_diffavatar.geometry import closest_point_on_mesh

    p, v, f = torch.from_numpy(points), torch.from_numpy(verts), torch.from_numpy(faces)
    tri, bary, _ = closest_point_on_mesh(p, v, f, max_dist)
    found = tri >= 0
    tri = tri.clamp_min(0)
    q = (bary[:, :, None] * v[f[tri]]).sum(1)
    a, b, c = v[f[tri]].unbind(1)
    n = torch.linalg.cross(b - a, c - a)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    return torch.where(found, ((p - q) * n).sum(-1), max_dist).numpy()


def _colour_evidence(colors: np.ndarray, labels: np.ndarray, region: np.ndarray) -> np.ndarray | None:
    """Log-likelihood ratio (garment vs not) of each colour under two isotropic Gaussians fit to labels."""
    c = colors.astype(np.float64)
    pos, neg = labels & region, ~labels
    if pos.sum() < 20 or neg.sum() < 20:
        return None
    mu_p, mu_n = c[pos].mean(0), c[neg].mean(0)
    var = max(0.5 * (c[pos].var(0).sum() + c[neg].var(0).sum()) / 3.0, 25.0)
    gap = ((mu_p - mu_n) ** 2).sum() / var
    if gap < 4.0:  # the two classes do not differ in colour: no colour evidence
        return None
    llr = (((c - mu_n) ** 2).sum(1) - ((c - mu_p) ** 2).sum(1)) / (2.0 * var)
    return np.clip(llr, -6.0, 6.0)


def _smooth(values: np.ndarray, nbr: np.ndarray) -> np.ndarray:
    return values[nbr].mean(1)


def segment_garment(
    points: np.ndarray,
    garment: str,
    body_vertices: np.ndarray,
    body_faces: np.ndarray,
    vertex_parts: np.ndarray,
    *,
    colors: np.ndarray | None = None,
    offset_threshold: float = 0.005,
    offset_scale: float = 0.003,
    neighbors: int = 16,
    grow_sigmas: float = 0.67,
    support_top: float | None = None,
    use_colour: bool = True,
) -> Segmentation:
    """Label the scan points of one garment using a fitted body.

    Args:
        points: (N, 3) scan points [m], world frame, in the same frame as the body.
        garment: a garment type (`GARMENT_TYPES`, aliases such as "t-shirt" accepted).
        body_vertices: (Vb, 3) fitted body [m]; body_faces: (Fb, 3) int, outward-facing, closed.
        vertex_parts: (Vb,) int index into `PART_NAMES` of each body vertex (`BodyModel.vertex_parts`).
        colors: optional (N, 3) uint8 RGB.
        offset_threshold: smoothed outward offset [m] above which a point is more likely cloth than skin.
        offset_scale: softness [m] of that threshold (offset evidence = (offset − threshold) / scale).
        neighbors: scan neighbours used for smoothing.
        grow_sigmas: the garment grows over the support parts of its type (`GARMENT_SUPPORT`) into
            points whose smoothed offset exceeds this many of its noise standard deviations (0: off).
        support_top: height [m] (world Y) of the body's waist, for trousers: their labels also grow
            over the torso (`WAIST_SUPPORT`) on points below it. `fit_setup.prepare` and
            ``diffavatar segment`` pass `BodyModel.waist_height`; None: only `GARMENT_SUPPORT`. Also
            where the torso's colour seeds end (`GARMENT_CORE`).
        use_colour: with ``colors``, label by geometry and colour (`colour.colour_labels`: colour models
            learned from the garment's core and the rest, a graph cut), or, when those colours do not
            tell the garment apart, by geometry and a two-Gaussian colour evidence; False: geometry only.

    Returns:
        a `Segmentation`.
    """
    kind = garment_type(garment)
    points = np.asarray(points, dtype=np.float64)
    body_vertices = np.asarray(body_vertices, dtype=np.float64)
    body_faces = np.asarray(body_faces, dtype=np.int64)
    vertex_parts = np.asarray(vertex_parts, dtype=np.int64)
    _, near = cKDTree(body_vertices).query(points)  # (N,) nearest body vertex
    offset = _surface_offsets(points, body_vertices, body_faces)  # (N,) signed [m]
    region = np.isin(vertex_parts[near], [PART_NAMES.index(p) for p in GARMENT_REGIONS[kind]])
    k = min(neighbors, len(points))
    _, nbr = cKDTree(points).query(points, k=k)
    nbr = nbr.reshape(len(points), -1)
    offset_s = _smooth(offset, nbr)
    evidence = (offset_s - offset_threshold) / offset_scale
    seeds = (evidence > 1.0) & _core_points(kind, vertex_parts[near], points, support_top)
    labels, colour_s, separability = _first_labels(
        evidence, region, seeds, nbr, colors if use_colour else None
    )
    if labels.any() and grow_sigmas > 0:
        open_points = _support_points(kind, vertex_parts[near], points, support_top)
        open_points &= offset_s > _growth_threshold(offset, offset_s, labels, k, grow_sigmas)
        if colour_s is not None:  # and never against the colour
            open_points &= colour_s >= 0
        labels = _grow_on_support(labels, open_points, nbr)
    if labels.any():
        # Skin seen through no opening is cloth lying close to the body (a fitted bodice within the
        # offset threshold): the patches of "skin" enclosed by the garment join it.
        covered = _covered_body(points, labels, body_vertices, body_faces, vertex_parts)
        enclosed = region & covered[near]
        if separability is not None:  # not where the colour is another's (a patch of trousers, of skin)
            enclosed &= colour_s >= 0
        labels = labels | enclosed
    loops = _boundary_loops(points, labels, near, body_vertices, body_faces, vertex_parts, kind)
    return Segmentation(
        labels=labels,
        garment_indices=np.flatnonzero(labels),
        loops=loops,
        offsets=offset_s,
        colour_separability=separability,
    )


def _first_labels(
    evidence: np.ndarray, region: np.ndarray, seeds: np.ndarray, nbr: np.ndarray, colors: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray | None, float | None]:
    """First garment labels (N,) bool: by the offset ``evidence`` (N,) and the ``colors`` (N, 3) through
    `colour.colour_labels` (colour models from the ``seeds`` (N,) bool, a graph cut over the neighbours
    ``nbr`` (N, k)), else, when those colours do not tell the garment apart, `_evidence_labels`.

    Returns:
        the labels, the (N,) smoothed colour evidence (None without any), and the colour models'
        separability (None when they did not label).
    """
    if colors is not None:
        colour = colour_labels(np.asarray(colors), evidence, region, seeds, nbr)
        if colour is not None:
            colour_s = _smooth(np.clip(colour.log_ratio, -6.0, 6.0), nbr[:, : max(nbr.shape[1] // 2, 1)])
            return colour.labels, colour_s, colour.separability
    # geometry, and the two-Gaussian colour evidence when the colours differ at all
    return (*_evidence_labels(evidence, region, nbr, colors), None)


def _evidence_labels(
    evidence: np.ndarray, region: np.ndarray, nbr: np.ndarray, colors: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray | None]:
    """First garment labels (N,) bool: the offset ``evidence`` (N,) within the garment's ``region`` (N,)
    bool, with the colour's evidence when ``colors`` (N, 3) tell garment from skin, then smoothed by a
    majority vote over the scan neighbours ``nbr`` (N, k).

    Returns:
        the labels and the (N,) smoothed colour evidence (None without colour evidence).
    """
    labels = region & (evidence > 0)
    colour_s = None  # smoothed colour evidence, when the colours tell garment from skin
    if colors is not None:
        for _ in range(2):  # re-estimate the colour model from the current labels
            colour = _colour_evidence(np.asarray(colors), labels, region)
            if colour is None:
                break
            colour_s = _smooth(colour, nbr[:, : max(nbr.shape[1] // 2, 1)])
            total = np.clip(evidence, -6.0, 6.0) + 2.0 * colour_s
            labels = region & (total > 0)
    for _ in range(2):  # neighbour majority vote
        labels = region & (_smooth(labels.astype(np.float64), nbr) > 0.5)
    return labels, colour_s


def _core_points(
    kind: str, near_parts: np.ndarray, points: np.ndarray, support_top: float | None
) -> np.ndarray:
    """(N,) bool: the scan points (N, 3) [m] over garment type ``kind``'s `GARMENT_CORE` parts
    (``near_parts`` (N,): each point's nearest body vertex's part), the torso only above ``support_top``."""
    core = np.isin(near_parts, [PART_NAMES.index(p) for p in GARMENT_CORE[kind]])
    if support_top is not None:
        core &= (near_parts != PART_NAMES.index("torso")) | (points[:, 1] > support_top)
    return core


def _support_points(
    kind: str, near_parts: np.ndarray, points: np.ndarray, support_top: float | None
) -> np.ndarray:
    """(N,) bool: the scan points (N, 3) [m] over the parts garment type ``kind`` hangs from
    (`GARMENT_SUPPORT`; ``near_parts`` (N,): the part of each point's nearest body vertex), and over
    `WAIST_SUPPORT` below ``support_top`` [m] when it is given."""
    support = np.isin(near_parts, [PART_NAMES.index(p) for p in GARMENT_SUPPORT[kind]])
    if support_top is not None and kind in WAIST_SUPPORT:
        waist = np.isin(near_parts, [PART_NAMES.index(p) for p in WAIST_SUPPORT[kind]])
        support |= waist & (points[:, 1] < support_top)
    return support


def _growth_threshold(
    offset: np.ndarray, offset_s: np.ndarray, labels: np.ndarray, k: int, grow_sigmas: float
) -> float:
    """Smoothed offset [m] above which a support point is open to the garment's growth: ``grow_sigmas``
    noise standard deviations of the smoothed offset ``offset_s`` (N,) (``k`` neighbours), at least 0.5 mm.
    """
    # Noise of the smoothed offset: robust spread of the raw offsets about their local mean,
    # over the skin, divided by sqrt(k).
    skin = ~labels & (np.abs(offset) < 0.05)
    resid = (offset - offset_s)[skin] if skin.sum() >= 20 else offset - offset_s
    sigma = 1.4826 * float(np.median(np.abs(resid - np.median(resid)))) / np.sqrt(k)
    # At least 0.5 mm: on a noise-free scan the fitted body's own error sets the floor.
    return max(grow_sigmas * sigma, 0.0005)


def _grow_on_support(labels: np.ndarray, open_points: np.ndarray, nbr: np.ndarray, k: int = 8) -> np.ndarray:
    """Garment labels (N,) bool grown over the scan's ``k``-nearest-neighbour graph (``nbr`` (N, >k),
    column 0 the point itself) into the connected ``open_points`` (N,) bool they touch.

    Where a garment hangs from the body (a bodice on the shoulders) the cloth lies within the offset
    threshold of the skin, so those points come out "skin"; yet they continue the confident garment
    without a rim, still lying a little outside the body, while the skin beside them (the neck, the
    arms) lies on it. The open points are that: a slightly positive offset on a support part.

    Returns:
        (N,) bool: ``labels`` plus the open points connected to them through open points.
    """
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    n = len(labels)
    cand = labels | open_points
    i = np.repeat(np.arange(n), min(k, nbr.shape[1] - 1))
    j = nbr[:, 1 : k + 1].reshape(-1)
    keep = cand[i] & cand[j]
    graph = sp.coo_matrix((np.ones(int(keep.sum())), (i[keep], j[keep])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    seeded = np.zeros(comp.max() + 1, dtype=bool)
    seeded[comp[labels]] = True
    return cand & seeded[comp]


def _linked_pieces(points: np.ndarray, link: float) -> np.ndarray:
    """(N,) piece id of each point (N, 3): pieces are joined by steps shorter than ``link`` [m]."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    n = len(points)
    pairs = cKDTree(points).query_pairs(link, output_type="ndarray")
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def _main_piece(points: np.ndarray, link: float, share: float = 0.1) -> np.ndarray:
    """(N,) bool: the points (N, 3) of the pieces, joined by steps shorter than ``link`` [m], that hold
    at least ``share`` of the largest piece's points."""
    comp = _linked_pieces(points, link)
    size = np.bincount(comp)
    return size[comp] >= share * size.max()


def _edge_cycles(edges: np.ndarray) -> list[list[int]]:
    """Chain undirected boundary edges (E, 2) into vertex cycles (open chains are returned as well)."""
    adj = defaultdict(list)
    for a, b in edges:
        adj[int(a)].append(int(b))
        adj[int(b)].append(int(a))
    seen_edges: set[tuple[int, int]] = set()
    cycles = []
    for start in list(adj):
        for nxt in adj[start]:
            if (min(start, nxt), max(start, nxt)) in seen_edges:
                continue
            cycle, prev, cur = [start], start, nxt
            seen_edges.add((min(start, nxt), max(start, nxt)))
            while cur != start:
                cycle.append(cur)
                options = [v for v in adj[cur] if (min(cur, v), max(cur, v)) not in seen_edges]
                if not options:
                    break
                prev, cur = cur, options[0]
                seen_edges.add((min(prev, cur), max(prev, cur)))
            cycles.append(cycle)
    return cycles


# The body's extremities: every real opening of a garment leads to one of them over uncovered skin
# (a neckline to the head, a sleeve to a hand, a hem or trouser leg to the feet); uncovered patches that
# lead to none are holes in the labels, not openings.
_EXTREMITIES = ("head", "hand.L", "hand.R", "foot.L", "foot.R")


def _limb_extremity(part: str) -> str:
    """The extremity at the end of a non-trunk body part's limb ("upperarm.L" -> "hand.L")."""
    if part == "head":
        return "head"
    return ("hand" if part.startswith(("upperarm", "forearm", "hand")) else "foot") + part[-2:]


# Opening-name suffix of each body side (`PART_NAMES`' ".L" is the body's left, +x), as the garment mesh
# names its openings (`pattern.mesher.name_boundary_loops`: "cuff_left", "hem_right" …).
_SIDE_NAMES = {".L": "_left", ".R": "_right"}


def _opening_name(extremity: str, kind: str) -> str:
    """Name of the opening through which uncovered skin leads to ``extremity`` (see `ScanOpening`)."""
    side = _SIDE_NAMES.get(extremity[-2:], "")
    if kind in ("pants", "skirt"):
        if extremity == "head" or extremity.startswith("hand"):
            return "waist"
        return ("hem" + side) if kind == "pants" else "hem"
    if extremity == "head":
        return "neck"
    if extremity.startswith("hand"):  # a sleeve's end, or a sleeveless top's armhole
        return "cuff" + side
    return ("hem" + side) if kind.startswith("jumpsuit") else "hem"


def _part_side(opening: str) -> str:
    """The `PART_NAMES` suffix (".L", ".R") of the body side an opening's name ends with; "" for none."""
    for side, suffix in _SIDE_NAMES.items():
        if opening.endswith(suffix):
            return side
    return ""


def _covered_body(
    points: np.ndarray, labels: np.ndarray, body_vertices: np.ndarray, body_faces: np.ndarray, vertex_parts
) -> np.ndarray:
    """(Vb,) bool: body vertices under the garment. Each takes the label of its nearest scan point (so
    scan holes inherit their rim's label), then `_clean_cover` fills enclosed patches and drops islands."""
    _, nearest_point = cKDTree(points).query(body_vertices)
    tri = body_vertices[body_faces]
    face_area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    area = np.zeros(len(body_vertices))
    for k in range(3):
        np.add.at(area, body_faces[:, k], face_area / 3.0)
    return _clean_cover(labels[nearest_point], body_faces, vertex_parts, area)


def _components(mask: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(Vb,) connected-component id of every vertex in ``mask`` over the mesh ``edges`` (E, 2); −1
    outside the mask."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    n = len(mask)
    keep = mask[edges[:, 0]] & mask[edges[:, 1]]
    graph = sp.coo_matrix((np.ones(int(keep.sum())), (edges[keep, 0], edges[keep, 1])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    return np.where(mask, comp, -1)


def _clean_cover(
    covered: np.ndarray, body_faces: np.ndarray, vertex_parts: np.ndarray, area: np.ndarray
) -> np.ndarray:
    """Covered body vertices (Vb,) bool without label holes and islands.

    An uncovered patch that reaches no extremity is a hole in the labels (a scan hole, noise) and is
    filled; a covered patch of less than a fifth of the largest one's area is dropped.
    """
    edges = np.concatenate([body_faces[:, [0, 1]], body_faces[:, [1, 2]], body_faces[:, [2, 0]]])
    out = covered.copy()
    if (~out).any():  # fill the uncovered patches that lead to no extremity
        comp = _components(~out, edges)
        extremity = np.isin(vertex_parts, [PART_NAMES.index(p) for p in _EXTREMITIES])
        reaches = np.zeros(comp.max() + 1, dtype=bool)
        reaches[comp[~out & extremity]] = True
        out[(comp >= 0) & ~reaches[np.maximum(comp, 0)]] = True
    if out.any():  # drop the small covered islands
        comp = _components(out, edges)
        comp_area = np.bincount(comp[out], weights=area[out], minlength=comp.max() + 1)
        small = comp_area < 0.2 * comp_area.max()
        out[(comp >= 0) & small[np.maximum(comp, 0)]] = False
    return out


def _lower_rim(
    garment_points: np.ndarray,
    sel: np.ndarray,
    side: str = "",
    sectors: int = 36,
    band: float = 0.015,
    max_rise: float = 0.01,
    max_slope: float = 0.8,
    link: float | None = None,
    lateral: np.ndarray | None = None,
    exclude: np.ndarray | None = None,
    others: np.ndarray | None = None,
) -> np.ndarray:
    """The garment points (indices into ``garment_points`` (G, 3)) on the lower rim of a bottom opening.

    A loose hem hangs away from the body, so the points found near the body's loop (``sel``) cover the
    whole lower part of the skirt. The rim is the garment's lower envelope instead: around the vertical
    axis through the candidates (`_bottom_candidates`: the garment points no higher than ``sel``, not
    ``exclude``d, on the ``side`` of a trouser leg, joined to ``sel`` within ``link``), in each of
    ``sectors`` angular sectors, the
    points within ``band`` [m] of the sector's lowest point. Holes in the scan are skipped: where the
    lowest point rises by more than ``max_rise`` [m] plus ``max_slope`` times a sector's length along the
    rim from one sector to the next, the sectors from there on are a hole while they stay that high
    (`_cliff_holes`). A hem rises gradually where a belly lifts it (up to 10 cm in all, 2.7 cm from one
    10° sector to the next on a polo: 0.9 of the length along the rim), a hole's edge at once (4.2-5.3 cm
    on a long sleeve, 1.5-1.8 of it; 5 cm and more on the suite's skirts, whose holes are plateaus up to
    five sectors wide). A rule that skipped every sector more than 5 cm above the median sector's took the
    raised front of T-shirts' hems for holes and traced their hems up to 14 cm short (docs/BENCHMARKS.md,
    "Raised hems, noisy cuffs and a cut-off forearm").
    With ``others`` ((N, 3) the scan points that are not garment), the hem's edge where it climbs out of
    a sector's band is added (`_lifted_rim`).
    """
    g = garment_points
    idx = _bottom_candidates(g, sel, side, link, lateral, exclude)
    if len(idx) < sectors:
        return sel
    p = g[idx]
    axis = p[:, [0, 2]].mean(0)
    angle = np.arctan2(p[:, 2] - axis[1], p[:, 0] - axis[0])
    radius = np.hypot(p[:, 0] - axis[0], p[:, 2] - axis[1])
    arc = 2 * np.pi * float(np.median(radius)) / sectors
    # the lowest: farthest down
    keep = _sector_envelope(-p[:, 1], angle, sectors, band, max_rise + max_slope * arc, cliffs=True)
    if not keep.any():
        return sel
    if others is None:
        return idx[keep]
    beside = _beside_rim(radius, _sector_index(angle, sectors), keep, sectors)
    return _lifted_rim(g, idx[keep], idx[beside], others, link=0.03 if link is None else link)


def _beside_rim(radius: np.ndarray, sector: np.ndarray, keep: np.ndarray, sectors: int, out: float = 0.03):
    """(C,) bool: the candidates (their ``radius`` (C,) [m] about the axis and ``sector`` (C,)) where a
    lifted hem may lie: in a sector that holds the envelope's rim (``keep`` (C,) bool), or in one the
    envelope skipped as a hole but more than ``out`` [m] farther out than the rim (its median radius) of
    the nearest holding sector on either side, the farther of the two (a flap lifted away from the body
    rises like a hole's edge; a hole's edge lies on the garment's surface, as far out as the rim beside
    it)."""
    held = np.zeros(sectors, dtype=bool)
    held[sector[keep]] = True
    rim_radius = np.full(sectors, np.nan)
    for k in np.flatnonzero(held):
        rim_radius[k] = np.median(radius[keep & (sector == k)])
    reach = np.full(sectors, np.inf)
    steps = np.arange(1, sectors)
    for k in np.flatnonzero(~held):
        ahead, behind = held[(k + steps) % sectors], held[(k - steps) % sectors]
        if ahead.any() and behind.any():
            a, b = (k + steps[ahead.argmax()]) % sectors, (k - steps[behind.argmax()]) % sectors
            reach[k] = max(rim_radius[a], rim_radius[b]) + out
    return held[sector] | (radius > reach[sector])


def _bottom_candidates(
    g: np.ndarray, sel: np.ndarray, side: str, link: float | None, lateral, exclude
) -> np.ndarray:
    """(C,) indices into the garment points ``g`` (G, 3) that may hold a bottom opening's rim: those no
    higher than the band ``sel``, not ``exclude``d ((G,) bool), on the ``side`` ".L" or ".R" of the
    garment's centre for a trouser leg (along ``lateral`` (3,), the body's left, +x by default), and, with
    ``link`` [m], joined to ``sel`` by steps shorter than that through other candidates (a long sleeve
    hanging beside the hips reaches below the hem, apart from it)."""
    cand = g[:, 1] <= g[sel, 1].max()
    if exclude is not None:
        cand &= ~exclude
    if side:
        across = g[:, 0] if lateral is None else g @ lateral
        centre = np.median(across)
        cand &= (across > centre) if side == ".L" else (across < centre)
    if link is not None and cand.any():
        idx = np.flatnonzero(cand)
        comp = _linked_pieces(g[idx], link)
        at = np.full(len(g), -1)
        at[idx] = comp
        joined = np.zeros(comp.max() + 1, dtype=bool)
        joined[at[sel][at[sel] >= 0]] = True
        cand[idx] = joined[comp]
    return np.flatnonzero(cand)


def _lifted_rim(
    g: np.ndarray,
    rim: np.ndarray,
    cand: np.ndarray,
    others: np.ndarray,
    *,
    rise: float = 0.1,
    radius: float = 0.02,
    drop: float = 0.02,
    link: float = 0.03,
) -> np.ndarray:
    """A bottom opening's ``rim`` (indices into the garment points ``g`` (G, 3)) with the garment's own
    edge beside it that the lower envelope leaves out: where a hem is lifted outward (over a hand, in a
    fold), it climbs out of its sector's band, and the envelope keeps only its lowest part.

    Added are the candidates ``cand`` (indices into ``g``; `_beside_rim`: so that a hole over the hem is
    still skipped) that lie no more than ``rise`` [m] above the rim's highest point and
    are on an opening's edge (`_opening_rim` against ``others`` (N, 3), the non-garment points: no garment
    across), facing down (the gap's middle below the horizontal), with no garment point within ``radius``
    [m] across more than ``drop`` [m] below them (a hole's rim has the cloth under the hole below it), and
    joined to the rim by steps shorter than ``link`` [m] through one another. On 20 ring-captured tops
    (docs/BENCHMARKS.md, "Hems lifted out of the envelope"), the 13 hems the envelope traced with a gap,
    up to 13.3 cm short, came within 1.1 cm of the true hem on 10 (one 1.9 cm short, two long sleeves 3.3
    and 9.5); the 7 traced whole stayed within 0.6 cm of it.
    """
    near = cand[g[cand, 1] <= g[rim, 1].max() + rise]
    edge = np.setdiff1d(np.flatnonzero(_opening_rim(g, others, near) > 0), rim)
    if len(edge) == 0:
        return rim
    _, direction = _edge_gaps(g, edge)
    across = cKDTree(g[:, [0, 2]]).query_ball_point(g[edge][:, [0, 2]], radius)
    deepest = np.array([g[i, 1] - g[nbrs, 1].min() for i, nbrs in zip(edge, across, strict=True)])
    edge = edge[(direction[:, 1] < 0) & (deepest < drop)]
    both = np.union1d(rim, edge)
    pieces = _linked_pieces(g[both], link)
    return both[np.isin(pieces, pieces[np.isin(both, rim)])]


def _sector_index(angle: np.ndarray, sectors: int) -> np.ndarray:
    """(n,) int64: the one of ``sectors`` equal sectors of [−π, π] each ``angle`` (n,) [rad] falls in."""
    return np.minimum(((angle + np.pi) / (2 * np.pi) * sectors).astype(np.int64), sectors - 1)


def _sector_envelope(
    t: np.ndarray,
    angle: np.ndarray,
    sectors: int,
    band: float,
    max_drop: float,
    cliffs: bool = False,
) -> np.ndarray:
    """(n,) bool: the points within ``band`` of the largest ``t`` (n,) [m] of their angular sector (``angle``
    (n,) [rad] in [−π, π], ``sectors`` equal sectors), except in the sectors that are holes in the scan,
    not the rim: whose largest ``t`` falls more than ``max_drop`` [m] short of the median sector's, or,
    with ``cliffs``, those behind a cliff of ``max_drop`` (`_cliff_holes`: a rim may fall away gradually,
    a hole's edge falls at once)."""
    sector = _sector_index(angle, sectors)
    far = np.full(sectors, -np.inf)
    np.maximum.at(far, sector, t)
    seen = np.isfinite(far)
    if cliffs:
        ok = seen & ~_cliff_holes(far, max_drop)
    else:
        ok = seen & (far >= np.median(far[seen]) - max_drop)
    return ok[sector] & (t >= far[sector] - band)


def _cliff_holes(far: np.ndarray, cliff: float) -> np.ndarray:
    """(sectors,) bool: the sectors of a hole in a rim, from each sector's largest ``t`` ``far`` (sectors,)
    [m] (−inf: no points there, skipped). A hole's edge is a cliff: where ``far`` falls by more than
    ``cliff`` [m] from one seen sector to the next, the sectors from there on are the hole while they stay
    that far short of the sector before the cliff (walking both ways round, so that a hole's two edges
    find it). A rim that falls away gradually has no cliff and no hole."""
    seen = np.flatnonzero(np.isfinite(far))
    hole = np.zeros(len(far), dtype=bool)
    n = len(seen)
    for order in (seen, seen[::-1]):
        for i in range(n):
            level = far[order[i]]
            j = 1
            while j < n and far[order[(i + j) % n]] < level - cliff:
                hole[order[(i + j) % n]] = True
                j += 1
    return hole


def _distal_rim(
    garment_points: np.ndarray,
    sel: np.ndarray,
    limb: list[np.ndarray],
    sectors: int = 24,
    band: float = 0.04,
    max_drop: float = 0.05,
    min_count: int = 24,
) -> np.ndarray:
    """Of a cuff's rim points ``sel`` (indices into ``garment_points`` (G, 3)), those at the sleeve's end.

    A cuff is the garment's far end along its arm. Rim points nearer the shoulder belong to a gap in the
    garment's labels (tight cloth on a shoulder taken for skin leaves a bare patch named after the arm,
    whose rim also lies within reach of the arm). ``limb``: the (n, 3) vertices of the arm's parts from
    the shoulder out (upper arm, forearm, hand). The axis runs from the mean of the part nearest the
    points' centre to the next part's mean (the upper arm's for a short sleeve, the forearm's for a long
    one: their cuffs lie across it). Around that axis, in each of ``sectors`` angular sectors, the points
    within ``band`` [m] of the sector's farthest along the axis are kept (why 4 cm: on the suite's
    labelled tops all but 3 cuff rim points lie within it, some 1.5-4 cm behind their sector's farthest,
    a hanging sleeve end or a hole's rim beside it; a 1.5 cm band dropped them and moved the fits; the
    unlabelled T-shirt's shoulder patches lay 8 cm and more back). A sector
    whose farthest point falls more than ``max_drop`` [m] short of the median sector's is a hole in the
    scan, not the cuff, and is skipped. Falls back to ``sel`` when fewer than ``min_count`` remain.
    """
    if len(sel) < min_count or len(limb) < 2 or any(len(part) == 0 for part in limb):
        return sel
    centre = garment_points[sel].mean(0)
    near = [float(cKDTree(part).query(centre)[0]) for part in limb[:-1]]
    k = int(np.argmin(near))
    origin = limb[k].mean(0)
    along, angle = _about_axis(garment_points[sel], origin, limb[k + 1].mean(0) - origin)
    keep = _sector_envelope(along, angle, sectors, band, max_drop)
    return sel[keep] if keep.sum() >= min_count else sel


def _about_axis(points: np.ndarray, origin: np.ndarray, direction: np.ndarray):
    """(n,) coordinate [m] along the axis through ``origin`` (3,) along ``direction`` (3,) and (n,) angle
    [rad] about it of ``points`` (n, 3)."""
    axis = direction / np.linalg.norm(direction)
    u = np.cross(axis, [0.0, 0.0, 1.0] if abs(axis[2]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    d = points - origin
    return d @ axis, np.arctan2(d @ v, d @ u)


def _neck_rim(
    garment_points: np.ndarray,
    sel: np.ndarray,
    head: np.ndarray,
    torso: np.ndarray,
    sectors: int = 24,
    band: float = 0.02,
    min_count: int = 24,
) -> np.ndarray:
    """Of a neckline's rim points ``sel`` (indices into ``garment_points`` (G, 3)), those on the neckline.

    The neckline is the garment's top edge around the neck. Rim points below it belong to a gap in the
    garment's labels: tight cloth on the shoulders or the upper back taken for skin leaves a bare patch
    that borders the neckline, and the body names its rim after the head too (measured on the suite's
    T-shirt without labels: 41 of 130 neck points 2-10 cm down the back and the front). Around the axis
    from the torso's mean to the head's (``torso``, ``head``: (n, 3) body vertices of those parts), in each
    of ``sectors`` angular sectors, the points within ``band`` [m] of the sector's highest along the axis
    are kept. No sector is skipped: a V or scoop neck lies far lower in front than at the back. Falls
    back to ``sel`` when fewer than ``min_count`` remain.
    """
    if len(sel) < min_count or len(head) == 0 or len(torso) == 0:
        return sel
    height, angle = _about_axis(garment_points[sel], head.mean(0), head.mean(0) - torso.mean(0))
    keep = _sector_envelope(height, angle, sectors, band, np.inf)
    return sel[keep] if keep.sum() >= min_count else sel


def _plane_normal(points: np.ndarray) -> np.ndarray:
    """(3,) unit normal of the least-squares plane of ``points`` (n, 3)."""
    return np.linalg.svd(points - points.mean(0), full_matrices=False)[2][2]


def _neck_opening(
    garment_points: np.ndarray,
    rim: np.ndarray,
    near: np.ndarray,
    skin_loop: np.ndarray,
    head: np.ndarray,
    torso: np.ndarray,
    forward: np.ndarray,
    max_tilt_deg: float = 45.0,
    max_back_deg: float = 120.0,
    sectors: int = 24,
    band: float = 0.03,
    min_count: int = 24,
) -> np.ndarray:
    """Of the rim points of the opening at the head, those on it: a neckline's or a hood's face opening.

    ``rim``: all the garment's rim points nearest this opening (indices into ``garment_points`` (G, 3));
    ``near``: those of them near the bare skin's boundary (the other openings' rule). ``skin_loop``
    (k, 3): that boundary on the body, around the neck, or around the face under a hood; ``torso``,
    ``head``: (n, 3) body vertices of those parts; ``forward`` (3,): the direction the body faces.

    When the plane of ``skin_loop`` tilts by more than ``max_tilt_deg`` from across the torso→head axis
    (necklines 10-21°, GarmentCode's hoody 88-89°), a hood covers the head. Its face opening stands in
    front of the face, its sides several centimetres off it, beyond ``near``'s reach (on the hoody, 48
    mm from the true opening with ``near`` alone), and a stiff hood's top juts forward like a visor.
    The opening's edge looks forward or across the opening; the rims of holes in the hood's sides and
    crown that look back, more than ``max_back_deg`` from ``forward``, go. The opening is the front of
    the rest: about the axis through the head's centre along ``forward``, in each of ``sectors``
    angular sectors, the points within ``band`` [m] of the sector's farthest forward (on four hoody
    scans 4-22 mm from the true opening, and it 10-20 mm from them; the neckline's rule: 20-69 and
    44-79 mm). Otherwise the opening is a neckline: `_neck_rim` of ``near``. Falls back to ``near``
    when fewer than ``min_count`` remain.
    """
    if len(rim) >= min_count and len(skin_loop) >= 3 and len(head) and len(torso):
        up = head.mean(0) - torso.mean(0)
        if abs(_plane_normal(skin_loop) @ up) < np.cos(np.deg2rad(max_tilt_deg)) * np.linalg.norm(up):
            _, out_of_cloth = _edge_gaps(garment_points, rim)
            facing = rim[out_of_cloth @ forward > np.cos(np.deg2rad(max_back_deg)) * np.linalg.norm(forward)]
            if len(facing) >= min_count:
                along, angle = _about_axis(garment_points[facing], head.mean(0), forward)
                keep = _sector_envelope(along, angle, sectors, band, np.inf)
                if keep.sum() >= min_count:
                    return facing[keep]
            return near
    return _neck_rim(garment_points, near, head, torso, min_count=min_count)


def _edge_gaps(garment_points: np.ndarray, sel: np.ndarray, k: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """Widest angular gap [rad] (S,) among the ``k`` nearest garment points of each of the points ``sel``
    (indices into ``garment_points`` (G, 3)), seen in its local tangent plane (PCA of those neighbours),
    and (S, 3) the unit direction of the gap's middle: at the garment's edge, out of the garment."""
    g = garment_points
    _, nbr = cKDTree(g).query(g[sel], k=k)
    d = g[nbr] - g[sel][:, None, :]  # (S, k, 3)
    centred = d - d.mean(1, keepdims=True)
    _, vec = np.linalg.eigh(np.einsum("ski,skj->sij", centred, centred))
    u, v = vec[:, :, 2], vec[:, :, 1]  # the two largest directions span the tangent plane
    angle = np.sort(np.arctan2(np.einsum("ski,si->sk", d, v), np.einsum("ski,si->sk", d, u))[:, 1:], axis=1)
    gaps = np.diff(np.concatenate([angle, angle[:, :1] + 2 * np.pi], axis=1), axis=1)
    widest = gaps.argmax(1)
    rows = np.arange(len(sel))
    middle = angle[rows, widest] + 0.5 * gaps[rows, widest]
    direction = np.cos(middle)[:, None] * u + np.sin(middle)[:, None] * v
    return gaps[rows, widest], direction


def _edge_points(
    garment_points: np.ndarray, sel: np.ndarray, k: int = 32, min_gap_deg: float = 120.0, min_count: int = 24
) -> np.ndarray:
    """Of the garment points ``sel`` (indices into ``garment_points`` (G, 3)) near an opening, those on
    the garment's edge: seen in its local tangent plane (PCA of its ``k`` nearest garment points), an
    edge point's neighbours leave an angular gap wider than ``min_gap_deg`` (they lie on one side). The
    band found from the body is a few centimetres wide; its edge points are the opening's rim. Falls back
    to ``sel`` when fewer than ``min_count`` qualify (a very noisy scan: a rim that sparse is a worse
    target than the whole band). Why k = 32 and 120°: n random directions leave a
    gap wider than θ with probability ≈ n (1 − θ/2π)^(n−1) — 16 % for 15 neighbours and 100° (interior
    points of an area-sampled scan got flagged), 0.02 % for 31 and 120°; an edge point's gap is ~180°.
    """
    k = min(k, len(garment_points))
    if k < 4 or len(sel) == 0:
        return sel
    gap, _ = _edge_gaps(garment_points, sel, k)
    edge = gap > np.deg2rad(min_gap_deg)
    return sel[edge] if edge.sum() >= min_count else sel


def _opening_rim(
    garment_points: np.ndarray,
    other_points: np.ndarray,
    sel: np.ndarray,
    k: int = 32,
    min_gap_deg: float = 120.0,
    near: float = 0.025,
    far: float = 0.15,
    cone_deg: float = 20.0,
    adjacent: float = 0.05,
    adjacent_cone_deg: float = 60.0,
) -> np.ndarray:
    """Of the garment points ``sel`` (indices into ``garment_points`` (G, 3)), those on the rim of an
    opening rather than of a hole in the scan.

    A rim point is on the garment's edge (`_edge_gaps`, as `_edge_points`). Looking out of the garment
    from it (along the gap's middle, within a cone of ``cone_deg`` from ``near`` to ``far`` [m]), a
    hole's rim sees the garment again across the hole before any skin (``other_points`` (N', 3), the
    scan points that are not garment): holes are cut through garment and skin alike, and the skin under
    the cloth is not seen. Out of an opening the limb (skin) comes first, or nothing (the air below a
    hem, a hand hidden by its cuff). Why 15 cm: the scan's holes are up to 16 cm across (8 cm balls);
    why 20°: the garment across a hole curves away from the ray with the body (a 16 cm chord of a 15 cm
    torso sags 2.3 cm; the cone is 5 cm wide there).

    Returns:
        (G,) int64 per garment point: 0, not an opening's rim (or not in ``sel``); 1, an opening's rim;
        2, one with skin right ahead (within ``adjacent`` [m], in a cone of ``adjacent_cone_deg``).
    """
    k = min(k, len(garment_points))
    if k < 4 or len(sel) == 0:
        return np.zeros(len(garment_points), dtype=np.int64)
    gap, direction = _edge_gaps(garment_points, sel, k)
    edge = np.flatnonzero(gap > np.deg2rad(min_gap_deg))
    p, d = garment_points[sel[edge]], direction[edge]
    tan_cone = np.tan(np.deg2rad(cone_deg))

    def first_ahead(cloud: np.ndarray) -> np.ndarray:
        """(R,) distance along the ray to the nearest point of ``cloud`` in each rim point's cone (inf)."""
        out = np.full(len(p), np.inf)
        if len(cloud) == 0:
            return out
        for i, nbrs in enumerate(cKDTree(cloud).query_ball_point(p, far)):
            if nbrs:
                q = cloud[nbrs] - p[i]
                t = q @ d[i]
                lateral = np.linalg.norm(q - t[:, None] * d[i], axis=1)
                inside = (t > near) & (lateral < tan_cone * t)
                if inside.any():
                    out[i] = t[inside].min()
        return out

    garment_at = first_ahead(garment_points)
    skin_at = first_ahead(np.asarray(other_points))
    # skin right ahead, in a wider cone
    strong = np.zeros(len(p), dtype=bool)
    if len(other_points):
        cos_adj = np.cos(np.deg2rad(adjacent_cone_deg))
        for i, nbrs in enumerate(cKDTree(other_points).query_ball_point(p, adjacent)):
            if nbrs:
                q = other_points[nbrs] - p[i]
                strong[i] = bool((q @ d[i] >= cos_adj * np.linalg.norm(q, axis=1)).any())
    kind = np.zeros(len(garment_points), dtype=np.int64)
    kind[sel[edge[skin_at <= garment_at]]] = 1
    kind[sel[edge[strong]]] = 2
    return kind


@dataclass(frozen=True)
class _OpeningRules:
    """The knobs of `_boundary_loops` (see its docstring): lengths [m], counts, an angle [deg]."""

    min_edges: int = 12
    reach: float = 0.1
    weak_reach: float = 0.05
    limb_reach: float = 0.06
    link: float = 0.03
    min_rim: int = 24
    max_neck_tilt_deg: float = 45.0


def _boundary_loops(
    points: np.ndarray,
    labels: np.ndarray,
    near: np.ndarray,
    body_vertices: np.ndarray,
    body_faces: np.ndarray,
    vertex_parts: np.ndarray,
    kind: str,
    min_edges: int = 12,
    reach: float = 0.1,
    weak_reach: float = 0.05,
    limb_reach: float = 0.06,
    link: float = 0.03,
    min_rim: int = 24,
    max_neck_tilt_deg: float = 45.0,
) -> list[ScanOpening]:
    """The garment's openings, found on the body (see the module docstring).

    Every boundary vertex of the covered region is named by the limb (head and neck, an arm, a leg)
    nearest to it along the uncovered skin (a multi-source Dijkstra over the body's edges): so a
    neckline and an armhole that meet at a bare shoulder still come out as two openings, and a low
    neckline, with only chest outside it, is still a neck.

    The points of an opening are garment rim points (`_opening_rim`: on the garment's edge, not a
    hole's), of the garment's main piece (`_main_piece`, steps < ``link`` [m]), nearest to this
    opening's body loop (within ``reach`` [m]; within ``weak_reach`` when no skin lies right ahead);
    a cuff's (or a sleeveless armhole's) also within ``limb_reach`` [m] of its arm, then its sleeve's
    far end (`_distal_rim`, sleeves only); a neck's: its neckline, or a hood's face opening, whose body
    loop (around the face) tilts by more than ``max_neck_tilt_deg`` from horizontal (`_neck_opening`).
    Fewer than ``min_rim``: the edge of the band near the loop, as before (`_edge_points`); fewer than
    three points: the opening is not found. Hems and trouser legs: `_lower_rim` over the main piece,
    joined to the loop's band by steps < ``link`` (a hanging sleeve is not hem).

    Args:
        points: (N, 3) scan points [m]; labels: (N,) bool garment labels; near: (N,) nearest body vertex.
        body_vertices: (Vb, 3) [m]; body_faces: (Fb, 3); vertex_parts: (Vb,) index into `PART_NAMES`.
        kind: the garment type (`GARMENT_TYPES`).
        min_edges: boundary vertices an opening needs on the body (fewer: a hole in the labels).

    Returns:
        the openings found, sorted by name.
    """
    rules = _OpeningRules(min_edges, reach, weak_reach, limb_reach, link, min_rim, max_neck_tilt_deg)
    if labels.sum() == 0:
        return []
    covered = _covered_body(points, labels, body_vertices, body_faces, vertex_parts)
    face_in = covered[body_faces].all(1)
    grouped = _opening_vertices(
        covered, face_in, body_vertices, body_faces, vertex_parts, kind, rules.min_edges
    )
    if not grouped:
        return []
    finder = _RimFinder.build(
        points, labels, near, body_vertices, body_faces, vertex_parts, face_in, grouped, rules
    )
    loops = []
    for i, (name, verts) in enumerate(grouped.items()):
        sel = finder.band(verts)
        if name.startswith("hem"):  # "hem", or a trouser leg's "hem_left" / "hem_right"
            sel = finder.lower_rim(sel, _part_side(name)) if len(sel) else sel
        else:
            sel = finder.rim(i, name, verts, sel, sleeved=kind in _SLEEVED)
        if len(sel) < 3:  # no loop to order (a sparse scan with a hole over the opening): not found
            continue
        order = _loop_order(finder.garment_points[sel])
        loops.append(ScanOpening(name=name, point_indices=sel[order], body_vertices=np.asarray(verts)))
    return sorted(loops, key=lambda loop: loop.name)


def _opening_vertices(
    covered: np.ndarray,
    face_in: np.ndarray,
    body_vertices: np.ndarray,
    body_faces: np.ndarray,
    vertex_parts: np.ndarray,
    kind: str,
    min_edges: int,
) -> dict[str, list[int]]:
    """Opening name -> the body vertices on the covered region's boundary named after it, in the order
    of their boundary cycles; openings with fewer than ``min_edges`` vertices are left out.

    Args:
        covered: (Vb,) bool covered body vertices; face_in: (Fb,) bool faces with three covered corners.
        body_vertices, body_faces, vertex_parts, kind: as in `_boundary_loops`.
    """
    fin = body_faces[face_in]
    edges = np.sort(np.concatenate([fin[:, [0, 1]], fin[:, [1, 2]], fin[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = uniq[counts == 1]
    if len(boundary) == 0:
        return {}
    nearest = _nearest_extremity(covered, boundary, body_vertices, body_faces, vertex_parts)
    if nearest is None:  # the garment covers every limb: no opening can be told apart
        return {}
    dist, origin, origin_name = nearest
    grouped: dict[str, list[int]] = {}
    for cycle in _edge_cycles(boundary):
        if len(cycle) < min_edges:
            continue
        for v in cycle:
            if np.isfinite(dist[v]):
                grouped.setdefault(_opening_name(origin_name[int(origin[v])], kind), []).append(v)
    return {name: verts for name, verts in grouped.items() if len(verts) >= min_edges}


def _nearest_extremity(
    covered: np.ndarray,
    boundary: np.ndarray,
    body_vertices: np.ndarray,
    body_faces: np.ndarray,
    vertex_parts: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, dict[int, str]] | None:
    """Geodesic distance over uncovered skin (and into the ``boundary`` (E, 2) edges' vertices) from the
    uncovered limb and head skin, named by the extremity at the end of its limb (the trunk, torso and
    hips, belongs to no opening by itself).

    Returns:
        (Vb,) distance [m] (inf: unreached), (Vb,) its nearest source vertex, source vertex -> extremity
        (`_EXTREMITIES`); None when no limb skin is uncovered.
    """
    import scipy.sparse as sp
    from scipy.sparse.csgraph import dijkstra

    e = np.concatenate([body_faces[:, [0, 1]], body_faces[:, [1, 2]], body_faces[:, [2, 0]]])
    on_boundary = np.zeros(len(body_vertices), dtype=bool)
    on_boundary[boundary.reshape(-1)] = True
    e = e[(~covered[e[:, 0]] | ~covered[e[:, 1]]) & (~covered | on_boundary)[e].all(1)]
    n = len(body_vertices)
    length = np.linalg.norm(body_vertices[e[:, 0]] - body_vertices[e[:, 1]], axis=1) + 1e-12
    graph = sp.coo_matrix((length, (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    limb = ~covered & ~np.isin(vertex_parts, [PART_NAMES.index("torso"), PART_NAMES.index("hips")])
    sources = np.flatnonzero(limb)
    if len(sources) == 0:
        return None
    source_names = [_limb_extremity(PART_NAMES[p]) for p in vertex_parts[sources]]
    dist, _, origin = dijkstra(
        graph, directed=False, indices=sources, min_only=True, return_predecessors=True
    )
    return dist, origin, {int(s): nm for s, nm in zip(sources, source_names)}


def _loop_order(p: np.ndarray) -> np.ndarray:
    """(M,) order of the points ``p`` (M, 3) by their angle about their centre in their best-fit plane."""
    centre = p.mean(0)
    _, _, vt = np.linalg.svd(p - centre, full_matrices=False)
    uv = (p - centre) @ vt[:2].T
    return np.argsort(np.arctan2(uv[:, 1], uv[:, 0]))


@dataclass
class _RimFinder:
    """The garment's points and the body, shared by `_boundary_loops` while it picks each opening's points.

    Attributes:
        garment_points: (G, 3) the garment's scan points [m]; garment_near: (G,) their nearest body vertex.
        main: (G,) bool, on the garment's main piece (`_main_piece`).
        nearest_loop: (G,) index (into the openings) of the body loop nearest each main point; −1 elsewhere.
        loop_dist: (G,) distance [m] to the nearest body loop.
        rim_kind: (G,) `_opening_rim` of the main points within ``rules.reach`` of a loop.
        other_points: (N', 3) the scan points that are not garment [m].
        body_vertices, body_faces, vertex_parts: the body; face_in: (Fb,) bool covered faces.
        rules: the knobs.
    """

    garment_points: np.ndarray
    garment_near: np.ndarray
    main: np.ndarray
    nearest_loop: np.ndarray
    loop_dist: np.ndarray
    rim_kind: np.ndarray
    other_points: np.ndarray
    body_vertices: np.ndarray
    body_faces: np.ndarray
    vertex_parts: np.ndarray
    face_in: np.ndarray
    rules: _OpeningRules

    @classmethod
    def build(
        cls, points, labels, near, body_vertices, body_faces, vertex_parts, face_in, grouped, rules
    ) -> _RimFinder:
        """From the scan (as `_boundary_loops`) and the openings' body vertices ``grouped`` (name -> list)."""
        garment_idx = np.flatnonzero(labels)
        garment_points = points[garment_idx]
        # Only the garment itself: its points joined by steps shorter than ``link`` to its largest piece
        # (stray garment labels on a hand or a leg have rims too, beside the openings).
        main = _main_piece(garment_points, rules.link)
        # Each garment point's nearest opening, by its distance to the openings' body loops: a point of a
        # sleeve hanging by the hips has its nearest body vertex on the hips, yet lies by its cuff's loop.
        names = list(grouped)
        loop_vertices = np.concatenate([np.asarray(grouped[nm]) for nm in names])
        owner = np.repeat(np.arange(len(names)), [len(grouped[nm]) for nm in names])
        loop_dist, j = cKDTree(body_vertices[loop_vertices]).query(garment_points)
        rim_kind = _opening_rim(
            garment_points, points[~labels], np.flatnonzero(main & (loop_dist < rules.reach))
        )
        return cls(
            garment_points=garment_points,
            garment_near=near[garment_idx],
            main=main,
            nearest_loop=np.where(main, owner[j], -1),
            loop_dist=loop_dist,
            rim_kind=rim_kind,
            other_points=points[~labels],
            body_vertices=body_vertices,
            body_faces=body_faces,
            vertex_parts=vertex_parts,
            face_in=face_in,
            rules=rules,
        )

    def band(self, verts: list[int]) -> np.ndarray:
        """(S,) the main garment points whose nearest body vertex lies on the loop ``verts`` or within
        two rings of it on the covered side (so that points near the edge are caught)."""
        ring = set(verts)
        for _ in range(2):
            grow = self.body_faces[np.isin(self.body_faces, list(ring)).any(1) & self.face_in]
            ring |= set(grow.reshape(-1).tolist())
        return np.flatnonzero(np.isin(self.garment_near, list(ring)) & self.main)

    def lower_rim(self, sel: np.ndarray, side: str) -> np.ndarray:
        """A hem's or a trouser leg's points (`_lower_rim` over the main piece; ``side`` ".L", ".R" or "")
        from its band ``sel`` (indices into the garment points, all on the main piece)."""
        in_main = np.flatnonzero(self.main)  # sel is within main
        pos = np.searchsorted(in_main, sel)
        parts = self.vertex_parts
        # A captured person faces any way: the legs lie left and right of the body's own left-right axis,
        # not of x (on scans turned 90° the trouser legs' hems each took half of both legs, 97-110 cm
        # traced against 69). Anny's left is +x.
        left = self.body_vertices[parts == PART_NAMES.index("thigh.L")].mean(0)
        lateral = left - self.body_vertices[parts == PART_NAMES.index("thigh.R")].mean(0)
        lateral[1] = 0.0
        # a long sleeve whose cuff hangs by the hem is no hem (a captured long sleeve's hem took both
        # cuffs: 236 cm traced against 115)
        arms = [PART_NAMES.index(p + s) for p in _ARM_PARTS for s in (".L", ".R")]
        on_arm = np.isin(parts[self.garment_near[self.main]], arms)
        rim = _lower_rim(
            self.garment_points[self.main],
            pos,
            side=side,
            link=self.rules.link,
            lateral=lateral / np.linalg.norm(lateral),
            exclude=on_arm,
            others=self.other_points,
        )
        return in_main[rim]

    def rim(self, i: int, name: str, verts: list[int], sel: np.ndarray, *, sleeved: bool) -> np.ndarray:
        """The points of opening ``i`` (``name``, body loop ``verts``) other than a hem: its rim points,
        else the edge of its band ``sel`` (see `_boundary_loops`); empty when neither is found."""
        rules = self.rules
        mine = np.flatnonzero((self.nearest_loop == i) & (self.rim_kind > 0))
        mine = mine[(self.rim_kind[mine] == 2) | (self.loop_dist[mine] < rules.weak_reach)]
        if name.startswith("cuff"):
            mine = self._arm_rim(mine, _part_side(name), distal=sleeved)
        elif name == "neck":
            mine = self._neck_rim(i, mine, verts)
        if len(mine) >= rules.min_rim:
            return mine
        if len(sel) == 0:
            return sel
        # too few rim points (a very noisy or sparse scan): the edge of the band near the loop
        edge = _edge_points(self.garment_points, sel)
        if name.startswith("cuff") and sleeved:
            # A depth capture's noise (σ 9 mm at 2.2 m) hides the edge, and the band then covers the
            # sleeve's last 20 cm: its far end is the cuff, within 2 cm, about twice the noise (on captured
            # T-shirts, seeds 62-64: the band 7.6-8.4 cm from the true cuff on average, the far end within
            # 4 cm 2.5-3.0, within 2 cm 1.7-1.9; a cuff whose rim is found: 1.1).
            edge = self._arm_rim(edge, _part_side(name), distal=True, band=0.02)
        return edge

    def _arm_rim(self, mine: np.ndarray, side: str, *, distal: bool, band: float = 0.04) -> np.ndarray:
        """Of the rim points ``mine``, those by the arm on ``side`` (".L" / ".R"): a garment labelled
        short of a shoulder leaves a bare "arm" patch there that the body names after the arm; with
        ``distal`` (a sleeve, not an armhole) only the sleeve's far end (`_distal_rim`, within ``band`` [m]
        of it)."""
        parts = self.vertex_parts
        limb = [self.body_vertices[parts == PART_NAMES.index(p + side)] for p in _ARM_PARTS]
        limb_dist, _ = cKDTree(np.concatenate(limb)).query(self.garment_points[mine])
        mine = mine[limb_dist < self.rules.limb_reach]
        return _distal_rim(self.garment_points, mine, limb, band=band) if distal else mine

    def _neck_rim(self, i: int, mine: np.ndarray, verts: list[int]) -> np.ndarray:
        """Of the rim points ``mine`` of opening ``i`` at the head (body loop ``verts``), the neckline's
        or a hood's face opening's (`_neck_opening`)."""
        head, torso, arm_l, arm_r = (
            self.body_vertices[self.vertex_parts == PART_NAMES.index(p)]
            for p in ("head", "torso", "upperarm.L", "upperarm.R")
        )
        # the body faces along left x up (Anny's left is +x, up +y, facing +z)
        forward = np.cross(arm_l.mean(0) - arm_r.mean(0), head.mean(0) - torso.mean(0))
        rim = np.flatnonzero((self.nearest_loop == i) & (self.rim_kind > 0))
        loop = self.body_vertices[verts]
        return _neck_opening(
            self.garment_points,
            rim,
            mine,
            loop,
            head,
            torso,
            forward,
            max_tilt_deg=self.rules.max_neck_tilt_deg,
        )
