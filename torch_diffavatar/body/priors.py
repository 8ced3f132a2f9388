"""Priors on the body pose: joint limits, a pull toward the A-pose, and a cheap self-penetration proxy.

Pure functions on tensors; `BodyModel` owns the bounds and vertex subsets they use.
"""

from __future__ import annotations

import torch


def joint_limit_penalty(pose: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor) -> torch.Tensor:
    """Soft joint limits: squared excess of each axis-angle component outside its bounds.

    Args:
        pose: (B, K, 3) per-bone axis-angle [rad] (Anny's world-aligned ``local-ref`` axes).
        lower, upper: (K, 3) bounds [rad] per bone and axis.

    Returns:
        (B,) penalty [rad²], zero when every component is inside its bounds.
    """
    excess = torch.relu(lower - pose) + torch.relu(pose - upper)  # (B, K, 3)
    return (excess**2).sum((-1, -2))


def pose_prior(pose: torch.Tensor, bone_weights: torch.Tensor | None = None) -> torch.Tensor:
    """Quadratic pull of the pose toward the reference A-pose (all axis-angles zero).

    Args:
        pose: (B, K, 3) per-bone axis-angle [rad].
        bone_weights: optional (K,) weight per bone (stiffer bones get larger weights).

    Returns:
        (B,) weighted sum of squared rotation angles [rad²].
    """
    sq = (pose**2).sum(-1)  # (B, K)
    if bone_weights is not None:
        sq = sq * bone_weights
    return sq.sum(-1)


def self_penetration_penalty(
    vertices: torch.Tensor, pairs: list[tuple[torch.Tensor, torch.Tensor]], margin: float = 0.01
) -> torch.Tensor:
    """Cheap self-penetration proxy: penalize vertices of different body parts closer than ``margin``.

    This is not an intersection test: it compares small, fixed vertex subsets of parts that must not
    touch (e.g. forearms/hands vs torso, left vs right leg) and penalizes ``relu(margin − d)²`` for every
    pair closer than the margin, which keeps limbs from sinking into the body during a fit.

    Args:
        vertices: (B, V, 3) body vertices [m].
        pairs: list of ``(idx_a (Na,), idx_b (Nb,))`` int64 vertex-index subsets to keep apart.
        margin: distance [m] below which a pair is penalized.

    Returns:
        (B,) penalty [m²].
    """
    total = vertices.new_zeros(vertices.shape[0])
    for idx_a, idx_b in pairs:
        d = torch.cdist(vertices[:, idx_a], vertices[:, idx_b])  # (B, Na, Nb)
        total = total + (torch.relu(margin - d) ** 2).sum((-1, -2))
    return total
