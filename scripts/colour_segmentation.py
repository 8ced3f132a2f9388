"""Garment segmentation with and without colour on capture-simulated scans (issue #29 item 3).

Each case is a folder with ``scan.ply`` (a `make-scan --capture` scan: colours and a ``label`` per point)
and ``body/`` (its `diffavatar fit-body` output, made here when missing). The scan goes through the
intake as `diffavatar segment` does, then `segment_garment` labels it three ways: geometry alone
(``use_colour=False``), as before this change (the two-Gaussian colour evidence: the new colour models
switched off), and with the colour models and graph cut (the default). Printed per way: precision and
recall of the garment's points (label 1) and how far its boundary strays (`boundary_distance`: the
mean and 95th percentile [cm] over the wrongly labelled points of their distance to the nearest point
truly of the label they were given); for scenes with a second garment (label 2), the same over the two
garments' points only (the boundary between the shirt and the trousers).

``--make SCENE TEMPLATE SEED FOLDER`` first writes a scene: ``outfit`` (the draped top over trousers:
the body's hips, legs and torso below the waist pushed out by 1.2 cm, dark blue, label 2), ``same-skin``
(the garment the colour of the skin), ``same-garments`` (the outfit with trousers the top's colour).
The capture: a ring of 4 cameras, a random yaw from the seed, centimetres, Y down.

    PYTHONPATH=. python scripts/colour_segmentation.py --make outfit tshirt 46 /tmp/cs/outfit_s46
    PYTHONPATH=. python scripts/colour_segmentation.py /tmp/cs/outfit_s46:tshirt /tmp/cs/outfit_s46:pants:2
    PYTHONPATH=. python scripts/colour_segmentation.py --smoothness 4 --rounds 1 /tmp/cs/outfit_s46:pants:2
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import subprocess
import sys
from pathlib import Path
from unittest import mock

import numpy as np
import torch
from scipy.spatial import cKDTree

TROUSERS_COLOR = (38, 44, 70)
TROUSERS_OFFSET_M = 0.012


def make_scene(scene: str, template: str, seed: int, folder: Path) -> None:
    """Write ``folder/scan.ply`` and ``folder/truth`` of the ``scene`` (see the module docstring)."""
    from torch_diffavatar.body.anny_model import load_anny
    from torch_diffavatar.capture import CaptureSettings, SceneMesh
    from torch_diffavatar.captured_scans import GARMENT_COLOR, SKIN_COLOR, capture_draped_scan
    from torch_diffavatar.commands.make_scan import YAW_SEED_OFFSET
    from torch_diffavatar.synthetic_scans import make_draped_scan, write_scan

    anny = load_anny(dtype=torch.float32)
    scan = make_draped_scan(template, anny_model=anny, seed=seed)
    garment_color = SKIN_COLOR if scene == "same-skin" else GARMENT_COLOR
    extra = ()
    if scene in ("outfit", "same-garments"):
        color = garment_color if scene == "same-garments" else TROUSERS_COLOR
        extra = (SceneMesh(*_trousers(scan, anny), 2, color),)
    # as `make-scan --capture ring --yaw random --scan-units cm --scan-up -y` draws them
    yaw = float(np.random.default_rng([seed, YAW_SEED_OFFSET]).uniform(0.0, 360.0))
    settings = CaptureSettings(yaw_deg=yaw, units="cm", up="-y")
    turned, captured = capture_draped_scan(
        scan, settings, seed, garment_color=garment_color, extra_meshes=extra
    )
    write_scan(turned, folder, capture=captured)


def _trousers(scan, anny) -> tuple[np.ndarray, np.ndarray]:
    """A trousers layer: the true body's faces over the hips, legs (not the feet) and torso below the
    waist, pushed out along the vertex normals by `TROUSERS_OFFSET_M`."""
    from torch_diffavatar.body.geometry import vertex_normals
    from torch_diffavatar.body.model import BodyModel
    from torch_diffavatar.body.parts import PART_NAMES, vertex_parts

    body = BodyModel(anny_model=anny)
    body.load_parameters_dict(scan.body_params)
    with torch.no_grad():
        waist = body.waist_height(body().joints[0])
    verts = scan.body_vertices
    parts = vertex_parts(anny).numpy()
    legs = [PART_NAMES.index(p) for p in ("hips", "thigh.L", "thigh.R", "shin.L", "shin.R")]
    inside = np.isin(parts, legs) | ((parts == PART_NAMES.index("torso")) & (verts[:, 1] < waist))
    faces = scan.body_faces[inside[scan.body_faces].all(1)]
    normals = vertex_normals(torch.as_tensor(verts), torch.as_tensor(scan.body_faces)).numpy()
    return verts + TROUSERS_OFFSET_M * normals, faces


def _body(folder: Path, anny):
    """The fitted body's vertices (Vb, 3) and waist height [m], from ``folder/body`` (fitted when missing)."""
    from torch_diffavatar.body.model import BodyModel

    out = folder / "body"
    if not (out / "body.json").is_file():
        cli = [sys.executable, "-m", "torch_diffavatar.cli", "fit-body", str(folder / "scan.ply")]
        subprocess.run([*cli, "--out", str(out)], check=True, stdout=subprocess.DEVNULL)
    body = BodyModel(anny_model=anny)
    body.load_parameters_dict(json.loads((out / "body.json").read_text()))
    with torch.no_grad():
        result = body()
    return result.vertices[0].double().numpy(), body.waist_height(result.joints[0])


def boundary_distance(points: np.ndarray, truth: np.ndarray, pred: np.ndarray) -> tuple[float, float]:
    """How far the predicted garment boundary strays from the true one [m]: the mean and the 95th
    percentile, over the wrongly labelled points, of the distance from each to the nearest point truly of
    the label it was given (0 when none is wrong); ``truth``, ``pred``: (N,) bool labels of the (N, 3)
    ``points``."""
    wrong = truth != pred
    if not wrong.any():
        return 0.0, 0.0
    dist = np.zeros(int(wrong.sum()))
    for label in (True, False):
        mine = pred[wrong] == label
        if mine.any() and (truth == label).any():
            dist[mine] = cKDTree(points[truth == label]).query(points[wrong][mine])[0]
    return float(dist.mean()), float(np.percentile(dist, 95))


def evaluate(folder: Path, garment: str, anny, label: int = 1) -> dict:
    """The three ways' figures on one case (see the module docstring); the garment's points are those
    labelled ``label`` (2: the trousers of an outfit scene, the top then the other garment)."""
    from torch_diffavatar.body import segment
    from torch_diffavatar.body.parts import vertex_parts
    from torch_diffavatar.scan_intake import intake_scan

    scan, _ = intake_scan(folder / "scan.ply")
    verts, waist = _body(folder, anny)
    faces = anny.faces.cpu().numpy()
    parts = vertex_parts(anny).cpu().numpy()
    truth = scan.labels == label
    out = {}
    for way in ("geometry", "before", "colour"):
        before = mock.patch.object(segment, "colour_labels", lambda *a, **k: None)
        with before if way == "before" else contextlib.nullcontext():
            seg = segment.segment_garment(
                scan.points, garment, verts, faces, parts, colors=scan.colors, support_top=waist,
                use_colour=way != "geometry",
            )  # fmt: skip
        pred = seg.labels
        tp = float((pred & truth).sum())
        row = {"precision": tp / max(pred.sum(), 1), "recall": tp / max(truth.sum(), 1)}
        row["wrong"] = int((pred != truth).sum())
        row["boundary_cm"] = [100 * d for d in boundary_distance(scan.points, truth, pred)]
        two = (scan.labels == 1) | (scan.labels == 2)
        if (scan.labels == 2).any():
            dist = boundary_distance(scan.points[two], truth[two], pred[two])
            row["between_garments_cm"] = [100 * d for d in dist]
        out[way] = row
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cases", nargs="*", help="FOLDER:GARMENT, or FOLDER:GARMENT:LABEL (default 1)")
    parser.add_argument("--make", nargs=4, metavar=("SCENE", "TEMPLATE", "SEED", "FOLDER"))
    parser.add_argument("--smoothness", type=float, default=None, help="`colour_labels`' (default its own)")
    parser.add_argument("--rounds", type=int, default=None, help="`colour_labels`' (default its own)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    from torch_diffavatar.body import colour, segment

    options = {k: v for k, v in (("smoothness", args.smoothness), ("rounds", args.rounds)) if v is not None}
    segment.colour_labels = functools.partial(colour.colour_labels, **options)
    if args.make:
        scene, template, seed, folder = args.make
        make_scene(scene, template, int(seed), Path(folder))
    from torch_diffavatar.body.anny_model import load_anny

    anny = load_anny(dtype=torch.float32)
    for case in args.cases:
        folder, garment, *label = case.split(":")
        result = evaluate(Path(folder), garment, anny, int(label[0]) if label else 1)
        for way, row in result.items():
            figures = " ".join(
                f"{k} {v:.3f}"
                if isinstance(v, float)
                else f"{k} {v}"
                if isinstance(v, int)
                else f"{k} {v[0]:.2f}/{v[1]:.2f}"
                for k, v in row.items()
            )
            print(f"{folder} {garment} {way}: {figures}", flush=True)


if __name__ == "__main__":
    main()
