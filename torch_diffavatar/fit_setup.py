"""The set-up of a fit to a scan: the scan, the initial body, the scan garment's points and openings, and
the template meshed and placed on the body (`prepare`); what a garment is (`infer_garment_type`).

`prepare` is the slow part of ``diffavatar fit`` (`torch_diffavatar.fit_scan.fit_scan`): load the scan
(per-point garment labels used when present), fit the Anny body to it (`body.fit.fit_body`, or start from
given body parameters), segment the garment when the scan is not labelled (`body.segment.segment_garment`),
find the garment's openings on the body (the segmentation's boundary loops: neck, hem, cuffs, waist …) and
match them to the template's named loops, and mesh and place the template (`sim.placement.place_garment`).
Its result builds a `FitParameters` and a `FitObjective` (``scripts/fit_loop.py``) or a `Fitter`.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
import torch

from torch_diffavatar.errors import InputError, SimulationError

if TYPE_CHECKING:
    from torch_diffavatar.fit_design import HemDesign
    from torch_diffavatar.pattern import GarmentMesh, Pattern
    from torch_diffavatar.sim.forward_drape import PoseRoute

# Template name -> segmentation garment type (`body.segment.GARMENT_TYPES`).
SEGMENT_TYPES = {
    "dress": "dress",
    "dress_pencil": "dress",
    "longsleeve": "shirt",
    "tshirt": "tshirt",
    "polo": "polo",
    "skirt": "skirt",
    "pants": "pants",
    "shorts": "pants",
}
# Garment (segmentation) type -> the bundled config a GarmentCode file of that type is fitted with.
TYPE_CONFIGS = {
    "dress": "dress",
    "shirt": "longsleeve",
    "tshirt": "tshirt",
    "polo": "polo",
    "skirt": "skirt",
    "pants": "pants",
    # a jumpsuit hangs from its shoulders: the tops' 40 substeps (on a jumpsuit scan with pants.yaml's 10
    # the fit softened k_b to 0.13x and bent the sleeves: outline 2.78 / 5.81 cm, against 1.24 / 4.76)
    "jumpsuit": "longsleeve",
    "jumpsuit_sleeveless": "dress",
}
LONG_SLEEVE = 0.45  # [m] a sleeve reaching farther than this from the shoulder point is a long one
GARMENT_LABEL = 1  # label of the garment's points in a labelled scan (0 = body / not garment)


def infer_garment_type(pattern) -> str:
    """The garment type (a key of `TYPE_CONFIGS`) of a pattern, from where its panels go on the body.

    GarmentCode lays panels out around its mean body; `sim.placement` reads that layout into panel kinds
    (torso, arm, leg, collar-like panels attached to a partner). Legs: ``pants``, or ``jumpsuit`` (with
    sleeves) and ``jumpsuit_sleeveless`` when the panels reach above the waist too; nothing above the waist:
    ``skirt``; panels reaching below the crotch: ``dress`` (with or without sleeves); sleeves: ``polo``
    with an attached collar, else ``shirt`` when a sleeve reaches farther than `LONG_SLEEVE` from the
    shoulder point, else ``tshirt``; otherwise ``dress`` (a sleeveless top: the dress's body regions and
    armholes fit it). On the bundled templates it gives `SEGMENT_TYPES`.
    """
    from torch_diffavatar.pattern.mesher import mesh_pattern
    from torch_diffavatar.sim.placement import GC_BODY, _attachments, _panel_kinds

    garment = mesh_pattern(pattern, spacing=0.05)  # coarse: only the layout matters
    pos = garment.vert_pos.detach().cpu().numpy().astype(np.float64)
    kinds = _panel_kinds(garment, pos)
    panel_kind = np.array(kinds)[garment.vert_panel.cpu().numpy()]
    above_waist = pos[:, 1].max() >= GC_BODY["waist"] + 0.05
    arm = np.char.startswith(panel_kind.astype(str), "arm")
    if any(k.startswith("leg") for k in kinds):
        if not above_waist:
            return "pants"
        return "jumpsuit" if arm.any() else "jumpsuit_sleeveless"
    if not above_waist:
        return "skirt"
    if pos[:, 1].min() < GC_BODY["crotch"]:
        return "dress"
    if arm.any():
        if _attachments(garment, kinds):
            return "polo"
        reach = np.hypot(
            np.abs(pos[arm, 0]) - GC_BODY["shoulder_half_width"], pos[arm, 1] - GC_BODY["shoulder"]
        )
        return "shirt" if reach.max() > LONG_SLEEVE else "tshirt"
    return "dress"


def covers_head(garment, reach: float = 0.1) -> bool:
    """Whether a garment covers the head (a hood): ``garment``, a `GarmentMesh` as `mesh_pattern` lays it
    out around GarmentCode's mean body (before placement), reaches within ``reach`` [m] of the body's top
    (GarmentCode's hoody: 14 cm above it; a polo's collar, the highest of the others: 14 cm below)."""
    from torch_diffavatar.sim.placement import GC_BODY

    return float(garment.vert_pos[:, 1].max()) > GC_BODY["height"] - reach


def scan_boundaries(
    points: np.ndarray,
    garment_mask: np.ndarray,
    body_verts: np.ndarray,
    body_faces: np.ndarray,
    vertex_parts: np.ndarray,
    segment_type: str,
) -> dict[str, np.ndarray]:
    """The scan garment's openings, named as the garment mesh names its own (``neck``, ``cuff_left`` …).

    Uses the body package's boundary finder (loops of the covered body region, named by the body part
    just outside): opening name -> (k, 3) scan points [m] in loop order.
    """
    from scipy.spatial import cKDTree

    from torch_diffavatar.body import segment

    finder = getattr(segment, "boundary_loops", None) or segment._boundary_loops
    _, near = cKDTree(body_verts).query(points)
    loops = finder(points, garment_mask, near, body_verts, body_faces, vertex_parts, segment_type)
    garment_idx = np.flatnonzero(garment_mask)
    return {loop.name: points[garment_idx[loop.point_indices]] for loop in loops}


def match_boundaries(garment, scan_loops: dict[str, np.ndarray], max_distance: float = 0.2) -> dict:
    """Map scan openings to the garment's loop names.

    A scan opening goes to the garment loop of its name (the segmentation names openings as the garment
    mesh does); the scan openings left over are matched to the garment's unmatched loops (``opening_k``
    …) by nearest centroid (placed garment, within ``max_distance`` [m]).

    Returns:
        garment loop name -> (k, 3) float64 tensor of scan points [m].
    """
    garment_names = [lp.name for lp in garment.boundary_loops]
    out, left = {}, {}
    for name, pts in scan_loops.items():
        if name in garment_names:
            out[name] = torch.as_tensor(pts, dtype=torch.float64)
        else:
            left[name] = pts
    pos = garment.sim_positions().double()
    free = [lp for lp in garment.boundary_loops if lp.name not in out]
    for pts in left.values():
        if not free:
            break
        c = torch.as_tensor(pts, dtype=torch.float64).mean(0)
        dist = [float((pos[lp.vertices].mean(0) - c).norm()) for lp in free]
        k = int(np.argmin(dist))
        if dist[k] < max_distance:
            out[free.pop(k).name] = torch.as_tensor(pts, dtype=torch.float64)
    return out


def arms_spacing(config, arm_angles: dict[str, float]) -> float:
    """The mesh spacing [m] of a fit: ``config.arms_low_spacing`` when it is set, finer than
    ``config.spacing``, and an upper arm stands less than ``config.arms_low_angle`` from the torso
    (``arm_angles``: `BodyModel.upper_arm_angles`, degrees); else ``config.spacing``."""
    finer = config.arms_low_spacing
    if finer is None or finer >= config.spacing or min(arm_angles.values()) >= config.arms_low_angle:
        return config.spacing
    return finer


def remesh_for_arms(pattern, mesh, config, arm_angles: dict[str, float]):
    """(mesh, spacing [m]): ``mesh`` (``pattern`` meshed at ``config.spacing``), or ``pattern`` meshed again
    at `arms_spacing` when the body's upper arms (``arm_angles`` [deg]) call for a finer one (said on
    stderr)."""
    from torch_diffavatar.pattern import mesh_pattern

    spacing = arms_spacing(config, arm_angles)
    if spacing == config.spacing:
        return mesh, spacing
    print(
        f"diffavatar fit: an upper arm hangs {min(arm_angles.values()):.0f}° from the torso (below "
        f"{config.arms_low_angle:g}°): meshing at {spacing:g} m instead of {config.spacing:g} m, since "
        "a coarser mesh crushes where the lowered arm presses the cloth flat",
        file=sys.stderr,
    )
    return mesh_pattern(pattern, spacing=spacing), spacing


def load_fit_scan(scan_path, *, units: str | None = "m", up: str | None = "y"):
    """The scan of a fit through the intake (`scan_intake.intake_scan`: ``units`` None: from the height,
    ``up`` None: from the floor; floor, clutter and outliers removed), its messages and warnings printed
    on stderr. Returns (the `Scan`, the intake's `IntakeReport`)."""
    import warnings

    from torch_diffavatar.scan import ScanWarning
    from torch_diffavatar.scan_intake import intake_scan

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ScanWarning)
        scan, report = intake_scan(scan_path, units=units, up=up)
    for message in report.messages:
        print(f"diffavatar fit: {message}", file=sys.stderr)
    for message in scan.warnings:
        print(f"diffavatar fit: warning: {message}", file=sys.stderr)
    return scan, report


def initial_body(body, scan, mesh, body_params: dict | None = None, workers: int = 1) -> float | None:
    """Set ``body`` (a `BodyModel`) to the fit's initial body: ``body_params`` (`BodyModel.parameters_dict`)
    when given, else fitted to the ``scan`` (`body.fit.fit_body` with ``workers``; not to the head's points
    when the garment ``mesh``, as `mesh_pattern` lays it out, covers it: `covers_head`). Returns the body
    fit's residual [m] (None with ``body_params``).

    Raises:
        InputError: ``body_params`` do not fit this body model.
    """
    from torch_diffavatar.body.fit import BodyFitConfig, fit_body

    if body_params is None:
        body_config = BodyFitConfig()
        if covers_head(mesh):  # a hood: the head's scan points are cloth, not skin
            body_config.skin_parts = tuple(p for p in body_config.skin_parts if p != "head")
        return fit_body(scan.points, body, config=body_config, workers=workers).chamfer_m
    try:
        body.load_parameters_dict(body_params)
    except (KeyError, ValueError, TypeError, RuntimeError) as exc:
        raise InputError(f"the given body parameters do not fit this BodyModel: {exc}") from exc
    return None


def garment_mask(
    scan, seg_type: str, body, body_out, faces: np.ndarray, parts: np.ndarray, use_colour: bool = True
):
    """(mask (N,) bool of the scan's garment points, whether the scan's labels gave it): the labels
    (`GARMENT_LABEL`) of a labelled scan, else `body.segment.segment_garment` of the garment type
    ``seg_type`` on the body (``body_out``: its `BodyOutput`; ``faces``, ``parts``: its triangles and
    vertex parts; ``use_colour``: `segment_garment`'s)."""
    if scan.labels is not None:
        return scan.labels == GARMENT_LABEL, True
    from torch_diffavatar.body.segment import segment_garment

    waist = body.waist_height(body_out.joints[0])
    body_verts = body_out.vertices[0].double().numpy()
    seg = segment_garment(
        scan.points,
        seg_type,
        body_verts,
        faces,
        parts,
        colors=scan.colors,
        support_top=waist,
        use_colour=use_colour,
    )
    return seg.labels, False


def scan_target(scan, mask: np.ndarray, boundaries: dict, coverage: dict | None, held: tuple[str, ...] = ()):
    """The `ScanTarget` of a fit: the (N,) bool ``mask``'s points of ``scan`` as the garment, the others
    as skin, the matched ``boundaries``, the sides the scan sees (``coverage["seen"]``) and the openings
    ``held`` at the start's length (`ScanTarget.held_openings`)."""
    from torch_diffavatar.objective import ScanTarget

    return ScanTarget(
        garment_points=torch.as_tensor(scan.points[mask]),
        boundaries=boundaries,
        body_points=torch.as_tensor(scan.points[~mask]),
        seen_sides=torch.tensor(coverage["seen"]) if coverage else None,
        held_openings=held,
    )


@dataclass
class DressedTemplate:
    """The template on the initial body (`dress_template`): ``pattern`` (the template, its hem set from the
    scan with ``FitConfig.hem_from_scan``), ``garment`` (meshed and placed), ``fallback`` (its
    `a_pose_route`), ``boundaries`` (the scan's openings matched to the garment's, `match_boundaries`) and
    ``design`` (`fit_design.HemDesign`: what the scan said of the hem, or None when not asked or no hem)."""

    pattern: Pattern
    garment: GarmentMesh
    fallback: PoseRoute | None
    boundaries: dict
    design: HemDesign | None = None


def dress_template(
    pattern, mesh, body, body_out, loops: dict, config, spacing: float, floor_cut=None
) -> DressedTemplate:
    """``mesh`` (``pattern`` meshed at ``spacing`` [m]) placed on the body facing its way, its openings
    matched to the scan's ``loops``; with ``config.hem_from_scan`` it is first sewn and draped once, and
    when the scan's hem lies higher or lower or traces a longer loop (`fit_design.hem_design`) the pattern
    is changed so (`pattern.design.changed_pattern`) and meshed and placed again. When that sewing fails,
    the template stays as it is (the fit's own first sewings may still succeed: `fit_start.first_states`).
    ``floor_cut``: (the scan's (P, 3) garment points [m], the intake's floor margin [m]) when the scan had a
    floor, for the hems its removal cut off (`fit_design.floor_cut_hems`; `floor_cut_inputs`)."""
    from torch_diffavatar.body.facing import body_facing_yaw
    from torch_diffavatar.fit_design import first_hem_drape, floor_cut_hems, hem_design
    from torch_diffavatar.pattern import mesh_pattern
    from torch_diffavatar.pattern.design import changed_pattern
    from torch_diffavatar.sim.placement import a_pose_route, place_garment_turned

    body_verts = body_out.vertices[0].double()
    yaw = body_facing_yaw(body.global_orient[0])  # a captured person faces any way (issue #29)
    arms = body.arm_joints(body_out.joints[0])

    def placed(pattern, mesh, design=None) -> DressedTemplate:
        garment = place_garment_turned(mesh, body_verts, body.faces, yaw, arm_joints=arms)
        fallback = a_pose_route(mesh, body, yaw)
        return DressedTemplate(pattern, garment, fallback, match_boundaries(garment, loops), design)

    dressed = placed(pattern, mesh)
    if not config.hem_from_scan:
        return dressed
    try:
        x = first_hem_drape(dressed.garment, body_verts, body.faces, config, fallback=dressed.fallback)
    except SimulationError as exc:
        print(f"diffavatar fit: the template's hem is not set from the scan ({exc})", file=sys.stderr)
        return dressed
    cut = {}
    if floor_cut is not None:
        cut = floor_cut_hems(dressed.garment, x, dressed.boundaries, *floor_cut, config.opening_length_bin)
    design = hem_design(dressed.garment, x, dressed.boundaries, config.opening_length_bin, cut)
    if design is None or not design.applied:
        return replace(dressed, design=design)
    print(f"diffavatar fit: {_hem_design_note(design)}", file=sys.stderr)
    changed = changed_pattern(pattern, design.hem_up, design.hem_widen, spacing=spacing)
    return placed(changed, mesh_pattern(changed, spacing=spacing), design)


def floor_cut_inputs(scan, mask: np.ndarray, intake) -> tuple | None:
    """(the (N,) bool ``mask``'s points of ``scan``, the garment's [m]; how far above the floor the intake
    removed every point [m], `scan_intake.floor_margin`) when the intake found a floor, else None."""
    from torch_diffavatar.scan_intake import floor_margin

    return None if intake.floor is None else (scan.points[mask], floor_margin(intake.floor["sigma_m"]))


def _held(design: HemDesign | None) -> tuple[str, ...]:
    """The hems that ``design`` measured on the legs above a floor that cut them off, held at the start's
    length in the fit (`ScanTarget.held_openings`; the template's where the legs traced no wider)."""
    return () if design is None else design.floor_cut


def _hem_design_note(design: HemDesign) -> str:
    """What `dress_template` changed of the template's hem (``design`` applied), in a sentence."""

    def where(up: float) -> str:
        return f"{abs(100 * up):.1f} cm {'above' if up > 0 else 'below'}"

    widen = f"{100 * design.hem_widen:.1f} % longer loop"
    if not design.loops:  # every hem cut off with the floor: their lengths alone
        hems = " and ".join(design.floor_cut)
        return (
            f"the garment reaches the floor and its {hems} are not in the scan; above the floor its legs "
            f"trace a {widen} than the template's: the fit starts from the template with its hem so"
        )
    waist = f", its waistband {where(design.waist_up)} the drape's," if design.waist_up else ""
    panels = f"{abs(100 * design.hem_up):.1f} cm {'shorter' if design.hem_up > 0 else 'longer'}"
    return (
        f"the scan's hem lies {where(design.hem_up + design.waist_up)} the template's first drape{waist} and "
        f"traces a {widen}: the fit starts from the template with its panels {panels} and its hem so"
    )


def prepare(
    scan_path,
    config,
    *,
    units="m",
    up="y",
    anny_model=None,
    pattern=None,
    garment_type=None,
    body_params=None,
    loaded_scan=None,
    workers=1,
) -> dict:
    """The slow set-up of a fit: scan, body fit, segmentation, openings, meshed and placed template.

    ``config.template`` is a template name or a GarmentCode file. ``pattern`` (a `Pattern`) starts the fit
    from it instead: an earlier fit's result, or a ground truth (`scripts/fit_checks.py` ``oracle``).
    ``garment_type`` (a key of `TYPE_CONFIGS`) drives the scan's segmentation and openings; default: the
    template's (`SEGMENT_TYPES`), else `infer_garment_type` of the pattern. ``body_params`` (a
    `BodyModel.parameters_dict`, e.g. the ``body.json`` of ``diffavatar fit-body`` or of an earlier fit, in
    the scan's world frame) is the body to start from instead of fitting one to the scan.

    ``loaded_scan``: the scan through the intake already (`load_fit_scan`'s). ``workers``: the body fit's
    (`initial_body`; the same set-up for any number). The pattern is meshed at ``config.spacing``, or at
    ``config.arms_low_spacing`` when the body holds an arm low (`arms_spacing`).

    Returns:
        a dict with ``garment`` (placed `GarmentMesh`), ``pattern``, ``target`` (`ScanTarget`),
        ``body_params`` (`BodyModel.parameters_dict` of the initial body), ``sewing_fallback`` (the
        garment's `a_pose_route` onto it, None in the A-pose), ``body_fit_chamfer_m`` (the body fit's
        residual [m]; None with ``body_params``), ``scan_points``, ``scan_coverage`` (the intake's
        `scan_intake.coverage`), ``scan_warnings`` (its doubts), ``scan_shift`` (`IntakeReport.shift`),
        ``labelled``, ``spacing`` (mesh [m]), ``upper_arm_angles_deg`` (initial body), ``setup_seconds``.
    """
    from torch_diffavatar.body.anny_model import load_anny
    from torch_diffavatar.body.model import BodyModel
    from torch_diffavatar.body.parts import vertex_parts
    from torch_diffavatar.pattern import mesh_pattern
    from torch_diffavatar.pattern.library import resolve_pattern

    t0 = time.perf_counter()
    scan, intake = load_fit_scan(scan_path, units=units, up=up) if loaded_scan is None else loaded_scan
    anny_model = load_anny(dtype=torch.float32) if anny_model is None else anny_model
    body = BodyModel(anny_model=anny_model)
    pattern = resolve_pattern(config.template) if pattern is None else pattern
    mesh = mesh_pattern(pattern, spacing=config.spacing)
    body_fit_chamfer_m = initial_body(body, scan, mesh, body_params, workers)
    with torch.no_grad():
        body_out = body()
        body_verts = body_out.vertices[0].double()
    arm_angles = body.upper_arm_angles(body_out.joints[0])
    mesh, spacing = remesh_for_arms(pattern, mesh, config, arm_angles)
    faces = body.faces.cpu().numpy()
    parts = vertex_parts(anny_model).cpu().numpy()
    seg_type = garment_type or SEGMENT_TYPES.get(config.template) or infer_garment_type(pattern)
    mask, labelled = garment_mask(scan, seg_type, body, body_out, faces, parts, config.segment_colour)
    if mask.sum() < 50:
        raise InputError(f"{scan_path}: only {int(mask.sum())} garment points; cannot fit a garment")
    loops = scan_boundaries(scan.points, mask, body_verts.numpy(), faces, parts, seg_type)
    floor_cut = floor_cut_inputs(scan, mask, intake)
    dressed = dress_template(pattern, mesh, body, body_out, loops, config, spacing, floor_cut)
    return {
        "garment": dressed.garment,
        "pattern": dressed.pattern,
        "hem_from_scan": None if dressed.design is None else dressed.design.as_dict(),
        "target": scan_target(scan, mask, dressed.boundaries, intake.coverage, _held(dressed.design)),
        "body_params": body.parameters_dict(),
        "sewing_fallback": dressed.fallback,
        "body_fit_chamfer_m": body_fit_chamfer_m,
        "scan_points": scan.point_count,
        "scan_coverage": intake.coverage,
        "scan_warnings": list(intake.warnings),
        "scan_floor": intake.floor,
        "scan_shift": intake.shift,
        "scan_boundaries": sorted(loops),
        "labelled": labelled,
        "spacing": spacing,
        "upper_arm_angles_deg": arm_angles,
        "setup_seconds": time.perf_counter() - t0,
    }
