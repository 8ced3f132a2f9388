"""Body motions for `diffavatar animate`: keyframed poses (JSON) and a procedural walk cycle.

A motion is a function of time giving, for some of the `BodyModel.POSE_BONES`, an axis-angle rotation
**offset** [rad] composed on top of the asset's own (fitted) pose, ``R_bone(t) = R_offset(t) · R_asset``,
in Anny's world-aligned bone axes (X = the body's left, Y = backward, Z = up; see `body.model`), plus an
optional root translation offset [m] in our world frame (Y up, facing +Z). At zero offset the body is
the one the garment was draped on, so an animation starts from the drape at rest.

Keyframe JSON (``--motion keys.json``)::

    {"ease": "smooth",                       # or "linear": interpolation between keyframes
     "keyframes": [
        {"time_s": 0.0, "pose": {}},
        {"time_s": 1.0, "pose": {"upperarm01.L": [0.0, -0.6, 0.0]}, "translation_m": [0, 0, 0.05]},
        {"time_s": 2.0, "pose": {}}]}

Bones missing from a keyframe are at zero offset there. Between keyframes each bone's rotation is
slerped with the time fraction eased by smoothstep (zero velocity at keys) or
not; before the first / after the last keyframe the pose holds.

Why the walk is procedural: the walk cycle Anny ships (``anny/data/mpfb2/walkcycles/
crappy_experimental_female.json``, a Blender action of MakeHuman's rig) drives the arms and legs through
IK targets (``left_foot_ik``, ``left_knee_ik``, ``left_hand_ik`` …) and gives forward-kinematics
rotations only for the root, spine, neck, head and clavicles; Anny's rig has no IK solver, so that data
cannot move the legs. `walk_cycle` is a sinusoidal in-place (treadmill) walk instead: hip flexion,
knee flexion in the swing phase, counter-swinging arms and a little spine twist, with the amplitude
ramped in so the animation starts at rest.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import roma
import torch

from torch_diffavatar.body.model import POSE_BONES, pose_from_bones
from torch_diffavatar.errors import InputError, read_json_file

EASES = ("smooth", "linear")


@dataclass(frozen=True)
class Keyframe:
    """One key: ``pose`` maps bone -> (3,) axis-angle offset [rad]; ``translation`` (3,) [m]."""

    time: float
    pose: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)


class Motion:
    """Base class: ``offsets(times)`` -> pose offsets (T, K, 3) [rad] of ``bones`` and translation (T, 3)."""

    bones: tuple[str, ...] = POSE_BONES
    duration: float = 0.0

    def offsets(self, times: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        raise NotImplementedError


class KeyframeMotion(Motion):
    """Pose interpolation through keyframes (see the module docstring).

    Args:
        keyframes: at least one `Keyframe`, times strictly increasing [s].
        ease: ``"smooth"`` (smoothstep time fraction) or ``"linear"``.
    """

    def __init__(self, keyframes: list[Keyframe], *, ease: str = "smooth"):
        if ease not in EASES:
            raise InputError(f"motion ease must be one of {EASES}, got {ease!r}")
        if not keyframes:
            raise InputError("a keyframe motion needs at least one keyframe")
        times = [k.time for k in keyframes]
        if any(b <= a for a, b in zip(times, times[1:])) or times[0] < 0:
            raise InputError(f"keyframe times must be >= 0 and strictly increasing, got {times}")
        key_pose = torch.stack([pose_from_bones(k.pose, f"keyframe at {k.time} s") for k in keyframes])
        self.keyframes = list(keyframes)
        self.ease = ease
        self.duration = times[-1]
        self._times = torch.tensor(times, dtype=torch.float64)
        self._pose = key_pose  # (N, K, 3)
        self._transl = torch.tensor([k.translation for k in keyframes], dtype=torch.float64)  # (N, 3)

    def offsets(self, times: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """times: (T,) [s] -> pose offsets (T, K, 3) [rad], translation offsets (T, 3) [m] (float64)."""
        t = torch.as_tensor(times, dtype=torch.float64).clamp(float(self._times[0]), float(self._times[-1]))
        n = len(self._times)
        if n == 1:
            return self._pose[0].expand(len(t), -1, -1).clone(), self._transl[0].expand(len(t), -1).clone()
        seg = (torch.searchsorted(self._times, t, right=True) - 1).clamp(0, n - 2)  # (T,)
        t0, t1 = self._times[seg], self._times[seg + 1]
        s = (t - t0) / (t1 - t0)
        if self.ease == "smooth":
            s = s * s * (3 - 2 * s)
        a, b = self._pose[seg], self._pose[seg + 1]  # (T, K, 3)
        # slerp per bone: a, then the fraction s of the relative rotation b·a⁻¹ (about a fixed axis)
        rel = roma.rotvec_composition([b, roma.rotvec_inverse(a)])
        pose = roma.rotvec_composition([s[:, None, None] * rel, a])
        transl = self._transl[seg] + s[:, None] * (self._transl[seg + 1] - self._transl[seg])
        return pose, transl


class WalkCycle(Motion):
    """Procedural in-place walk (see the module docstring). Angles in [rad], times in [s].

    Args:
        duration: length of the motion [s].
        period: one full stride (left + right step) [s].
        hip: hip flexion amplitude; knee: peak knee flexion in the swing phase; arm: arm swing amplitude;
        elbow: extra elbow flexion at the forward swing; twist: spine twist amplitude about the vertical.
        ramp: the amplitudes ramp from 0 (smoothstep) over this time, so the motion starts at rest.
    """

    def __init__(
        self,
        duration: float = 4.0,
        *,
        period: float = 1.2,
        hip: float = 0.35,
        knee: float = 0.7,
        arm: float = 0.3,
        elbow: float = 0.15,
        twist: float = 0.06,
        ramp: float = 0.6,
    ):
        if duration <= 0 or period <= 0 or ramp < 0:
            raise InputError("walk duration and period must be > 0 and ramp >= 0")
        self.duration, self.period, self.ramp = float(duration), float(period), float(ramp)
        self.hip, self.knee, self.arm, self.elbow, self.twist = hip, knee, arm, elbow, twist

    def offsets(self, times: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        t = torch.as_tensor(times, dtype=torch.float64)
        r = (t / self.ramp).clamp(0, 1) if self.ramp > 0 else torch.ones_like(t)
        amp = r * r * (3 - 2 * r)
        ph = 2 * math.pi * t / self.period
        # Positive rotation about Anny's X swings a limb backward (+Y), so flexion forward is negative.
        hip_l = -self.hip * torch.sin(ph)
        hip_r = self.hip * torch.sin(ph)
        # The left leg swings forward while cos(ph) > 0: the knee flexes during the swing.
        knee_l = self.knee * torch.cos(ph).clamp_min(0) ** 2
        knee_r = self.knee * (-torch.cos(ph)).clamp_min(0) ** 2
        arm_l, arm_r = self.arm / self.hip * hip_r, self.arm / self.hip * hip_l  # opposite to the legs
        elbow_l = self.elbow * (-arm_l / self.arm).clamp_min(0)
        elbow_r = self.elbow * (-arm_r / self.arm).clamp_min(0)
        twist = self.twist * torch.sin(ph)
        pose = torch.zeros(len(t), len(POSE_BONES), 3, dtype=torch.float64)

        def put(bone, axis, value):
            pose[:, POSE_BONES.index(bone), axis] = amp * value

        put("upperleg01.L", 0, hip_l)
        put("upperleg01.R", 0, hip_r)
        put("lowerleg01.L", 0, knee_l)
        put("lowerleg01.R", 0, knee_r)
        put("upperarm01.L", 0, arm_l)
        put("upperarm01.R", 0, arm_r)
        put("lowerarm01.L", 0, -elbow_l)
        put("lowerarm01.R", 0, -elbow_r)
        put("spine03", 2, twist)
        return pose, torch.zeros(len(t), 3, dtype=torch.float64)


def keyframes_from_dict(data: dict) -> KeyframeMotion:
    """A `KeyframeMotion` from the JSON layout of the module docstring."""
    if not isinstance(data, dict) or not isinstance(data.get("keyframes"), list):
        raise InputError('a keyframe motion is a JSON object with a "keyframes" list')
    keys = []
    for i, k in enumerate(data["keyframes"]):
        try:
            pose = {b: tuple(float(c) for c in rv) for b, rv in k.get("pose", {}).items()}
            if any(len(rv) != 3 for rv in pose.values()):
                raise ValueError("every bone rotation needs 3 axis-angle components")
            transl = tuple(float(c) for c in k.get("translation_m", (0.0, 0.0, 0.0)))
            if len(transl) != 3:
                raise ValueError("translation_m needs 3 components")
            keys.append(Keyframe(float(k["time_s"]), pose, transl))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise InputError(f"keyframe {i}: {exc}") from exc
    return KeyframeMotion(keys, ease=data.get("ease", "smooth"))


def load_motion(spec: str | os.PathLike, *, duration: float | None = None) -> Motion:
    """``"walk"`` (the procedural walk, ``duration`` s, default 4) or a keyframe JSON file."""
    if str(spec) == "walk":
        return WalkCycle(4.0 if duration is None else duration)
    return keyframes_from_dict(read_json_file(spec, f"--motion {spec}: give 'walk' or a keyframe JSON file"))


def compose_pose(base: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
    """Axis-angle ``offset ∘ base``: base (K, 3) or (T, K, 3), offset (T, K, 3) -> (T, K, 3) [rad]."""
    base = base.to(offset.dtype).expand_as(offset)
    return roma.rotvec_composition([offset, base])
