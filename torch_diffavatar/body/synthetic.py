"""Synthetic scans for tests and demos: random Anny bodies sampled as noisy, holey point clouds,
optionally under a stand-in garment layer (an outward offset of the body, not a simulated drape).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from torch_diffavatar.body.geometry import vertex_normals
from torch_diffavatar.body.model import POSE_BONES, BodyModel
from torch_diffavatar.body.parts import PART_NAMES

PART_INDEX = {name: i for i, name in enumerate(PART_NAMES)}

# Body parts whose surface the stand-in layer of each garment type covers (exactly; segmentation only
# knows the wider `segment.GARMENT_REGIONS`).
GARMENT_PARTS: dict[str, tuple[str, ...]] = {
    "dress": ("torso", "hips", "thigh.L", "thigh.R"),
    "shirt": ("torso", "hips", "upperarm.L", "upperarm.R", "forearm.L", "forearm.R"),
    "tshirt": ("torso", "hips", "upperarm.L", "upperarm.R"),
    "polo": ("torso", "hips", "upperarm.L", "upperarm.R"),
    "skirt": ("hips", "thigh.L", "thigh.R"),
    "pants": ("hips", "thigh.L", "thigh.R", "shin.L", "shin.R"),
}


def random_phenotypes(generator: torch.Generator, batch_size: int = 1) -> torch.Tensor:
    """(B, 6) plausible adult phenotypes (gender, age, muscle, weight, height, proportions), float64.

    Age stays in [0.45, 0.85] (adults); the others are uniform in [0.15, 0.85].
    """
    lo = torch.tensor([0.15, 0.45, 0.15, 0.15, 0.15, 0.15], dtype=torch.float64)
    hi = torch.tensor([0.85, 0.85, 0.85, 0.85, 0.85, 0.85], dtype=torch.float64)
    return lo + (hi - lo) * torch.rand(batch_size, 6, generator=generator, dtype=torch.float64)


# Typical amplitude [rad] of a random plausible pose, per bone (uniform in ±amplitude per axis).
_POSE_AMPLITUDE = {
    "spine": 0.08,
    "neck": 0.1,
    "head": 0.2,
    "clavicle": 0.08,
    "shoulder01": 0.1,
    "upperarm01": 0.35,
    "lowerarm01": 0.35,
    "wrist": 0.3,
    "upperleg01": 0.25,
    "lowerleg01": 0.0,
    "foot": 0.2,
}


def random_pose(generator: torch.Generator, bones: tuple[str, ...] = POSE_BONES) -> torch.Tensor:
    """(1, K, 3) float64 random plausible pose: small per-axis rotations, knees bent 0–0.4 rad."""
    pose = torch.zeros(1, len(bones), 3, dtype=torch.float64)
    for k, bone in enumerate(bones):
        amp = next(a for prefix, a in _POSE_AMPLITUDE.items() if bone.startswith(prefix))
        pose[0, k] = (2 * torch.rand(3, generator=generator, dtype=torch.float64) - 1) * amp
        if bone.startswith("lowerleg01"):
            pose[0, k, 0] = 0.4 * torch.rand((), generator=generator, dtype=torch.float64)
    return pose


def sample_surface(
    vertices: np.ndarray, faces: np.ndarray, count: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Uniform area-weighted surface samples.

    Args:
        vertices: (V, 3) [m]; faces: (F, 3) int.
        count: number of samples.

    Returns:
        points (count, 3) [m], face index (count,), barycentric weights (count, 3).
    """
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    face = rng.choice(len(faces), size=count, p=area / area.sum())
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    bary = np.stack([1 - u - v, u, v], axis=1)
    points = np.einsum("nk,nkd->nd", bary, tri[face])
    return points, face, bary


def hole_mask(
    points: np.ndarray, fraction: float, rng: np.random.Generator, radius: float = 0.08
) -> np.ndarray:
    """(N,) bool mask of points to keep after cutting ~``fraction`` of them away in round holes.

    Holes are balls of ``radius`` [m] around random sample points, added until the fraction is reached.
    """
    keep = np.ones(len(points), dtype=bool)
    target = int(round(fraction * len(points)))
    while (~keep).sum() < target:
        centre = points[rng.integers(len(points))]
        inside = np.linalg.norm(points - centre, axis=1) < radius
        room = target - (~keep).sum()
        new = np.flatnonzero(inside & keep)[:room]
        keep[new] = False
    return keep


@dataclass
class SyntheticScan:
    """A synthetic scan and its ground truth.

    Attributes:
        points: (N, 3) float64 noisy scan points [m], world frame.
        labels: (N,) int64, 1 for garment points, 0 for skin.
        colors: (N, 3) uint8 RGB (garment blue-ish, skin tan, both with noise).
        body_vertices: (Vb, 3) float64 ground-truth body [m].
        phenotypes: (1, 6) and pose (1, K, 3): ground-truth body parameters.
        height: ground-truth standing height [m].
        layer_vertices: (Vb, 3) noise-free outer surface [m] (the garment layer where covered, else the body).
        covered: (Vb,) bool, body vertices under the garment layer.
    """

    points: np.ndarray
    labels: np.ndarray
    colors: np.ndarray
    body_vertices: np.ndarray
    phenotypes: torch.Tensor
    pose: torch.Tensor
    height: float
    layer_vertices: np.ndarray
    covered: np.ndarray


def garment_offset(
    vertices: np.ndarray,
    covered: np.ndarray,
    joints_y: dict[str, float],
    rng: np.random.Generator,
    flare: bool,
) -> np.ndarray:
    """(V,) outward offset [m] of a stand-in garment layer: 1–4 cm, smoothly varying, 0 where uncovered.

    The offset is a sum of a few low-frequency sinusoids of the position mapped into [0.01, 0.04] m; with
    ``flare`` it grows linearly below the hips (a skirt flare), up to 4 cm more at the knees.
    """
    freq = rng.normal(size=(3, 3)) * 6.0
    phase = rng.random(3) * 2 * np.pi
    wave = np.sin(vertices @ freq.T + phase).mean(1)  # (V,) in [-1, 1]
    offset = 0.025 + 0.015 * wave
    if flare:
        hip, knee = joints_y["hip"], joints_y["knee"]
        t = np.clip((hip - vertices[:, 1]) / max(hip - knee, 1e-6), 0.0, 1.0)
        offset = offset + 0.04 * t
    return np.where(covered, offset, 0.0)


def make_scan(
    anny_model,
    seed: int,
    *,
    point_count: int = 20000,
    noise: float = 0.01,
    hole_fraction: float = 0.2,
    garment: str | None = None,
) -> SyntheticScan:
    """A random Anny body (random phenotypes and plausible pose) sampled as a noisy, holey point cloud.

    Args:
        anny_model: a model from `load_anny` (not modified).
        seed: seed for everything random.
        point_count: points sampled before the holes are cut.
        noise: standard deviation [m] of the isotropic Gaussian noise added to each coordinate.
        hole_fraction: fraction of the points removed in round holes.
        garment: optional key of `GARMENT_PARTS`. The covered parts are replaced by a stand-in cloth layer
            (the body offset outward along its normals by 1–4 cm, see `garment_offset`; skirts and dresses
            flare). This is a stand-in for a simulated drape, not one.

    Returns:
        a `SyntheticScan` (world frame, feet near y = 0).
    """
    gen = torch.Generator().manual_seed(seed)
    rng = np.random.default_rng(seed)
    body = BodyModel(anny_model=anny_model, dtype=torch.float64)
    phen = random_phenotypes(gen)
    pose = random_pose(gen, body.pose_bones)
    with torch.no_grad():
        out = body(phenotypes=phen, pose=pose)
        height = float(body.standing_height(phen)[0])
    verts = out.vertices[0]
    lift = -float(verts[:, 1].min())
    verts = verts + verts.new_tensor([0.0, lift, 0.0])
    faces = out.faces
    v_np, f_np = verts.numpy(), faces.numpy()
    layer = v_np.copy()
    if garment is not None:
        if garment not in GARMENT_PARTS:
            raise ValueError(f"unknown garment {garment!r}; known: {sorted(GARMENT_PARTS)}")
        covered = np.isin(body.vertex_parts.numpy(), [PART_INDEX[p] for p in GARMENT_PARTS[garment]])
        labels_of = anny_model.bone_labels.index
        joints = out.joints[0].numpy() + np.array([0.0, lift, 0.0])
        joints_y = {
            "hip": float(joints[labels_of("upperleg01.L"), 1]),
            "knee": float(joints[labels_of("lowerleg01.L"), 1]),
        }
        off = garment_offset(v_np, covered, joints_y, rng, flare=garment in ("dress", "skirt"))
        layer = v_np + off[:, None] * vertex_normals(verts, faces).numpy()
    else:
        covered = np.zeros(len(v_np), dtype=bool)
    points, face, bary = sample_surface(layer, f_np, point_count, rng)
    # A sample is garment when the majority of its triangle's vertices are covered.
    labels = (covered[f_np[face]].sum(1) >= 2).astype(np.int64)
    keep = hole_mask(points, hole_fraction, rng)
    points, labels = points[keep], labels[keep]
    points = points + rng.normal(scale=noise, size=points.shape)
    skin, cloth = np.array([205, 160, 130]), np.array([40, 70, 160])
    colors = np.where(labels[:, None] == 1, cloth, skin) + rng.normal(scale=12.0, size=points.shape)
    return SyntheticScan(
        points=points,
        labels=labels,
        colors=np.clip(colors, 0, 255).astype(np.uint8),
        body_vertices=v_np,
        phenotypes=phen,
        pose=pose,
        height=height,
        layer_vertices=layer,
        covered=covered,
    )
