"""A fit's TensorBoard log (``<out>/tb``) and progress bar: the scalars of one evaluation (every loss term,
weighted and not, Chamfer distances, rest/draped mesh quality, the material (bending stiffness, membrane
stretch factor and stiffnesses), body parameters, drape
diagnostics), pictures of the drape and the pattern, and the draped mesh."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from torch_diffavatar.fit_config import FitConfig, config_to_dict, yaml_dump
from torch_diffavatar.fit_report import chamfer_m
from torch_diffavatar.losses import rest_area_ratio
from torch_diffavatar.metrics import triangle_quality
from torch_diffavatar.objective import FitObjective, FitParameters, ObjectiveOutput, membrane_stiffnesses
from torch_diffavatar.pattern.garment_mesh import GarmentMesh


def fit_scalars(
    out: ObjectiveOutput,
    objective: FitObjective,
    params: FitParameters,
    *,
    rejected_total: int,
    nan_gradients: int,
) -> dict:
    """Scalars of one evaluation ``out``, by TensorBoard tag (``loss/…``, ``chamfer/…`` [m], ``quality/…``,
    ``material/…``, ``body/…``, ``steps/…``, ``drape/…``); ``rejected_total`` and ``nan_gradients``: the
    driver's counts so far."""
    scalars = {"loss/total": float(out.loss.detach())}
    for k, v in out.terms.items():
        scalars[f"loss/{k}"] = float(v.detach())
        scalars[f"loss_weighted/{k}"] = float(objective.weight(k) * v.detach())
    scalars["chamfer/interior_m"] = chamfer_m(out.x, objective.scan_points)
    for loop in out.openings:
        scalars[f"chamfer/boundary_{loop.name}_m"] = chamfer_m(
            out.x[loop.vertices], objective.scan_boundaries[loop.name]
        )
    garment = objective.garment
    with torch.no_grad():
        q_rest = triangle_quality(out.rest_uv.detach(), garment.tri_vertices)
        q_drape = triangle_quality(out.x.detach(), garment.sim_faces)
        ratio = rest_area_ratio(out.rest_uv.detach(), objective.template_uv, garment.tri_vertices)
    scalars["quality/rest_min"] = float(q_rest.min())
    scalars["quality/rest_mean"] = float(q_rest.mean())
    scalars["quality/draped_min"] = float(q_drape.min())
    scalars["quality/draped_mean"] = float(q_drape.mean())
    scalars["quality/inverted_rest_triangles"] = int((ratio <= 0).sum())
    scalars["material/bend_stiffness"] = float(out.bend_stiffness.detach())
    scalars["material/log_bend_stiffness"] = float(params.log_bend_stiffness.detach())
    scalars["material/log_stretch"] = float(params.log_stretch.detach())  # s, before its bound
    scalars["material/stretch_scale"] = float(params.stretch().detach())  # the factor of k_uu, k_vv, k_uv
    for name, value in membrane_stiffnesses(objective.material, out.stretch).items():
        scalars[f"material/{name}"] = value
    scalars["placement/waist_shift_m"] = float(params.waist_shift().detach())
    body = params.body
    if body is not None:
        for label, value in zip(body.phenotype_labels, body.phenotypes[0].detach().tolist()):
            scalars[f"body/{label}"] = value
        for axis, value in zip("xyz", body.translation[0].detach().tolist()):
            scalars[f"body/translation_{axis}"] = value
    scalars["steps/rejected_total"] = rejected_total
    scalars["steps/nan_gradients"] = nan_gradients
    for k in ("newton_force_residual", "forward_seconds", "backward_seconds", "xpbd_steps", "predicted_move"):
        if isinstance(out.stats.get(k), int | float):
            scalars[f"drape/{k}"] = float(out.stats[k])
    return scalars


def open_writer(out_dir: Path, config: FitConfig):
    """A TensorBoard ``SummaryWriter`` on ``<out_dir>/tb`` with the resolved config as its text."""
    from torch.utils.tensorboard import SummaryWriter

    writer = SummaryWriter(log_dir=str(out_dir / "tb"))
    writer.add_text("config", "```\n" + yaml_dump(config_to_dict(config)) + "\n```", 0)
    return writer


def progress_bar(total: int, initial: int):
    """A tqdm bar on stderr over ``total`` iterations, ``initial`` of them done."""
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, desc="fit", unit="it", file=sys.stderr)


def update_bar(bar, scalars: dict) -> None:
    """One iteration more on ``bar``, with the loss and the interior Chamfer distance [mm] of ``scalars``."""
    bar.update(1)
    loss, chamfer = scalars["loss/total"], scalars["chamfer/interior_m"]
    bar.set_postfix(loss=f"{loss:.4g}", chamfer_mm=f"{1e3 * chamfer:.2f}")


def log_scalars(writer, history: list[dict]) -> None:
    """Write the scalars of every ``history`` entry (one dict per iteration, with its ``iteration``)."""
    for entry in history:
        for k, v in entry.items():
            if k != "iteration":
                writer.add_scalar(k, v, entry["iteration"])


def log_evaluation(
    writer, out: ObjectiveOutput, scalars: dict, it: int, images: bool, objective: FitObjective
) -> None:
    """Write ``scalars`` at step ``it``, and with ``images`` the pictures of the drape and the pattern and
    the draped mesh; nothing without a ``writer``."""
    if writer is None:
        return
    for k, v in scalars.items():
        writer.add_scalar(k, v, it)
    if images:
        garment = objective.garment
        try:
            writer.add_image("drape", drape_image(out, garment, objective.body_faces), it, dataformats="HWC")
            writer.add_image("pattern", pattern_image(out.rest_uv.detach(), garment), it, dataformats="HWC")
            writer.add_mesh(
                "draped_mesh",
                vertices=out.x.detach()[None].float(),
                faces=garment.sim_faces[None].int(),
                global_step=it,
            )
        except Exception as exc:  # pictures are diagnostics: never let them stop a fit
            print(f"fit: could not log images ({exc})", file=sys.stderr)
    writer.flush()


def drape_image(out: ObjectiveOutput, garment: GarmentMesh, body_faces: torch.Tensor | None) -> np.ndarray:
    """(H, W, 3) uint8 front and back views of the drape (and the body)."""
    from torch_diffavatar.render import CLOTH_COLOR, CLOTH_DEPTH_BIAS, RenderMesh, render_views

    meshes = [RenderMesh(out.x.detach().cpu(), garment.sim_faces, CLOTH_COLOR, CLOTH_DEPTH_BIAS)]
    if out.body_verts is not None:
        meshes.insert(0, RenderMesh(out.body_verts.detach().cpu(), body_faces.cpu()))
    return render_views(meshes, views=("front", "back"), width=256, height=320)


def pattern_image(rest_uv: torch.Tensor, garment: GarmentMesh, size: int = 512) -> np.ndarray:
    """The rest mesh of every panel, side by side, drawn with Pillow ((H, W, 3) uint8)."""
    from PIL import Image, ImageDraw

    uv = rest_uv.cpu().double().numpy()
    vert_panel = garment.vert_panel.cpu().numpy()
    offsets, x0 = [], 0.0
    for pid in range(len(garment.panel_names)):
        p = uv[vert_panel == pid]
        offsets.append((x0 - p[:, 0].min(), -p[:, 1].min()))
        x0 += p[:, 0].max() - p[:, 0].min() + 0.05
    pos = uv + np.array(offsets)[vert_panel]
    extent = max(pos[:, 0].max(), pos[:, 1].max(), 1e-6)
    s = (size - 20) / extent
    img = Image.new("RGB", (size, size), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    for tri in garment.tri_vertices.cpu().numpy():
        pts = [(10 + s * pos[i, 0], size - 10 - s * pos[i, 1]) for i in tri]
        draw.polygon(pts, outline=(70, 110, 190))
    return np.asarray(img)
