"""`diffavatar animate`: the recovered garment on the recovered body through a new motion.

The asset folder (`torch_diffavatar.assets.load_assets`) gives the garment (rest shape, seams, drape),
the material and the Anny parameters of the body. The body is posed along a `torch_diffavatar.motion`
motion (pose offsets on top of its own pose), and the draped garment is simulated with our XPBD solver
on the seam-merged mesh, starting from the drape.

Moving body, no tunnelling: `XPBDSolver.step` with ``body_verts_end`` detects contacts once per frame
(closest body triangle of every cloth vertex, in a band widened by how far the body and the cloth move
in that frame) and then runs the frame's substeps one by one with the body vertices linearly
interpolated between the frame's start and end poses, so the contact planes move with the body in
steps of one substep (≈ 0.4 mm at 1 m/s with 40 substeps at 60 Hz) instead of one frame; the cloth in
contact picks up the body's velocity instead of an impulse of a frame's motion.

`diffavatar export-template NAME --out DIR` writes the same asset folder for a template garment
(meshed, placed, sewn and draped on the default Anny body), so templates animate through the same path.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from torch_diffavatar.atomic_file import atomic_path
from torch_diffavatar.errors import InputError
from torch_diffavatar.json_io import write_json
from torch_diffavatar.mesh_io import write_ply
from torch_diffavatar.sim import ops
from torch_diffavatar.sim.floor import FLOOR_FACES, sole_height, with_floor
from torch_diffavatar.sim.solver import XPBDConfig, XPBDSolver

# A body vertex may move this far [m] from the pose the asset's body.obj was written in before the
# reconstruction from body.json counts as wrong (the files disagree).
_BODY_MATCH_TOL = 2e-3


def _body_model(assets, anny_model=None):
    """A `BodyModel` carrying the asset's body.json parameters."""
    from torch_diffavatar.body.model import BodyModel

    body = BodyModel(anny_model, dtype=torch.float32)
    params = assets.body_params
    if list(params.get("pose_bones", [])) != list(body.pose_bones):
        raise InputError(f"{assets.path}/body.json: pose_bones do not match this version's BodyModel")
    body.load_parameters_dict(params)
    return body.requires_grad_(False)


def body_sequence(assets, motion, times: torch.Tensor, *, anny_model=None) -> torch.Tensor:
    """(T, Vb, 3) float32 body vertices [m] at ``times`` (T,) [s] of ``motion`` on the asset's body.

    At zero motion offset the body must reproduce the asset's body.obj (up to a constant shift, which is
    applied to every pose); else `InputError`.
    """
    from torch_diffavatar.motion import compose_pose

    body = _body_model(assets, anny_model)
    base_pose = body.pose.detach()[0].double()  # (K, 3)
    pose_off, transl_off = motion.offsets(times)
    pose = compose_pose(base_pose, pose_off).to(torch.float32)  # (T, K, 3)
    with torch.no_grad():
        rest = body().vertices[0].double()
        target = assets.body_verts.double()
        if rest.shape != target.shape:
            raise InputError(
                f"{assets.path}/body.obj has {target.shape[0]} vertices, the Anny body {rest.shape[0]}"
            )
        shift = (target - rest).mean(0)
        err = float((rest + shift - target).norm(dim=-1).max())
        if err > _BODY_MATCH_TOL:
            raise InputError(
                f"{assets.path}: body.json does not reproduce body.obj (max deviation {err * 1e3:.1f} mm)"
            )
        frames = []
        for i in range(len(times)):
            out = body(pose=pose[i : i + 1], translation=body.translation + transl_off[i : i + 1].float())
            frames.append(out.vertices[0])
    return torch.stack(frames) + shift.to(torch.float32)


def animate(
    assets,
    motion,
    out_dir: str | Path | None = None,
    *,
    fps: float = 30.0,
    sim_fps: float = 60.0,
    duration: float | None = None,
    config: XPBDConfig | None = None,
    velocity_scale: float = 0.99,
    anny_model=None,
    write_body: bool = True,
    gif: bool = True,
    gif_size: int = 240,
    progress: bool = False,
    floor: bool = True,
) -> dict:
    """Simulate the asset's garment through ``motion``; optionally write frames and a GIF.

    Args:
        assets: `load_assets` output.
        motion: a `torch_diffavatar.motion.Motion`.
        out_dir: where ``frames/garment_XXXX.obj`` (vt = rest coordinates [m]), ``frames/body_XXXX.ply``
            and ``animation.gif`` go (None: nothing is written).
        fps: output frame rate [1/s]; sim_fps: simulated frames per second (a multiple of ``fps``).
        duration: seconds to simulate (default the motion's duration).
        config: XPBD options (default `XPBDConfig()`: 40 substeps × 1 iteration per simulated frame).
        velocity_scale: velocity factor per simulated frame (mild air drag, as in the drape).
        write_body: also write the body per frame; gif: write the preview GIF (front and side views).
        floor: the cloth also collides with a floor under the first frame's soles (`sim.floor`; the fit
            drapes on one): trousers piled on it stay on it while the feet lift.

    Returns:
        a summary: frames, seconds, worst penetration fraction (vertices behind the body surface /
        all cloth vertices, over every simulated frame) and its frame, max speed [m/s], max strain,
        wall time, written files, and ``per_frame`` penetration fractions and max speeds.

    Raises:
        SimulationError: the simulation blew up.
    """
    per_out, n_out, n_sim = _frame_counts(motion, fps, sim_fps, duration)
    dt = 1.0 / sim_fps
    t0 = time.perf_counter()
    times = torch.arange(n_sim + 1, dtype=torch.float64) * dt
    bodies = body_sequence(assets, motion, times, anny_model=anny_model)  # (n_sim + 1, Vb, 3)
    faces = assets.body_faces.to(torch.int64)
    solver, rest, state = _cloth_solver(assets, config, floor)
    out = Path(out_dir) if out_dir is not None else None
    writer = _FrameWriter(out, assets.garment, faces, write_body=write_body, gif=gif, gif_size=gif_size)
    colliders, c_faces = with_floor(bodies, faces, sole_height(bodies[0])) if floor else (bodies, faces)
    nb = bodies.shape[1]

    def emit(k, x, collider):  # the body's frame, without the floor
        writer(k, x, collider[:nb])

    run = _simulate(
        solver, rest, state, colliders, c_faces, dt, velocity_scale, per_out, emit, progress=progress
    )
    summary = {
        "garment": assets.garment.garment_type,
        "vertices": solver.model.vert_count,
        "motion": type(motion).__name__,
        "duration_s": n_sim * dt,
        "fps": fps,
        "sim_fps": sim_fps,
        "substeps": solver.config.substeps,
        "output_frames": n_out + 1,
        "sim_frames": n_sim,
        **run.stats(),
        "wall_s": round(time.perf_counter() - t0, 2),
        "per_frame": {"penetration_fraction": run.penetration, "max_speed_m_s": run.speed},
    }
    if out is not None:
        summary["frames_dir"] = str(writer.frames_dir)
        if gif and writer.images:
            summary["gif"] = str(writer.save_gif(out / "animation.gif", fps))
        write_json(out / "animation.json", summary)
    return summary


def _frame_counts(motion, fps: float, sim_fps: float, duration: float | None) -> tuple[int, int, int]:
    """(simulated frames per output frame, output frames after the first, simulated frames) of
    `animate`; InputError for rates that do not divide or a duration [s] that is not positive."""
    ratio = sim_fps / fps
    if fps <= 0 or abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
        raise InputError(f"sim_fps ({sim_fps}) must be a positive multiple of fps ({fps})")
    per_out = int(round(ratio))
    duration = motion.duration if duration is None else float(duration)
    if duration <= 0:
        raise InputError(f"the motion lasts {duration} s; give a positive duration")
    n_out = int(math.floor(duration * fps + 1e-9))
    return per_out, n_out, n_out * per_out


def _cloth_solver(assets, config: XPBDConfig | None, floor: bool = False):
    """The asset's garment on its seam-merged mesh (float32): (`XPBDSolver`, rest data, state at the
    asset's drape). With ``floor`` the body mesh it steps against ends with the floor (`sim.floor`)."""
    from torch_diffavatar.sim.model import ClothModelBuilder

    if floor:
        config = replace(XPBDConfig() if config is None else config, floor_faces=FLOOR_FACES)
    model = (
        ClothModelBuilder(assets.material)
        .add_garment(assets.garment, merge_seams=True)
        .finalize(dtype=torch.float32)
    )
    rest = model.rest_data(assets.rest_uv.to(torch.float32))
    solver = XPBDSolver(model, config)
    return solver, rest, model.initial_state(assets.draped_x.to(torch.float32))


class _FrameWriter:
    """Writes the output frames of `animate` under ``out/frames`` (nothing when ``out`` is None) and
    keeps the GIF's pictures (front and side, one camera for the whole clip)."""

    def __init__(
        self,
        out: Path | None,
        garment,
        body_faces: torch.Tensor,
        *,
        write_body: bool,
        gif: bool,
        gif_size: int,
    ):
        self.frames_dir = None if out is None else out / "frames"
        if self.frames_dir is not None:
            self.frames_dir.mkdir(parents=True, exist_ok=True)
        self.garment, self.tri_sim, self.body_faces = garment, garment.sim_faces, body_faces
        self.write_body, self.gif, self.gif_size = write_body, gif, gif_size
        self.images: list[np.ndarray] = []  # (H, 2W, 3) uint8 per output frame
        self.cameras = None

    def __call__(self, k: int, x: torch.Tensor, bv: torch.Tensor) -> None:
        """Output frame ``k``: cloth ``x`` (Vs, 3) [m] on the body ``bv`` (Vb, 3) [m]."""
        from torch_diffavatar.mesh_io import write_obj

        if self.frames_dir is None:
            return
        garment = self.garment
        write_obj(
            self.frames_dir / f"garment_{k:04d}.obj",
            x.double(),
            self.tri_sim,
            uv=garment.vert_uv,
            uv_faces=garment.tri_vertices,
        )
        if self.write_body:
            write_ply(self.frames_dir / f"body_{k:04d}.ply", bv.numpy(), self.body_faces.numpy())
        if self.gif:
            self.images.append(self._picture(x, bv))

    def _picture(self, x: torch.Tensor, bv: torch.Tensor) -> np.ndarray:
        """(5/4 W, 2 W, 3) uint8 front and side views of cloth ``x`` on body ``bv``, W = ``gif_size``."""
        from torch_diffavatar.render import CLOTH_COLOR, CLOTH_DEPTH_BIAS, RenderMesh, look_at_camera, render

        size, height = self.gif_size, self.gif_size * 5 // 4
        if self.cameras is None:  # one camera for the whole clip (from the first frame, padded)
            lo = bv.min(0).values.double().numpy() - 0.1
            hi = bv.max(0).values.double().numpy() + 0.1
            self.cameras = [
                look_at_camera(lo, hi, view, width=size, height=height, perspective=False)
                for view in ("front", 60.0)
            ]
        meshes = [
            RenderMesh(bv.numpy(), self.body_faces.numpy()),
            RenderMesh(x.numpy(), self.tri_sim.numpy(), CLOTH_COLOR, CLOTH_DEPTH_BIAS),
        ]
        return np.concatenate(
            [render(meshes, camera=c, width=size, height=height) for c in self.cameras], axis=1
        )

    def save_gif(self, path: Path, fps: float) -> Path:
        """Write the pictures kept so far as a looping GIF at ``fps`` [1/s]; returns ``path``."""
        from PIL import Image

        pil = [Image.fromarray(im) for im in self.images]
        with atomic_path(path) as tmp:
            pil[0].save(tmp, save_all=True, append_images=pil[1:], duration=int(round(1000 / fps)), loop=0)
        return path


@dataclass
class _Rollout:
    """What `_simulate` measured.

    Attributes:
        state: the final `ClothState`.
        penetration0: penetration fraction of the initial state (vertices behind the body surface / all).
        penetration, speed: per simulated frame, the penetration fraction and the max speed [m/s].
        worst, worst_frame: the largest penetration fraction (the initial one included) and its frame.
        max_strain: the final max |Green strain| [-].
    """

    state: object
    penetration0: float
    penetration: list[float]
    speed: list[float]
    worst: float
    worst_frame: int
    max_strain: float

    def stats(self) -> dict:
        """The summary's entries of `animate` from ``finite`` to ``final_max_strain``."""
        return {
            "finite": bool(torch.isfinite(self.state.x).all()),
            "initial_penetration_fraction": self.penetration0,
            "max_penetration_fraction": self.worst,
            "max_penetration_sim_frame": self.worst_frame,
            "max_speed_m_s": max(self.speed) if self.speed else 0.0,
            "final_max_strain": self.max_strain,
        }


def _simulate(
    solver: XPBDSolver,
    rest,
    state,
    bodies: torch.Tensor,
    faces: torch.Tensor,
    dt: float,
    velocity_scale: float,
    per_out: int,
    emit,
    *,
    progress: bool = False,
) -> _Rollout:
    """Step the cloth from ``state`` through the body frames ``bodies`` (T + 1, Vb, 3) [m] (faces
    (Fb, 3)), ``dt`` [s] per frame, calling ``emit(k, x, body)`` on every ``per_out``-th frame (and the
    first, as k = 0)."""
    from torch_diffavatar.sim.forward_drape import penetration_diagnostics

    model = solver.model

    def penetration(x, bv) -> float:
        d = penetration_diagnostics(x, bv, faces)
        return d["penetrating_count"] / model.vert_count

    pen0 = penetration(state.x, bodies[0])
    emit(0, state.x, bodies[0])
    pen, speed, worst, worst_frame = [], [], pen0, 0
    iterator = range(len(bodies) - 1)
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, desc="animate", unit="frame")
    for i in iterator:
        state = solver.step(
            state,
            rest,
            dt,
            body_verts=bodies[i],
            body_faces=faces,
            body_verts_end=bodies[i + 1],
            velocity_scale=velocity_scale,
        )
        p = penetration(state.x, bodies[i + 1])
        pen.append(p)
        speed.append(float(state.v.norm(dim=-1).max()))
        if p > worst:
            worst, worst_frame = p, i + 1
        if (i + 1) % per_out == 0:
            emit((i + 1) // per_out, state.x, bodies[i + 1])
    max_strain = float(ops.max_abs_green_strain(state.x, model.tri_vertices, rest.tri_rest_inv))
    return _Rollout(state, pen0, pen, speed, worst, worst_frame, max_strain)


def template_assets(
    name: str, out_dir: str | Path, *, spacing: float = 0.02, anny_model=None, png: bool = True
) -> dict:
    """Mesh, place, sew and drape template ``name`` on the default Anny body; write its asset folder.

    Returns:
        `write_assets`' file map (asset name -> path).

    Raises:
        SimulationError: the template does not sew or drape.
    """
    from torch_diffavatar.assets import write_assets
    from torch_diffavatar.body.model import BodyModel
    from torch_diffavatar.pattern import load_template, mesh_pattern
    from torch_diffavatar.sim.forward_drape import sew_and_drape
    from torch_diffavatar.sim.material import medium_cotton
    from torch_diffavatar.sim.placement import place_garment

    body = BodyModel(anny_model, dtype=torch.float32).requires_grad_(False)
    with torch.no_grad():
        # the default draping body: default phenotypes, A-pose, feet on y = 0
        body.translation[:, 1] = -body().vertices[0, :, 1].min()
        body_verts = body().vertices[0].double()
    pattern = load_template(name)
    garment = place_garment(mesh_pattern(pattern, spacing=spacing), body_verts, body.faces)
    material = medium_cotton()
    t0 = time.perf_counter()
    result = sew_and_drape(garment, body_verts=body_verts, body_faces=body.faces, material=material)
    params = dict(body.parameters_dict())
    params["phenotypes_by_name"] = dict(zip(body.phenotype_labels, body.phenotypes[0].tolist()))
    report = {
        "source": f"template {name!r} sewn and draped on the default Anny body (no fit)",
        "spacing_m": spacing,
        "drape_frames": result.steps,
        "drape_converged": result.converged,
        "drape_seconds": round(time.perf_counter() - t0, 2),
        "penetrating_count": result.diagnostics.get("penetrating_count"),
    }
    before = (garment.sim_positions(), garment.sim_faces, body_verts, body.faces) if png else None
    return write_assets(
        out_dir,
        pattern=pattern,
        garment=garment,
        rest_uv=garment.vert_uv,
        draped_x=result.x,
        body_verts=body_verts,
        body_faces=body.faces,
        body_params=params,
        material=material,
        report=report,
        before=before,
    )
