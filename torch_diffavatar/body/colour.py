"""Colour for the garment segmentation (issue #29 item 3): colour models learned from the geometric
prior's confident points, and a graph cut over the scan's neighbour graph.

`segment.segment_garment` labels the garment from geometry (the offset of each point from the fitted
body, and the body parts the garment may cover). Geometry alone cannot tell a garment from another
garment beside it (a T-shirt from the trousers it hangs over: both stand off the body), nor from skin
where the body fit is off (forearms and hands). Colour can, when the colours differ. Here:

1. colours go to CIE Lab (`rgb_to_lab`), where distances are closer to perceived ones than in RGB;
2. a Gaussian mixture (`GaussianMixture`, a few full-covariance components fitted by EM) models the
   garment's colours from confident *seed* points (standing off the body over the garment's core, e.g.
   a top's torso above the waist), another models everything else's colours (skin, other garments)
   from the points outside the garment's region and those lying on the body (tight trousers under a
   top lie there too, and only weaken the evidence);
3. when the two models do not tell the seeds from the points outside the garment's region
   (`ColourModel.separability`, a balanced accuracy below ``min_separability``: a garment the colour
   of the skin, or of another garment seen beyond its region) the colour is not used and the
   segmentation stays as it was without these models;
4. else each point's unary evidence is the geometric evidence plus the colours' log-likelihood ratio,
   and the labels are the minimum cut (`graph_cut`, Boykov & Jolly 2001, "Interactive graph cuts";
   the colour models re-learned from its labels once, as in GrabCut, Rother et al. 2004) of that
   evidence and a contrast-sensitive Potts term over the k-nearest-neighbour graph: neighbours of
   similar colour pay to differ.

Limitations: one colour model per garment, so a print or stripes of a skin-like colour weakens the
evidence there; the seeds come from the geometric prior, so a garment the prior misses entirely cannot
be recovered by colour.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# sRGB D65 -> XYZ (IEC 61966-2-1), and the D65 white point
_RGB_TO_XYZ = np.array(
    [[0.4124564, 0.3575761, 0.1804375], [0.2126729, 0.7151522, 0.0721750], [0.0193339, 0.1191920, 0.9503041]]
)
_WHITE = np.array([0.95047, 1.0, 1.08883])


def rgb_to_lab(colors: np.ndarray) -> np.ndarray:
    """(N, 3) float64 CIE L*a*b* (D65) of (N, 3) uint8 sRGB colours (L in [0, 100])."""
    c = np.asarray(colors, dtype=np.float64) / 255.0
    linear = np.where(c > 0.04045, ((c + 0.055) / 1.055) ** 2.4, c / 12.92)
    xyz = linear @ _RGB_TO_XYZ.T / _WHITE
    eps = (6.0 / 29.0) ** 3
    f = np.where(xyz > eps, np.cbrt(xyz), xyz / (3.0 * (6.0 / 29.0) ** 2) + 4.0 / 29.0)
    return np.stack([116.0 * f[:, 1] - 16.0, 500.0 * (f[:, 0] - f[:, 1]), 200.0 * (f[:, 1] - f[:, 2])], 1)


@dataclass
class GaussianMixture:
    """A Gaussian mixture in colour space.

    Attributes:
        weights: (K,) mixing weights (sum 1); means: (K, 3); covariances: (K, 3, 3), each with at least
            ``min_variance`` on its diagonal (the colour noise floor, in Lab units squared).
    """

    weights: np.ndarray
    means: np.ndarray
    covariances: np.ndarray

    @classmethod
    def fit(
        cls,
        x: np.ndarray,
        components: int = 3,
        *,
        iterations: int = 30,
        min_variance: float = 4.0,
        max_points: int = 5000,
        seed: int = 0,
    ) -> GaussianMixture:
        """EM on the (N, 3) samples ``x`` (a seeded subset of ``max_points`` when more), started from
        k-means++-like picks; ``components`` is lowered to what the samples support."""
        rng = np.random.default_rng(seed)
        if len(x) > max_points:
            x = x[rng.choice(len(x), max_points, replace=False)]
        k = max(1, min(components, len(x) // 20))
        means = x[[rng.integers(len(x))]]
        for _ in range(k - 1):  # k-means++ picks: by squared distance to the nearest pick
            d2 = ((x[:, None, :] - means[None]) ** 2).sum(-1).min(1)
            if d2.sum() <= 0:
                break
            means = np.concatenate([means, x[[rng.choice(len(x), p=d2 / d2.sum())]]])
        k = len(means)
        gmm = cls(np.full(k, 1.0 / k), means, np.tile(np.cov(x.T) + min_variance * np.eye(3), (k, 1, 1)))
        for _ in range(iterations):
            log_r = gmm._component_log_density(x)  # (N, K)
            log_r -= _logsumexp(log_r)[:, None]
            r = np.exp(log_r)
            nk = r.sum(0) + 1e-9
            gmm.weights = nk / nk.sum()
            gmm.means = (r.T @ x) / nk[:, None]
            diff = x[:, None, :] - gmm.means[None]  # (N, K, 3)
            gmm.covariances = np.einsum("nk,nki,nkj->kij", r, diff, diff) / nk[:, None, None]
            gmm.covariances += min_variance * np.eye(3)
        return gmm

    def _component_log_density(self, x: np.ndarray) -> np.ndarray:
        """(N, K) log(weight_k · N(x | mean_k, cov_k))."""
        chol = np.linalg.cholesky(self.covariances)  # (K, 3, 3)
        diff = x[:, None, :] - self.means[None]  # (N, K, 3)
        z = np.linalg.solve(chol[None], diff[..., None])[..., 0]
        log_det = 2.0 * np.log(np.diagonal(chol, axis1=1, axis2=2)).sum(1)
        return np.log(self.weights) - 0.5 * ((z**2).sum(-1) + log_det + 3.0 * np.log(2.0 * np.pi))

    def log_density(self, x: np.ndarray) -> np.ndarray:
        """(N,) log density of the (N, 3) samples ``x``."""
        return _logsumexp(self._component_log_density(x))


def _logsumexp(a: np.ndarray) -> np.ndarray:
    m = a.max(1)
    return m + np.log(np.exp(a - m[:, None]).sum(1))


@dataclass
class ColourModel:
    """Garment and not-garment colour mixtures (Lab) and how well they tell their training points apart.

    Attributes:
        garment, other: `GaussianMixture`s; separability: balanced accuracy of the sign of
            `log_ratio` on the training points (0.5: no better than chance, 1: perfect).
    """

    garment: GaussianMixture
    other: GaussianMixture
    separability: float

    @classmethod
    def fit(
        cls,
        lab: np.ndarray,
        garment: np.ndarray,
        other: np.ndarray,
        components: int = 3,
        *,
        not_garment: np.ndarray | None = None,
    ) -> ColourModel:
        """From the (N, 3) Lab colours and the (N,) bool masks of the garment's and the others' points;
        the separability is measured on the garment's points against ``not_garment`` (N,) bool (default
        ``other``): points sure not to be the garment, when ``other`` may hold some of it."""
        model = cls(
            GaussianMixture.fit(lab[garment], components, seed=1),
            GaussianMixture.fit(lab[other], components, seed=2),
            0.0,
        )
        g_ok = (model.log_ratio(lab[garment]) > 0).mean()
        o_ok = (model.log_ratio(lab[other if not_garment is None else not_garment]) < 0).mean()
        model.separability = float(0.5 * (g_ok + o_ok))
        return model

    def log_ratio(self, lab: np.ndarray) -> np.ndarray:
        """(N,) log p(colour | garment) − log p(colour | other) of the (N, 3) Lab colours."""
        return self.garment.log_density(lab) - self.other.log_density(lab)


def knn_edges(nbr: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The undirected edges (i, j), i < j, of the k-nearest-neighbour lists ``nbr`` (N, >k) (column 0:
    the point itself), each once: two (E,) int64 arrays."""
    n = len(nbr)
    k = min(k, nbr.shape[1] - 1)
    i = np.repeat(np.arange(n), k)
    j = nbr[:, 1 : k + 1].reshape(-1)
    a, b = np.minimum(i, j), np.maximum(i, j)
    keep = a != b
    pairs = np.unique(np.stack([a[keep], b[keep]], 1), axis=0)
    return pairs[:, 0], pairs[:, 1]


def graph_cut(
    evidence: np.ndarray,
    allowed: np.ndarray,
    edge_i: np.ndarray,
    edge_j: np.ndarray,
    edge_weight: np.ndarray,
    *,
    scale: float = 100.0,
) -> np.ndarray:
    """Binary labels minimising Σ unary + Σ Potts over a graph, by a minimum s–t cut
    (`scipy.sparse.csgraph.maximum_flow`, Dinic's algorithm, integer capacities).

    Args:
        evidence: (N,) log-odds of label True per point: labelling a point False costs max(evidence, 0),
            True costs max(−evidence, 0).
        allowed: (N,) bool, points that may be True (the others are False whatever their evidence).
        edge_i, edge_j: (E,) the graph's undirected edges; edge_weight: (E,) ≥ 0 cost of cutting each.
        scale: capacities are rounded after multiplying by this.

    Returns:
        (N,) bool labels.
    """
    import scipy.sparse as sp
    from scipy.sparse.csgraph import breadth_first_order, maximum_flow

    n = len(evidence)
    source, sink = n, n + 1
    big = int(scale * (np.abs(evidence).max(initial=0.0) + edge_weight.sum() + 1.0))
    big = min(big, 2**30)
    to_true = np.round(scale * np.clip(evidence, 0.0, None)).astype(np.int64)  # cut: labelled False
    to_false = np.round(scale * np.clip(-evidence, 0.0, None)).astype(np.int64)
    to_false[~allowed] = big
    pair = np.round(scale * edge_weight).astype(np.int64)
    nodes = np.arange(n)
    rows = np.concatenate([np.full(n, source), nodes, edge_i, edge_j])
    cols = np.concatenate([nodes, np.full(n, sink), edge_j, edge_i])
    caps = np.concatenate([to_true, to_false, pair, pair])
    keep = caps > 0
    graph = sp.csr_matrix((caps[keep].astype(np.int32), (rows[keep], cols[keep])), shape=(n + 2, n + 2))
    graph.sum_duplicates()
    flow = maximum_flow(graph, source, sink, method="dinic").flow
    residual = (graph - flow).tocsr()
    residual.data = np.where(residual.data > 0, 1, 0)
    residual.eliminate_zeros()
    reached = breadth_first_order(residual, source, directed=True, return_predecessors=False)
    labels = np.zeros(n + 2, dtype=bool)
    labels[reached] = True
    return labels[:n] & allowed


@dataclass
class ColourLabels:
    """Result of `colour_labels`.

    Attributes:
        labels: (N,) bool garment labels.
        log_ratio: (N,) the colours' log-likelihood ratio (garment vs other) under the last model.
        separability: the first colour model's `ColourModel.separability` (seeds against the points
            outside the garment's region).
    """

    labels: np.ndarray
    log_ratio: np.ndarray
    separability: float


def colour_labels(
    colors: np.ndarray,
    evidence: np.ndarray,
    region: np.ndarray,
    seeds: np.ndarray,
    nbr: np.ndarray,
    *,
    min_separability: float = 0.9,
    min_seeds: int = 50,
    smoothness: float = 1.0,
    neighbors: int = 8,
    rounds: int = 2,
) -> ColourLabels | None:
    """Garment labels from geometry and colour (see the module docstring), or None when the colours do
    not tell the garment from the rest (then the caller keeps its geometric labels).

    Args:
        colors: (N, 3) uint8 RGB.
        evidence: (N,) geometric log-odds of garment (the offset's, `segment.segment_garment`).
        region: (N,) bool, points the garment may cover (the others are never garment).
        seeds: (N,) bool, confident garment points (the garment's colour model is learned from them).
        nbr: (N, >neighbors) k-nearest-neighbour indices, column 0 the point itself.
        min_separability: the colour is used only when its models reach this balanced accuracy.
        min_seeds: fewer seed points (or fewer other points): None.
        smoothness: weight of the Potts term, in units of the evidence, between neighbours of equal colour.
        neighbors: neighbours per point in the graph.
        rounds: graph cuts; after each but the last, the colour models are learned again from its labels.
    """
    lab = rgb_to_lab(colors)
    geometric = np.clip(evidence, -3.0, 3.0)
    # Not the garment for sure: outside its region. Likely not: lying on the body (a tight garment of
    # another kind, e.g. trousers under a top, lies there too: it only weakens the colour's evidence).
    outside = ~region & ~seeds
    other = outside | ((geometric < -1.0) & ~seeds)
    if seeds.sum() < min_seeds or outside.sum() < min_seeds:
        return None
    edge_i, edge_j = knn_edges(nbr, neighbors)
    contrast = ((lab[edge_i] - lab[edge_j]) ** 2).sum(1)
    weight = smoothness * np.exp(-contrast / (2.0 * max(float(contrast.mean()), 1e-6)))
    model = ColourModel.fit(lab, seeds, other, not_garment=outside)
    if model.separability < min_separability:  # the garment's colours are also found off it
        return None
    separability = model.separability
    for round_ in range(rounds):
        log_ratio = model.log_ratio(lab)
        labels = graph_cut(geometric + np.clip(log_ratio, -6.0, 6.0), region, edge_i, edge_j, weight)
        if labels.sum() < min_seeds or (~labels).sum() < min_seeds:
            return None
        if round_ + 1 < rounds:  # learned again from this cut
            model = ColourModel.fit(lab, labels, ~labels)
    return ColourLabels(labels=labels, log_ratio=log_ratio, separability=separability)
