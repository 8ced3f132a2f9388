"""`BodyModel`: a learnable Anny body (shape, pose, placement) in our world frame.

World frame: Y up, metres, facing +Z (see `body.frames`). Pose is per-bone axis-angle for the major bones
(`POSE_BONES`), in Anny's ``local-ref`` parameterization: zero is the reference A-pose and each rotation is
about the bone's head, in Anny's world-aligned axes (X = body's left, Y = backward, Z = up). Fingers, toes
and eyes stay at the reference.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import roma
import torch
from torch import nn

from torch_diffavatar.body.anny_model import load_anny
from torch_diffavatar.body.frames import anny_to_world
from torch_diffavatar.body.parts import PART_NAMES, vertex_parts
from torch_diffavatar.errors import InputError

_BODY = (0.35, 0.35, 0.35)
# Major bones that are posed, with symmetric per-axis soft limits [rad] in Anny's world-aligned axes
# (X = lateral, Y = front/back, Z = vertical), unless a (lo, hi) pair is given.
_LIMITS: dict[str, tuple] = {
    "spine05": _BODY,
    "spine04": _BODY,
    "spine03": _BODY,
    "spine02": _BODY,
    "spine01": _BODY,
    "neck01": (0.4, 0.4, 0.5),
    "head": (0.5, 0.4, 0.6),
    "clavicle.L": (0.3, 0.3, 0.3),
    "clavicle.R": (0.3, 0.3, 0.3),
    "shoulder01.L": (0.4, 0.4, 0.4),
    "shoulder01.R": (0.4, 0.4, 0.4),
    "upperarm01.L": (1.6, 1.6, 1.6),
    "upperarm01.R": (1.6, 1.6, 1.6),
    "lowerarm01.L": (1.5, 1.5, 1.5),
    "lowerarm01.R": (1.5, 1.5, 1.5),
    "wrist.L": (0.9, 0.9, 0.9),
    "wrist.R": (0.9, 0.9, 0.9),
    "upperleg01.L": (1.3, 0.8, 0.8),
    "upperleg01.R": (1.3, 0.8, 0.8),
    # Knee flexion is a positive rotation about X (the shin swings backward, to Anny's +Y).
    "lowerleg01.L": ((-0.1, 2.4), 0.25, 0.25),
    "lowerleg01.R": ((-0.1, 2.4), 0.25, 0.25),
    "foot.L": (0.7, 0.5, 0.5),
    "foot.R": (0.7, 0.5, 0.5),
}
POSE_BONES: tuple[str, ...] = tuple(_LIMITS)


def pose_from_bones(bones: dict, context: str = "pose") -> torch.Tensor:
    """(K, 3) float64 axis-angles [rad] of the `POSE_BONES` from ``{bone: [rx, ry, rz]}``; the bones not
    named stay at the A-pose (zero). Raises `InputError`, prefixed with ``context``, for anything else."""
    if not isinstance(bones, dict):
        raise InputError(f"{context}: a pose is an object {{bone: [rx, ry, rz]}}, got {type(bones).__name__}")
    unknown = sorted(set(bones) - set(POSE_BONES))
    if unknown:
        raise InputError(f"{context}: unknown bones {unknown}; posable: {list(POSE_BONES)}")
    pose = torch.zeros(len(POSE_BONES), 3, dtype=torch.float64)
    for bone, value in bones.items():
        try:
            row = torch.tensor([float(v) for v in value], dtype=torch.float64)
        except (TypeError, ValueError) as exc:
            raise InputError(f"{context}: {bone!r} must be three numbers [rad], got {value!r}") from exc
        if row.shape != (3,):
            raise InputError(f"{context}: {bone!r} must be three numbers [rad], got {value!r}")
        pose[POSE_BONES.index(bone)] = row
    return pose


def pose_limits(bones: tuple[str, ...] = POSE_BONES) -> tuple[torch.Tensor, torch.Tensor]:
    """(lower (K, 3), upper (K, 3)) float64 soft joint limits [rad] of ``bones`` (see `_LIMITS`)."""
    lo, hi = [], []
    for bone in bones:
        axes = _LIMITS[bone]
        lo.append([a[0] if isinstance(a, tuple) else -a for a in axes])
        hi.append([a[1] if isinstance(a, tuple) else a for a in axes])
    return torch.tensor(lo, dtype=torch.float64), torch.tensor(hi, dtype=torch.float64)


@dataclass
class BodyOutput:
    """Named outputs of `BodyModel.forward`, world frame (Y up, facing +Z) [m].

    Attributes:
        vertices: (B, Vb, 3) posed body vertices.
        faces: (Fb, 3) int64 triangles of one closed watertight mesh, outward-facing.
        joints: (B, J, 3) bone head positions (J = 104, in ``anny_model.bone_labels`` order).
    """

    vertices: torch.Tensor
    faces: torch.Tensor
    joints: torch.Tensor


def _module_dtype(anny_model) -> torch.dtype:
    return anny_model.template_vertices.dtype


class BodyModel(nn.Module):
    """Anny with learnable shape, pose, global rotation, translation and scale (paper §3.1, §4.1).

    Parameters (all ``nn.Parameter``; freeze what you do not fit with ``requires_grad_(False)``):
        phenotype_logits: (B, P) logits of the phenotypes (``anny_model.phenotype_labels``: gender, age,
            muscle, weight, height, proportions); the phenotypes are their sigmoid, so they stay in (0, 1).
        pose: (B, K, 3) axis-angle [rad] of the `POSE_BONES`, zero = A-pose.
        global_orient: (B, 3) axis-angle [rad] of a rotation about the world origin, applied after the
            Anny→world conversion.
        translation: (B, 3) [m] world translation (the pelvis is at the origin when it is zero, so the
            feet are about 0.87 m below the world's floor: `stand_on_floor` puts them on y = 0, the frame
            of the placement, the scans and the assets).
        log_scale: (B,) log of a uniform scale about the world origin.
        local_changes: (B, L) Anny local changes (only when the given model was built with them and
            ``local_changes=True``; the project's shared configuration has none).

    Forward: ``world = scale · R(global_orient) · anny_to_world(anny(pose, phenotypes)) + translation``.

    Limitations: Anny's skinning runs on CPU through warp on this machine; rotations of the posed bones
    are in Anny's world-aligned axes, not in anatomical joint axes, so the joint limits are per-axis
    boxes in those axes (see `_LIMITS`).
    """

    def __init__(
        self,
        anny_model=None,
        *,
        batch_size: int = 1,
        dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
        pose_bones: tuple[str, ...] = POSE_BONES,
        local_changes: bool = False,
    ):
        super().__init__()
        if anny_model is None:
            anny_model = load_anny(dtype=dtype or torch.float32, device=device)
        elif (dtype is not None and dtype != _module_dtype(anny_model)) or device is not None:
            anny_model = copy.deepcopy(anny_model).to(device=device, dtype=dtype)  # keep the caller's intact
        self.anny = anny_model
        dtype = _module_dtype(anny_model)
        device = anny_model.template_vertices.device
        unknown = [b for b in pose_bones if b not in anny_model.bone_labels]
        if unknown:
            raise ValueError(f"pose_bones not in the Anny rig: {unknown}")
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.pose_bones = tuple(pose_bones)
        self.phenotype_labels = tuple(anny_model.phenotype_labels)
        kw = dict(dtype=dtype, device=device)
        self.register_buffer(
            "pose_bone_indices",
            torch.tensor([anny_model.bone_labels.index(b) for b in pose_bones], device=device),
        )
        self.register_buffer("faces", anny_model.faces.to(device=device, dtype=torch.int64).clone())
        lo, hi = pose_limits(self.pose_bones)
        self.register_buffer("pose_lower", lo.to(**kw))
        self.register_buffer("pose_upper", hi.to(**kw))
        self.register_buffer("vertex_parts", vertex_parts(anny_model).to(device))
        B, K, P = batch_size, len(pose_bones), len(self.phenotype_labels)
        self.phenotype_logits = nn.Parameter(torch.zeros(B, P, **kw))
        self.pose = nn.Parameter(torch.zeros(B, K, 3, **kw))
        self.global_orient = nn.Parameter(torch.zeros(B, 3, **kw))
        self.translation = nn.Parameter(torch.zeros(B, 3, **kw))
        self.log_scale = nn.Parameter(torch.zeros(B, **kw))
        n_local = len(getattr(anny_model, "local_change_labels", ()))
        if local_changes and n_local == 0:
            raise ValueError("local_changes=True needs an Anny model built with local changes")
        self.local_changes = nn.Parameter(torch.zeros(B, n_local, **kw)) if local_changes else None

    @property
    def batch_size(self) -> int:
        return self.pose.shape[0]

    @property
    def phenotypes(self) -> torch.Tensor:
        """(B, P) phenotypes in (0, 1)."""
        return torch.sigmoid(self.phenotype_logits)

    @property
    def scale(self) -> torch.Tensor:
        """(B,) uniform scale."""
        return self.log_scale.exp()

    @torch.no_grad()
    def stand_on_floor(self) -> BodyModel:
        """Shift ``translation`` vertically so each body's lowest vertex lies on y = 0 (the world frame's
        floor, which `place_garment`, the scans and the assets assume). Returns ``self``, for
        ``BodyModel().stand_on_floor()``. Call it again after changing shape, pose or scale."""
        lowest = self().vertices[..., 1].amin(dim=1)  # (B,)
        self.translation[:, 1] -= lowest
        return self

    @torch.no_grad()
    def set_phenotypes(self, phenotypes: torch.Tensor | dict[str, float]) -> None:
        """Set phenotypes from a (B, P) tensor or a {label: value} dict (clamped to [1e-4, 1 − 1e-4])."""
        if isinstance(phenotypes, dict):
            unknown = set(phenotypes) - set(self.phenotype_labels)
            if unknown:
                raise ValueError(f"unknown phenotypes {sorted(unknown)}; known: {self.phenotype_labels}")
            values = self.phenotypes.clone()
            for name, value in phenotypes.items():
                values[:, self.phenotype_labels.index(name)] = float(value)
        else:
            values = torch.as_tensor(phenotypes, dtype=self.pose.dtype, device=self.pose.device)
            values = values.expand_as(self.phenotype_logits)
        self.phenotype_logits.copy_(torch.logit(values.clamp(1e-4, 1 - 1e-4)))

    def full_pose(self, pose: torch.Tensor) -> torch.Tensor:
        """(B, K, 3) axis-angle of the posed bones -> (B, 104, 4, 4) Anny ``local-ref`` delta transforms."""
        B = pose.shape[0]
        n_bones = len(self.anny.bone_labels)
        full = torch.eye(4, dtype=pose.dtype, device=pose.device).repeat(B, n_bones, 1, 1)
        full[:, self.pose_bone_indices, :3, :3] = roma.rotvec_to_rotmat(pose)
        return full

    def forward(
        self,
        phenotypes: torch.Tensor | None = None,
        pose: torch.Tensor | None = None,
        global_orient: torch.Tensor | None = None,
        translation: torch.Tensor | None = None,
        scale: torch.Tensor | None = None,
        local_changes: torch.Tensor | None = None,
    ) -> BodyOutput:
        """Pose and place the body. Each argument overrides the module's own parameter.

        Args:
            phenotypes: (B, P) in [0, 1] (not logits).
            pose: (B, K, 3) axis-angle [rad] of `pose_bones`.
            global_orient: (B, 3) axis-angle [rad], world frame.
            translation: (B, 3) [m], world frame.
            scale: (B,) uniform scale.
            local_changes: (B, L) Anny local changes (only with a model that has them).

        Returns:
            `BodyOutput` (world frame, [m]).
        """
        phen = self.phenotypes if phenotypes is None else phenotypes
        pose = self.pose if pose is None else pose
        rot = self.global_orient if global_orient is None else global_orient
        transl = self.translation if translation is None else translation
        scale = self.scale if scale is None else scale
        if local_changes is None and self.local_changes is not None:
            local_changes = self.local_changes
        out = self.anny(
            pose_parameters=self.full_pose(pose),
            phenotype_kwargs=phen,
            local_changes_kwargs=local_changes,
        )
        world_rot = roma.rotvec_to_rotmat(rot)  # (B, 3, 3)
        scale = scale.reshape(-1, 1, 1)

        def place(points):  # (B, N, 3) Anny frame -> world
            return scale * anny_to_world(points) @ world_rot.transpose(-1, -2) + transl[:, None]

        return BodyOutput(
            vertices=place(out["vertices"]),
            faces=self.faces,
            joints=place(out["bone_poses"][..., :3, 3]),
        )

    def standing_height(self, phenotypes: torch.Tensor | None = None) -> torch.Tensor:
        """(B,) height [m] of the body in its reference A-pose (top of head to sole), times the scale."""
        phen = self.phenotypes if phenotypes is None else phenotypes
        out = self.anny(phenotype_kwargs=phen)
        up = out["vertices"][..., 2]  # Anny is Z-up
        return (up.max(-1).values - up.min(-1).values) * self.scale

    def part_indices(self, *names: str) -> torch.Tensor:
        """(N,) int64 indices of the vertices whose dominant part is one of ``names`` (see `PART_NAMES`)."""
        unknown = [n for n in names if n not in PART_NAMES]
        if unknown:
            raise ValueError(f"unknown body parts {unknown}; known: {PART_NAMES}")
        ids = torch.tensor([PART_NAMES.index(n) for n in names], device=self.vertex_parts.device)
        return torch.nonzero(torch.isin(self.vertex_parts, ids)).flatten()

    @torch.no_grad()
    def pose_path(self, keys: int = 4, tol: float = 1e-3) -> BodyOutput | None:
        """The first body of the batch on its way from the A-pose to its own pose, for sewing a garment
        in the A-pose and then posing the body under it (`sim.forward_drape.sew_and_drape`'s ``body_path``).

        Args:
            keys: poses on the way: the pose scaled by 0, 1/keys, ..., (keys − 1)/keys (each bone turns
                about its own axis; shape, orientation and placement stay the body's).
            tol: a body whose every bone is within this of the A-pose [rad] has no path.

        Returns:
            `BodyOutput` with ``vertices`` (keys, Vb, 3) and ``joints`` (keys, J, 3) [m], the A-pose first
            and the body's own pose excluded; None when the body is in the A-pose.
        """
        if keys < 1:
            raise ValueError(f"keys must be >= 1, got {keys}")
        pose = self.pose[:1]
        if float(pose.abs().max()) <= tol:
            return None
        s = torch.arange(keys, dtype=pose.dtype, device=pose.device) / keys

        def rep(t):  # the first body's parameter, once per key
            return t[:1].repeat(keys, *([1] * (t.ndim - 1)))

        local = None if self.local_changes is None else rep(self.local_changes)
        return self(
            phenotypes=rep(self.phenotypes),
            pose=s[:, None, None] * pose,
            global_orient=rep(self.global_orient),
            translation=rep(self.translation),
            scale=rep(self.scale),
            local_changes=local,
        )

    def arm_joints(self, joints: torch.Tensor) -> dict[str, np.ndarray]:
        """Each arm's joints for `sim.placement.place_garment` (a body not in the A-pose).

        Args:
            joints: (J, 3) one body's `BodyOutput.joints` [m].

        Returns:
            ``{"left": (4, 3), "right": (4, 3)}`` float64 numpy: the shoulder joint, the elbow, the wrist
            and the middle of the hand (halfway to the middle finger's knuckle, where the fingers part).
        """
        labels = self.anny.bone_labels
        j = joints.detach().cpu().double().numpy()
        out = {}
        for name, s in (("left", "L"), ("right", "R")):
            shoulder, elbow, wrist, knuckle = (
                j[labels.index(f"{b}.{s}")] for b in ("upperarm01", "lowerarm01", "wrist", "finger3-1")
            )
            out[name] = np.stack([shoulder, elbow, wrist, 0.5 * (wrist + knuckle)])
        return out

    def upper_arm_angles(self, joints: torch.Tensor) -> dict[str, float]:
        """How far each upper arm stands out from the torso: the angle [degrees] between the shoulder
        joint → elbow and the torso's downward axis (``neck01`` → ``spine05`` joints). Anny's A-pose: 42°;
        0° hangs along the torso, 90° is level. The torso's axis, not world −Y, so a bent or turned body
        reads the same.

        Args:
            joints: (J, 3) one body's `BodyOutput.joints` [m].

        Returns:
            ``{"left": degrees, "right": degrees}``.
        """
        labels = self.anny.bone_labels
        j = joints.detach().cpu().double().numpy()
        down = j[labels.index("spine05")] - j[labels.index("neck01")]
        down = down / np.linalg.norm(down)
        out = {}
        for name, chain in self.arm_joints(joints).items():
            arm = chain[1] - chain[0]  # shoulder joint -> elbow
            cos = float(np.clip(arm @ down / np.linalg.norm(arm), -1.0, 1.0))
            out[name] = float(np.degrees(np.arccos(cos)))
        return out

    def waist_height(self, joints: torch.Tensor) -> float:
        """Height [m] (world Y) of the ``spine02`` joint: just above where skirts and trousers end at
        the waist (1.9-4.8 cm on eight Anny bodies, slim to heavy), and below the ribs.
        `body.segment.segment_garment` grows trousers' labels over the torso below it.

        Args:
            joints: (J, 3) one body's `BodyOutput.joints` [m].
        """
        return float(joints[self.anny.bone_labels.index("spine02"), 1])

    def parameters_dict(self) -> dict:
        """JSON-friendly copy of the fit variables (batch element lists)."""
        return {
            "phenotype_labels": list(self.phenotype_labels),
            "phenotypes": self.phenotypes.detach().cpu().tolist(),
            "pose_bones": list(self.pose_bones),
            "pose_axis_angle": self.pose.detach().cpu().tolist(),
            "global_orient_axis_angle": self.global_orient.detach().cpu().tolist(),
            "translation_m": self.translation.detach().cpu().tolist(),
            "scale": self.scale.detach().cpu().tolist(),
        }

    @torch.no_grad()
    def load_parameters_dict(self, params: dict) -> None:
        """Inverse of `parameters_dict` (batch size and pose bones must match)."""
        if list(params["pose_bones"]) != list(self.pose_bones):
            raise ValueError("pose_bones in the parameters do not match this BodyModel")
        kw = dict(dtype=self.pose.dtype, device=self.pose.device)
        self.set_phenotypes(torch.tensor(params["phenotypes"], **kw))
        self.pose.copy_(torch.tensor(params["pose_axis_angle"], **kw))
        self.global_orient.copy_(torch.tensor(params["global_orient_axis_angle"], **kw))
        self.translation.copy_(torch.tensor(params["translation_m"], **kw))
        self.log_scale.copy_(torch.tensor(params["scale"], **kw).log())
