"""How long a hem (or a waistband) is: read off a scan's opening points and off a pattern's rest shape.

Cloth barely stretches along a free edge (about 1 % where another simulator's soft cloth hangs, 0.1-0.5 %
in ours), so a draped hem is as long as its pattern's hem edges whatever physics draped it. A fit that
cannot reproduce a scan's folds can still match the hem's position with a narrower hem, and did: on
Newton-made scans the fits narrowed the true hems by up to 24 cm (issue #30). The length is evidence that
does not depend on the physics, so the fit holds the pattern's hem to it (`opening_length_loss`; which
openings: `FitConfig.opening_length_names`, the hems, and a trouser's waistband, which lies on the body).

`scan_loop_length` traces the opening's points around their centre: the median point of each angular bin
(``bin_length`` along the loop), joined in angle order. Holes and unseen sides are crossed by a chord and
folds finer than a few bins are smoothed away (on a 1.2 m ring with 3 mm noise and 1.5 cm deep folds,
2 cm bins: −0.7 % at a 15 cm wavelength, −6 % at 8.5 cm), both of which shorten the curve, so the length
is a lower bound of the true loop's up to the noise the medians leave. Measured on 17 hems of 15 scans
(Newton's and ours, and the demo's; docs/BENCHMARKS.md, "The hem's length from the scan"): −11.0 to
+1.7 cm against the true hem, the large shortfalls where a hole covers part of a hem or folds are fine.
Hence the loss is one-sided. The fit gives the garment's own opening as a reference, whose curve bridges
a hole instead of the chord (on 18 partly seen hems and waists: shortfalls of up to 9.8 cm cut to 7.5, at
most 2.9 cm over the truth, three sparse waists held that had no length; docs/BENCHMARKS.md, "Holes over a
hem bridged by the garment's curve").
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from torch_diffavatar.geometry import gather_rows
from torch_diffavatar.pattern.garment_mesh import BoundaryLoop, GarmentMesh


def scan_loop_length(
    points,
    *,
    bin_length: float = 0.02,
    min_bins: int = 12,
    points_per_bin: int = 10,
    reference=None,
    min_seen: float = 0.6,
) -> tuple[float, float]:
    """The length [m] of the closed curve that a scan opening's points trace, and how much of it is seen.

    The points are projected on their least-squares plane and binned by their angle about their centroid
    into bins about ``bin_length`` [m] long (at the median radius; longer where ``points_per_bin`` asks);
    each bin with two or more points gives its median radius and median height at the bin's mid-angle; the
    bins are joined in angle order, across empty bins by a chord.

    With a ``reference`` loop (the garment's own opening, in order: as placed, or a drape) and a scan that
    does not show the whole opening (a hole over a hem, a sparse waistband missing a bin), the gaps are
    bridged by the reference's curve instead of a chord (`_seen_loop_length`), never shorter than the
    chord's trace; and a sparse opening with one empty bin gets a length at all (without a reference
    every bin of the fewest, ``min_bins``, must hold points).

    Args:
        points: (k, 3) scan points of one opening [m] (numpy or tensor).
        bin_length: bin length along the loop [m]: shorter bins follow finer folds but keep more noise.
        min_bins: the fewest bins with points for a length (fewer: ``(nan, coverage)``).
        points_per_bin: longer bins when the opening has fewer than this many points per bin: a median of
            a few points of a band a few cm tall jitters from bin to bin and lengthens the curve (a scan
            of 14k cloth points with 320 hem points, the bundled demo's: +4.5 cm on its 139 cm hem at 2 cm
            bins, +1.0 at this rule's 4.5 cm).
        reference: optional (m, 3) [m] the garment's opening, its vertices in loop order (numpy or tensor).
        min_seen: with a ``reference``, the least share of it the scan must show for a length.

    Returns:
        ``(length, coverage)``: the length [m] (nan when too few bins hold points) and the fraction [0, 1]
        of the bins with points.
    """
    p = _as_points(points, "points")
    if not bin_length > 0:
        raise ValueError(f"bin_length must be > 0, got {bin_length}")
    if len(p) < 2 * min_bins:
        return math.nan, 0.0
    centre, axes = _loop_plane(p)
    curve = _binned_curve(p, centre, axes, _bin_count(p, centre, axes, bin_length, min_bins, points_per_bin))
    seen = ~np.isnan(curve[:, 0])
    coverage = float(seen.mean())
    traced = math.nan
    if seen.sum() >= min_bins:
        traced = float(_steps(curve[seen]).sum())
    if reference is None or coverage == 1.0:
        return traced, coverage
    kw = dict(bin_length=bin_length, min_bins=min_bins, points_per_bin=points_per_bin, min_seen=min_seen)
    extrapolated = _seen_loop_length(p, _as_points(reference, "reference"), **kw)
    # the chord's trace is a lower bound (up to noise): never less than it
    return float(np.fmax(extrapolated, traced)), coverage


def mirrored_lengths(traced: dict[str, tuple[float, float]]) -> dict[str, tuple[float, list[str]]]:
    """One length for each mirrored pair of openings, ``<name>_left`` and ``<name>_right`` (a trouser's
    hems): the better-seen one's trace, their mean when both are seen as much.

    A pattern whose mirrored panels are tied (`ControlCage` ``tie_mirrored``) has one length for both, and
    each held no shorter than its own trace held both to the longer. Where a hem is partly hidden the
    bridge over the gap, and the stray points of a fold beside it, can lengthen its trace past the truth:
    Newton's trousers of seed 0 traced 70.2 cm on the left hem, seen whole, and 75.8 on the right, 86 %
    seen, against a true 68.8, and the fit widened both hems to 75.4 (docs/BENCHMARKS.md, "A mirrored pair
    of hems held to the better-seen one").

    Args:
        traced: opening name -> ``(length [m], seen [0, 1])`` as `scan_loop_length` returns them (nan
            length: traced none).

    Returns:
        opening name -> ``(length [m], names)``: the length to hold it to and the openings whose traces
        give it (its own; its mirror's; or both, averaged), for every opening of ``traced``.
    """
    out = {name: (length, [name]) for name, (length, _) in traced.items()}
    for name, (length, seen) in traced.items():
        if not name.endswith("_left"):
            continue
        mirror = name[: -len("_left")] + "_right"
        if mirror not in traced or not math.isfinite(length) or not math.isfinite(traced[mirror][0]):
            continue
        other, other_seen = traced[mirror]
        if seen == other_seen:
            both = (0.5 * (length + other), [name, mirror])
            out[name] = out[mirror] = both
        else:
            out[name] = out[mirror] = (length, [name]) if seen > other_seen else (other, [mirror])
    return out


def _seen_loop_length(
    p: np.ndarray, reference: np.ndarray, *, bin_length, min_bins, points_per_bin, min_seen
) -> float:
    """The length [m] of an opening that the scan points ``p`` (k, 3) show in part, with the garment's
    ``reference`` loop (m, 3, in loop order) for the curve of the parts they miss.

    Both are binned by angle about the reference's centre (as `scan_loop_length` bins). The steps between
    neighbouring bins that both hold scan points are traced as the scan shows them; across each run of
    empty bins the scan's chord is scaled by the reference's arc over its chord between the same bins
    (1.11 over a quarter of a circle): a hole bridged by the curve the garment has there, not by a straight
    line, and by the scan's own width across it (the reference's size does not count, only its shape).
    nan when fewer than three steps are seen, when the seen bins cover less than ``min_seen`` of the
    reference's length, or when the reference is not a loop around its centre.
    """
    dense = _densify_loop(reference)
    centre, axes = _loop_plane(dense)
    bins = _bin_count(p, centre, axes, bin_length, min_bins, points_per_bin)
    scan, ref = _binned_curve(p, centre, axes, bins), _binned_curve(dense, centre, axes, bins)
    if np.isnan(ref).any():  # a bin the reference does not pass through: not a loop around its centre
        return math.nan
    has = ~np.isnan(scan[:, 0])
    held = np.flatnonzero(has)
    ref_step = _steps(ref)
    seen = has & np.roll(has, -1)  # the steps b -> b + 1 with scan points at both ends
    if seen.sum() < 3 or float(ref_step[seen].sum()) < min_seen * float(ref_step.sum()):
        return math.nan
    length = float(_steps(scan)[seen].sum())
    for a, b in zip(held, np.roll(held, -1), strict=True):  # each run of empty bins between a and b
        if (b - a) % bins > 1:
            steps = (a + np.arange((b - a) % bins)) % bins
            ref_chord = float(np.linalg.norm(ref[b] - ref[a]))
            arc_over_chord = float(ref_step[steps].sum()) / ref_chord if ref_chord > 0 else 1.0
            length += float(np.linalg.norm(scan[b] - scan[a])) * arc_over_chord
    return length


def _steps(curve: np.ndarray) -> np.ndarray:
    """(n,) the lengths of the steps b -> b + 1 (cyclic) of a curve (n, 3); nan where an end is nan."""
    return np.linalg.norm(np.roll(curve, -1, 0) - curve, axis=1)


def _as_points(points, name: str) -> np.ndarray:
    """(k, 3) float64 numpy points from numpy or a tensor; ValueError for another shape."""
    p = np.asarray(points.detach().cpu() if torch.is_tensor(points) else points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name} must have shape (k, 3), got {p.shape}")
    return p


def _loop_plane(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centre (3,), axes (3, 3)) of points (k, 3): their centroid, and as rows their least-squares
    plane's two axes, then its normal."""
    centre = p.mean(0)
    return centre, np.linalg.svd(p - centre, full_matrices=False)[2]


def _bin_count(p, centre, axes, bin_length: float, min_bins: int, points_per_bin: int) -> int:
    """Angular bins about ``bin_length`` [m] long at the points' median radius about ``centre`` in the
    plane ``axes``, at least ``min_bins``, fewer when the points are fewer than ``points_per_bin`` a bin."""
    q = p - centre
    radius = np.hypot(q @ axes[0], q @ axes[1])
    bins = int(round(2 * math.pi * float(np.median(radius)) / bin_length))
    return max(min_bins, min(bins, len(p) // points_per_bin))


def _binned_curve(p: np.ndarray, centre: np.ndarray, axes: np.ndarray, bins: int) -> np.ndarray:
    """(bins, 3) in the plane's coordinates: per angular bin about ``centre`` with two or more of the
    points ``p`` (k, 3), their median radius and median height at the bin's mid-angle; nan rows elsewhere."""
    q = p - centre
    u, v, h = q @ axes[0], q @ axes[1], q @ axes[2]
    angle, radius = np.arctan2(v, u), np.hypot(u, v)
    index = np.floor((angle + math.pi) / (2 * math.pi) * bins).astype(np.int64) % bins
    curve = np.full((bins, 3), math.nan)
    for b in range(bins):
        inside = index == b
        if inside.sum() < 2:
            continue
        mid = (b + 0.5) / bins * 2 * math.pi - math.pi
        r = float(np.median(radius[inside]))
        curve[b] = (r * math.cos(mid), r * math.sin(mid), float(np.median(h[inside])))
    return curve


def _densify_loop(loop: np.ndarray, per_edge: int = 10) -> np.ndarray:
    """(m * per_edge, 3) points evenly along each edge of the closed polyline ``loop`` (m, 3)."""
    t = np.arange(per_edge)[:, None, None] / per_edge
    return (loop[None] + t * (np.roll(loop, -1, 0) - loop)[None]).reshape(-1, 3)


def rest_loop_edges(garment: GarmentMesh, loop: BoundaryLoop) -> torch.Tensor:
    """(L, 2) int64 panel-vertex pairs of the rest edges along an opening ``loop`` (on sim vertices): for
    each step of the loop, the two ends of the panel outline edge that makes it.

    Raises:
        ValueError: a step of the loop is on no panel's outline (the loop is not this garment's).
    """
    to_sim = garment.vert_to_sim.tolist()
    edges = {}
    for outline in garment.panel_boundary:
        ring = outline.tolist()
        for a, b in zip(ring, ring[1:] + ring[:1], strict=True):
            edges[(to_sim[a], to_sim[b])] = (a, b)
            edges[(to_sim[b], to_sim[a])] = (b, a)
    steps = loop.vertices.tolist()
    pairs = []
    for s, t in zip(steps, steps[1:] + steps[:1], strict=True):
        if (s, t) not in edges:
            raise ValueError(f"opening {loop.name!r}: sim vertices {s}-{t} are on no panel outline")
        pairs.append(edges[(s, t)])
    return torch.tensor(pairs, dtype=torch.int64).reshape(-1, 2)


def rest_loop_length(rest_uv: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """() the rest length [m] of an opening: the summed lengths of its (L, 2) ``edges`` (`rest_loop_edges`)
    at the panel-vertex rest coordinates ``rest_uv`` (V, 2) [m]."""
    return _edge_lengths(rest_uv, edges).sum()


def _edge_lengths(rest_uv: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """(L,) [m] the lengths of the (L, 2) panel-vertex ``edges`` at ``rest_uv`` (V, 2) [m]."""
    e = edges.to(rest_uv.device)
    return (gather_rows(rest_uv, e[:, 1]) - gather_rows(rest_uv, e[:, 0])).norm(dim=-1)


def opening_length_loss(
    rest_uv: torch.Tensor,
    edges: Sequence[torch.Tensor],
    least: torch.Tensor,
    most: torch.Tensor | None = None,
) -> torch.Tensor:
    """() the openings' shortfall and excess: Σ_k (max(0, least_k − L_k) / least_k)² + (max(0, L_k − most_k)
    / most_k)² [-] over the openings k, L_k the rest length of ``edges[k]`` (`rest_loop_length`) at
    ``rest_uv`` (V, 2) [m], ``least`` (K,) [m] the shortest length the scan allows (`scan_loop_length` less a
    tolerance), ``most`` (K,) [m] the longest (inf: none; None: none for any; an opening held at the
    template's has both its length). 0 with no openings."""
    if len(edges) != least.shape[0]:
        raise ValueError(f"{len(edges)} openings but {least.shape[0]} lengths")
    if most is not None and most.shape != least.shape:
        raise ValueError(f"{least.shape[0]} shortest lengths but {tuple(most.shape)} longest")
    if not edges:
        return rest_uv.sum() * 0.0
    lengths = torch.stack([rest_loop_length(rest_uv, e) for e in edges])
    least = least.to(lengths)
    loss = ((least - lengths).clamp(min=0) / least).square().sum()
    if most is not None:
        most = most.to(lengths)
        bounded = torch.isfinite(most)
        excess = (lengths[bounded] - most[bounded]).clamp(min=0) / most[bounded]
        loss = loss + excess.square().sum()
    return loss


def rest_loop_panels(garment: GarmentMesh, edges: torch.Tensor) -> torch.Tensor:
    """(L,) int64 the panel of each of an opening's rest ``edges`` (`rest_loop_edges`), numbered 0, 1, …
    in the order the panels first appear along the opening."""
    panel = garment.vert_panel[edges[:, 0].to(garment.vert_panel.device)].cpu()
    order = list(dict.fromkeys(panel.tolist()))
    return torch.tensor([order.index(p) for p in panel.tolist()], dtype=torch.int64)


def rest_loop_shares(rest_uv: torch.Tensor, edges: torch.Tensor, panels: torch.Tensor) -> torch.Tensor:
    """(P,) [-] the share of each panel in an opening's rest length: its ``edges``' (L, 2) lengths at
    ``rest_uv`` (V, 2) [m] summed per panel (``panels`` (L,), `rest_loop_panels`), over the whole."""
    lengths = _edge_lengths(rest_uv, edges)
    count = int(panels.max()) + 1
    per_panel = lengths.new_zeros(count).index_add(0, panels.to(rest_uv.device), lengths)
    return per_panel / per_panel.sum()


def opening_split_loss(
    rest_uv: torch.Tensor,
    edges: Sequence[torch.Tensor],
    panels: Sequence[torch.Tensor],
    shares: Sequence[torch.Tensor],
) -> torch.Tensor:
    """() how far the panels' split of each opening moved: Σ_k Σ_p (s_kp − ``shares[k][p]``)² [-], s_kp
    the share of panel p in opening k's rest length at ``rest_uv`` (V, 2) [m] (`rest_loop_shares` of
    ``edges[k]`` and ``panels[k]``), ``shares`` the template's. 0 with no openings.

    Why: a scan shows a hem's whole length (`opening_length_loss` holds it) but not where its seams are,
    so while the length is held the fit may move hem from one panel to another unseen. It did, on the
    dresses: 4-5 cm from the back skirt panel to the front on a ring-captured dress and on Newton's
    (docs/BENCHMARKS.md, "The hem's split and lopsided skirt panels"). Where the scan cannot tell, the
    template's split stands. The tops' configs hold it; the dress's symmetric skirt panels
    (``tie_symmetric``) took the drift there.
    """
    if not len(edges) == len(panels) == len(shares):
        raise ValueError(f"{len(edges)} openings, {len(panels)} panel lists and {len(shares)} share lists")
    total = rest_uv.sum() * 0.0
    for e, p, share in zip(edges, panels, shares, strict=True):
        total = total + (rest_loop_shares(rest_uv, e, p) - share.to(rest_uv)).square().sum()
    return total
