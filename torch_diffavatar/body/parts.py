"""Body-part regions of the Anny mesh, derived from its skinning weights.

Anny ships only a coarse face segmentation (body/head/hands/feet), so finer regions (torso, upper arm,
forearm, thigh, shin, …) are obtained by summing each vertex's skinning weights over the bones of a part.
"""

from __future__ import annotations

import torch

# Part names, in the column order of `part_weights`.
PART_NAMES = (
    "head",
    "torso",
    "hips",
    "upperarm.L",
    "forearm.L",
    "hand.L",
    "upperarm.R",
    "forearm.R",
    "hand.R",
    "thigh.L",
    "shin.L",
    "foot.L",
    "thigh.R",
    "shin.R",
    "foot.R",
)


def bone_part(bone_label: str) -> str:
    """The body part (one of `PART_NAMES`) a bone of the Anny rig belongs to."""
    side = bone_label[-2:] if bone_label.endswith((".L", ".R")) else ""
    base = bone_label[:-2] if side else bone_label
    if base.startswith(("neck", "head", "eye")):
        return "head"
    if base.startswith(("spine", "clavicle", "shoulder")):
        return "torso"
    if base in ("root", "pelvis"):
        return "hips"
    if base.startswith("upperarm"):
        return "upperarm" + side
    if base.startswith("lowerarm"):
        return "forearm" + side
    if base.startswith(("wrist", "finger", "metacarpal")):
        return "hand" + side
    if base.startswith("upperleg"):
        return "thigh" + side
    if base.startswith("lowerleg"):
        return "shin" + side
    if base.startswith(("foot", "toe")):
        return "foot" + side
    raise ValueError(f"unknown Anny bone {bone_label!r}")


def part_weights(anny_model) -> torch.Tensor:
    """Soft part membership of every vertex: its skinning weights summed per part.

    Args:
        anny_model: a model from `load_anny`.

    Returns:
        (V, P) weights on the model's device/dtype, rows summing to 1, columns in `PART_NAMES` order.
    """
    bone_to_part = torch.tensor(
        [PART_NAMES.index(bone_part(label)) for label in anny_model.bone_labels],
        device=anny_model.vertex_bone_indices.device,
    )
    w = anny_model.vertex_bone_weights  # (V, K)
    parts = bone_to_part[anny_model.vertex_bone_indices]  # (V, K)
    out = torch.zeros(w.shape[0], len(PART_NAMES), dtype=w.dtype, device=w.device)
    out.scatter_add_(1, parts, w)
    return out / out.sum(1, keepdim=True).clamp_min(1e-12)


def vertex_parts(anny_model) -> torch.Tensor:
    """(V,) int64 index into `PART_NAMES` of each vertex's dominant part."""
    return part_weights(anny_model).argmax(1)
