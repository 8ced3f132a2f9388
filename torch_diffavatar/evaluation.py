"""Fitted assets against a known ground truth (the demo's bundled answer, synthetic scans).

`evaluate_assets` (the ``diffavatar eval ASSETS_DIR --gt GT_DIR`` command) measures everything against a
``diffavatar make-scan`` ground truth. Its pattern and material part, `compare_with_truth`, reads the
assets a fit wrote (``pattern.json``, ``material.json``) and measures them against the true pattern and
material:

* ``pattern_outline_error_m``: per panel, the mean distance between the fitted and the true outline after
  a rigid alignment of the panel (`metrics.outline_distance`); the value is the worst panel's [m];
* ``pattern_outline_hausdorff_m``: the same with the largest distance (dart tips and corners dominate);
* ``pattern_outline_errors``: both per panel;
* ``garment_measurements``: what a tailor checks (`pattern.measurements`: opening circumferences, garment,
  panel and sleeve lengths, hem widths), fitted and true, both measured on the truth's openings:
  ``{name: {"fitted_cm", "true_cm", "error_cm"}}`` (error = fitted − true) [cm], and
  ``garment_measurement_max_error_cm``, the largest absolute error [cm];
* ``garment_area_m2``: the total panel area ``{"fitted_m2", "true_m2", "error_m2"}`` [m²];
* ``bending_stiffness_ratio``: fitted / true bending stiffness [-] (1 is exact);
* ``stretch_stiffness_ratio`` (given the true material): fitted / true stiffness of a strip pulled along one
  axis with its width free (`sim.material.uniaxial_stiffness`, the geometric mean over the two axes) [-].

`save_drape_comparison` draws the fit's first drape, its result and the true drape side by side, front
and back (the command writes it as ``ASSETS_DIR/eval_drapes.png``).
"""

from __future__ import annotations

from pathlib import Path

import torch

from torch_diffavatar.atomic_file import atomic_path
from torch_diffavatar.errors import InputError, read_json_file


def compare_with_truth(
    assets_dir, truth_pattern, truth_bend_stiffness: float | None = None, truth_material=None
) -> dict:
    """Measures of the assets in ``assets_dir`` against the truth (see the module docstring).

    Args:
        assets_dir: a folder written by `assets.write_assets`.
        truth_pattern: the true pattern: a `Pattern` or a GarmentCode JSON path, with the template's
            panel names.
        truth_bend_stiffness: the true bending stiffness [N·m], or None to skip the ratio.
        truth_material: the true `ClothMaterial`, or None; given, both ratios (bending and stretch) come
            from it.

    Raises:
        InputError: a file is missing, or the patterns' panels differ.
    """
    from torch_diffavatar.metrics import pattern_outline_errors
    from torch_diffavatar.pattern.garmentcode import load_pattern

    folder = Path(assets_dir)
    fitted_path = folder / "pattern.json"
    if not fitted_path.is_file():
        raise InputError(f"{fitted_path} is missing: is {folder} the output folder of a fit?")
    truth = load_pattern(truth_pattern) if isinstance(truth_pattern, str | Path) else truth_pattern
    fitted = load_pattern(fitted_path)
    try:
        errors = pattern_outline_errors(fitted, truth)
    except ValueError as exc:
        raise InputError(f"{fitted_path} vs the true pattern: {exc}") from exc
    out = {
        "pattern_outline_error_m": max(e["mean_m"] for e in errors.values()),
        "pattern_outline_hausdorff_m": max(e["max_m"] for e in errors.values()),
        "pattern_outline_errors": errors,
    }
    out.update(garment_measurement_errors(fitted, truth))
    if truth_material is not None:
        truth_bend_stiffness = float(truth_material.bend_stiffness)
    if truth_bend_stiffness is not None:
        from torch_diffavatar.assets import material_from_dict
        from torch_diffavatar.sim.material import uniaxial_stiffness

        material_path = folder / "material.json"
        if not material_path.is_file():
            raise InputError(f"{material_path} is missing: is {folder} the output folder of a fit?")
        material = material_from_dict(read_json_file(material_path, f"{material_path}: missing"))
        out["bending_stiffness_ratio"] = float(material.bend_stiffness) / float(truth_bend_stiffness)
        if truth_material is not None:
            out["stretch_stiffness_ratio"] = uniaxial_stiffness(material) / uniaxial_stiffness(truth_material)
    return out


def garment_measurement_errors(fitted, truth) -> dict:
    """Garment measurements of a fitted pattern against the true one (`pattern.measurements`).

    Both are measured with the edges of the truth's openings (the fit keeps the template's panels and
    edges), so both have the same measurements.

    Args:
        fitted, truth: `Pattern` s with the same panels and edges [m].

    Returns:
        ``garment_measurements``: name -> ``{"fitted_cm", "true_cm", "error_cm"}`` (error = fitted −
        true) [cm]; ``garment_measurement_max_error_cm``: the largest absolute error [cm] (0 without
        measurements); ``garment_area_m2``: ``{"fitted_m2", "true_m2", "error_m2"}`` [m²].

    Raises:
        InputError: the true pattern cannot be meshed, or the fitted one lacks its panels or edges.
    """
    from torch_diffavatar.errors import PatternError
    from torch_diffavatar.pattern.measurements import measure_pattern, pattern_openings

    try:
        openings = pattern_openings(truth)
        true, fit = measure_pattern(truth, openings), measure_pattern(fitted, openings)  # [m], [m²]
    except PatternError as exc:
        raise InputError(f"garment measurements of the fitted vs the true pattern: {exc}") from exc
    table = {
        name: {"fitted_cm": 100 * fit.lengths[name], "true_cm": 100 * value}
        for name, value in true.lengths.items()
    }
    for row in table.values():
        row["error_cm"] = row["fitted_cm"] - row["true_cm"]
    return {
        "garment_measurements": table,
        "garment_measurement_max_error_cm": max((abs(r["error_cm"]) for r in table.values()), default=0.0),
        "garment_area_m2": {"fitted_m2": fit.area, "true_m2": true.area, "error_m2": fit.area - true.area},
    }


def seam_length_mismatch(pattern) -> dict:
    """How much the two sides of the pattern's seams differ in length (darts included).

    Returns:
        ``mean_m`` and ``max_m``: of the absolute length differences of the stitched edge pairs [m] (0
        without stitches); ``per_seam_m``: each seam's, keyed ``"panel[edge]~panel[edge]"`` (edge indices
        as in the pattern JSON) [m].
    """
    per_seam = {
        f"{s.a.panel}[{s.a.edge}]~{s.b.panel}[{s.b.edge}]": float(
            abs(
                pattern.panels[s.a.panel].edge_length(s.a.edge)
                - pattern.panels[s.b.panel].edge_length(s.b.edge)
            )
        )
        for s in pattern.stitches
    }
    diffs = list(per_seam.values())
    if not diffs:
        return {"mean_m": 0.0, "max_m": 0.0, "per_seam_m": {}}
    return {"mean_m": sum(diffs) / len(diffs), "max_m": max(diffs), "per_seam_m": per_seam}


def mesh_distance_m(a_verts, a_faces, b_verts, b_faces, samples: int = 50000) -> float:
    """Symmetric mean surface-to-surface distance [m] between two triangle meshes (seeded samples)."""
    from torch_diffavatar.chamfer import sample_surface
    from torch_diffavatar.geometry import closest_point_on_mesh

    gen = torch.Generator().manual_seed(0)
    out = []
    for (sv, sf), (tv, tf) in (
        ((a_verts, a_faces), (b_verts, b_faces)),
        ((b_verts, b_faces), (a_verts, a_faces)),
    ):
        pts = sample_surface(sv, sf, samples, generator=gen)
        _, _, dist = closest_point_on_mesh(pts.contiguous(), tv.contiguous(), tf.contiguous(), 10.0)
        out.append(float(dist.mean()))
    return 0.5 * sum(out)


def evaluate_assets(assets_dir, gt_dir) -> dict:
    """Every measure of a fit's assets against a synthetic scan's ground truth (`diffavatar eval`).

    Args:
        assets_dir: the output folder of ``diffavatar fit`` (`assets.write_assets`).
        gt_dir: the output folder of ``diffavatar make-scan`` (``scan.ply`` and ``truth/``).

    Returns:
        a dict: ``units`` ("m"), ``chamfer_scan_m`` (scan garment points ↔ fitted drape, on the surface,
        `chamfer.surface_chamfer_m`, not squared), ``chamfer_truth_drape_m`` (fitted ↔ true drape,
        symmetric mean surface-to-surface distance), ``chamfer_scan_truth_m`` (the true drape's own
        ``chamfer_scan_m``: the floor the scan's noise and holes put under it), the pattern errors and
        garment measurements of `compare_with_truth` (``garment_measurements`` [cm],
        ``garment_measurement_max_error_cm``, ``garment_area_m2``), ``seam_length_mismatch`` (fitted
        pattern, `seam_length_mismatch`), ``seam_length_mismatch_truth`` (the true pattern's: the
        mismatch a design has on purpose, ease), ``body_height_error_m`` (fitted − true),
        ``body_mean_vertex_error_m``, ``bending_stiffness_ratio`` and ``stretch_stiffness_ratio``,
        ``rest_quality``, ``draped_quality`` (min, mean), ``inverted_rest_triangles`` (the fit's report);
        when the folder holds the fit's first drape (``draped_initial.obj``), also ``chamfer_scan_initial_m``
        and ``chamfer_truth_drape_initial_m``, the same two distances before the fit.
    """
    from torch_diffavatar.assets import material_from_dict
    from torch_diffavatar.chamfer import surface_chamfer_m
    from torch_diffavatar.mesh_io import read_obj
    from torch_diffavatar.metrics import triangle_quality
    from torch_diffavatar.pattern.garmentcode import load_pattern
    from torch_diffavatar.scan import load_scan

    folder, gt = Path(assets_dir), Path(gt_dir)
    truth = gt / "truth"
    needed = (folder / "draped.obj", folder / "body.obj", gt / "scan.ply", truth / "pattern.json")
    for path in (*needed, truth / "material.json", truth / "draped.obj", truth / "body.obj"):
        if not path.is_file():
            raise InputError(f"{path} is missing (ASSETS_DIR: a fit's output; --gt: a make-scan output)")
    true_material = material_from_dict(read_json_file(truth / "material.json", f"{truth}: no material.json"))
    out: dict = {"units": "m"}
    draped = read_obj(folder / "draped.obj")
    # a simulated depth capture's file is in its own units and axes (truth.json "capture"; captured_scans)
    capture = (
        read_json_file(truth / "truth.json", "").get("capture", {})
        if (truth / "truth.json").is_file()
        else {}
    )
    scan = load_scan(gt / "scan.ply", units=capture.get("units", "m"), up=capture.get("up", "y"), check=False)
    if scan.labels is None:
        raise InputError(f"{gt / 'scan.ply'} has no 'label' property: is --gt a make-scan output?")
    garment_points = torch.as_tensor(scan.points[scan.labels == 1])
    true_drape = read_obj(truth / "draped.obj")
    drapes = {"": draped}
    if (folder / "draped_initial.obj").is_file():
        drapes["_initial"] = read_obj(folder / "draped_initial.obj")
    for suffix, mesh in drapes.items():
        scan_distance = surface_chamfer_m(mesh.verts, mesh.faces, garment_points)
        out[f"chamfer_scan{suffix}_m"] = scan_distance["symmetric"]
        out[f"chamfer_truth_drape{suffix}_m"] = mesh_distance_m(
            mesh.verts, mesh.faces, true_drape.verts, true_drape.faces
        )
    # what a perfect fit scores against this scan: noise, and true cloth under holes far from any point
    floor = surface_chamfer_m(true_drape.verts, true_drape.faces, garment_points)
    out["chamfer_scan_truth_m"] = floor["symmetric"]
    true_pattern = load_pattern(truth / "pattern.json")
    out.update(compare_with_truth(folder, true_pattern, truth_material=true_material))
    out["seam_length_mismatch"] = seam_length_mismatch(load_pattern(folder / "pattern.json"))
    # the design's own (ease: GarmentCode's trousers take 24 mm more back than front at the crotch)
    out["seam_length_mismatch_truth"] = seam_length_mismatch(true_pattern)
    body, true_body = read_obj(folder / "body.obj"), read_obj(truth / "body.obj")
    height = lambda v: float(v[:, 1].max() - v[:, 1].min())  # noqa: E731
    out["body_height_error_m"] = height(body.verts) - height(true_body.verts)
    if body.verts.shape == true_body.verts.shape:  # same Anny topology: vertex to vertex
        out["body_mean_vertex_error_m"] = float((body.verts - true_body.verts).norm(dim=1).mean())
    q_draped = triangle_quality(draped.verts, draped.faces)
    out["draped_quality"] = {"min": float(q_draped.min()), "mean": float(q_draped.mean())}
    rest = read_obj(folder / "rest.obj")
    if rest.uv is not None:
        q_rest = triangle_quality(rest.uv, rest.uv_faces)
        out["rest_quality"] = {"min": float(q_rest.min()), "mean": float(q_rest.mean())}
    report = folder / "report.json"
    if report.is_file():
        out["inverted_rest_triangles"] = read_json_file(report, "").get("inverted_rest_triangles")
    return out


DRAPE_PICTURE = "eval_drapes.png"


def _facing_deg(body_json: Path) -> float:
    """The azimuth [deg] of a camera in front of the body of an asset folder's ``body.json``
    (`body.facing.body_facing_yaw`); 0 (the +Z camera) when it holds no global orientation."""
    from torch_diffavatar.body.facing import body_facing_yaw

    if not body_json.is_file():
        return 0.0
    orient = read_json_file(body_json, f"{body_json} is missing").get("global_orient_axis_angle")
    return (
        0.0 if orient is None else body_facing_yaw(torch.tensor(orient, dtype=torch.float64).reshape(-1)[:3])
    )


def save_drape_comparison(assets_dir, gt_dir, path, *, size: int = 320, frame: float = 0.1) -> Path:
    """A PNG of the fit's first drape, its result and the true drape, each from the front and the back (of
    the fitted body, whichever way it faces the scan's frame).

    All six views share one camera per side, so sizes compare: the box around the three garments, grown
    by ``frame`` [m] (the body beyond it is cut off). The first drape (``draped_initial.obj``, left out
    when missing) and the result are drawn on the fitted body (the asset folder keeps no other), the
    truth on the true body. A title names each pair.

    Args:
        assets_dir: a ``diffavatar fit`` output; gt_dir: a ``diffavatar make-scan`` output.
        path: the PNG to write.
        size: width of one view [px] (height 5/4 of it).

    Returns:
        ``path``.

    Raises:
        InputError: a mesh is missing.
    """
    import numpy as np
    from PIL import Image, ImageDraw

    from torch_diffavatar.mesh_io import read_obj
    from torch_diffavatar.render import CLOTH_COLOR, CLOTH_DEPTH_BIAS, RenderMesh, look_at_camera, render

    folder, truth = Path(assets_dir), Path(gt_dir) / "truth"
    for where, what in ((folder, "ASSETS_DIR: a fit's output"), (truth, "--gt: a make-scan output")):
        for name in ("draped.obj", "body.obj"):
            if not (where / name).is_file():
                raise InputError(f"{where / name} is missing ({what})")
    body, true_body = read_obj(folder / "body.obj"), read_obj(truth / "body.obj")
    columns = []
    if (folder / "draped_initial.obj").is_file():
        columns.append(("first drape", read_obj(folder / "draped_initial.obj"), body))
    columns += [
        ("fitted", read_obj(folder / "draped.obj"), body),
        ("truth", read_obj(truth / "draped.obj"), true_body),
    ]
    scenes = [
        [
            RenderMesh(b.verts.numpy(), b.faces.numpy()),
            RenderMesh(c.verts.numpy(), c.faces.numpy(), CLOTH_COLOR, CLOTH_DEPTH_BIAS),
        ]
        for _, c, b in columns
    ]
    cloth = np.concatenate([scene[1].verts for scene in scenes])
    lo, hi = cloth.min(0) - frame, cloth.max(0) + frame  # the garments fill the views; the body is cut
    width, height, title = size, size * 5 // 4, 16
    views = []
    front = _facing_deg(folder / "body.json")
    for scene in scenes:
        for view in (front, front + 180.0):
            camera = look_at_camera(lo, hi, view, width=width, height=height)
            views.append(render(scene, width=width, height=height, camera=camera))
    image = Image.fromarray(np.concatenate(views, axis=1))
    canvas = Image.new("RGB", (image.width, image.height + title), "white")
    canvas.paste(image, (0, title))
    draw = ImageDraw.Draw(canvas)
    for k, (name, _, _) in enumerate(columns):
        draw.text((2 * k * width + 4, 2), f"{name} (front, back)", fill=(0, 0, 0))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        canvas.save(tmp)
    return path


OVERLAY_COLOURS = {"template": (150, 150, 150), "truth": (0, 150, 0), "result": (210, 30, 30)}


def save_pattern_overlay(patterns: dict, path, scale: float = 400.0) -> None:
    """A PNG of patterns drawn over each other, panel by panel in each panel's own 2D frame.

    Args:
        patterns: name -> `Pattern` with the same panels; ``"template"``, ``"truth"`` and ``"result"``
            get grey, green and red (`OVERLAY_COLOURS`), others black; later ones are drawn on top.
        path: output PNG.
        scale: pixels per metre.
    """
    import numpy as np
    from PIL import Image, ImageDraw

    names = list(next(iter(patterns.values())).panels)
    boxes = []
    for panel in names:
        pts = np.concatenate([p.panels[panel].outline() for p in patterns.values()])
        boxes.append((pts.min(0), pts.max(0)))
    pad = 12
    # each panel's column is as wide as the panel or its name, whichever is wider (names of narrow
    # panels such as collars ran into the next one's)
    label = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    columns = [max(scale * (hi[0] - lo[0]), label.textlength(panel)) for panel, (lo, hi) in zip(names, boxes)]
    width = int(sum(c + pad for c in columns)) + pad
    height = int(max(scale * (hi[1] - lo[1]) for lo, hi in boxes)) + 2 * pad + 16
    img = Image.new("RGB", (width, height), "white")
    draw = ImageDraw.Draw(img)
    x0 = pad
    for panel, (lo, _hi), column in zip(names, boxes, columns):
        for key, pattern in patterns.items():
            o = pattern.panels[panel].outline() - lo
            pts = [(x0 + scale * x, height - pad - scale * y) for x, y in o]
            draw.polygon(pts, outline=OVERLAY_COLOURS.get(key, (0, 0, 0)), width=2)
        draw.text((x0, 2), panel, fill=(0, 0, 0))
        x0 += column + pad
    with atomic_path(path) as tmp:
        img.save(tmp)
