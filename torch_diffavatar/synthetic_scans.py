"""Synthetic clothed scans with ground truth: a template with a changed design, draped by our simulator on
an Anny body with chosen phenotypes and pose, degraded like a real capture.

`make_draped_scan` drapes the garment at a finer spacing than fits use, samples the cloth surface and the
skin that the cloth does not cover (area-uniform), cuts holes (round holes over ``hole_fraction`` of the
points, and one under each arm, where real scanners see nothing), optionally drops the bottom of the
scan (feet and floor), and adds Gaussian noise. `write_scan` writes the labelled scan (``scan.ply``:
``x y z label``, label 1 = garment, 0 = skin) and the ground truth beside it (``truth/``: the changed
pattern, the body OBJ and parameters, the material, the draped garment OBJ, ``truth.json``).

Design changes act on the pattern's hem (the panel corners on the garment's bottom openings, found on
the meshed template: ``hem``, ``hem_left``, ``hem_right``): ``hem_up`` raises them in their panels
(shorter), ``hem_widen`` spreads them about their panel's hem centre (more flare).

With ``simulator="newton"`` the truth is not our simulator's: our drape (sewn and placed) is settled
again by NVIDIA Newton's VBD cloth (`sim_newton`) with a random material drawn from the seed
(`sim_newton.draw_material`), and ``truth/material.json`` holds that material in our units. A waist-held
garment (skirt, trousers) starts ``waist_drop`` lower and its waist is pinned there, as long as its
pattern makes it (`sim_newton`).

``diffavatar make-scan TEMPLATE --out DIR [--seed S] [--simulator newton] [...] --json`` is the command.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from torch_diffavatar.errors import InputError
from torch_diffavatar.json_io import write_json
from torch_diffavatar.pattern.design import changed_pattern

# Default range of the random phenotypes of `make_draped_scan` (each of the six, uniform).
DEFAULT_PHENOTYPE_RANGE = (0.35, 0.65)
# ``--pose random`` draws from seed + this offset, apart from the phenotypes' draws.
POSE_SEED_OFFSET = 1000
# The Newton truth's material and waist drop draw from seed + this offset (the scan's own draws unchanged).
NEWTON_SEED_OFFSET = 2000
SIMULATORS = ("ours", "newton")
# [m] range of the random waist drop of a waist-held garment under ``simulator="newton"``
WAIST_DROP_RANGE = (0.0, 0.08)


def covered_by(
    points: np.ndarray, normals: np.ndarray, cloth: np.ndarray, lateral: float = 0.02, depth: float = 0.12
) -> np.ndarray:
    """(N,) bool: a cloth vertex lies above the point (along its normal, within ``lateral`` of the line).

    Args:
        points: (N, 3) skin points [m]; normals: (N, 3) their outward unit normals; cloth: (C, 3) [m].
        lateral, depth: the cylinder searched above each point [m].
    """
    tree = cKDTree(cloth)
    out = np.zeros(len(points), dtype=bool)
    for i, nbrs in enumerate(tree.query_ball_point(points, depth)):
        if not nbrs:
            continue
        d = cloth[nbrs] - points[i]
        along = d @ normals[i]
        side = np.linalg.norm(d - along[:, None] * normals[i], axis=1)
        out[i] = bool(((along > 0) & (side < lateral)).any())
    return out


@dataclass
class DrapedScan:
    """A synthetic clothed scan and its ground truth.

    Attributes:
        points: (N, 3) float64 noisy scan points [m], world frame (Y up, feet on y = 0, facing +Z).
        labels: (N,) int64, 1 = garment, 0 = skin.
        pattern: the true (changed) `Pattern`; garment: its placed `GarmentMesh`.
        cloth_x: (Vs, 3) the noise-free draped garment [m] (sim vertices of ``garment``).
        body_vertices: (Vb, 3) float64 true body [m]; body_faces: (Fb, 3) int64.
        body_params: `BodyModel.parameters_dict` of the true body; height: its standing height [m].
        bend_stiffness: true bending stiffness [N·m].
        material: the true `ClothMaterial` (None: ``ClothMaterial(bend_stiffness=bend_stiffness)``).
        info: the settings and the drape's diagnostics (what `write_scan` puts in ``truth.json``).
    """

    points: np.ndarray
    labels: np.ndarray
    pattern: object
    garment: object
    cloth_x: np.ndarray
    body_vertices: np.ndarray
    body_faces: np.ndarray
    body_params: dict
    height: float
    bend_stiffness: float
    info: dict = field(default_factory=dict)
    material: object = None


def make_draped_scan(
    template: str,
    *,
    anny_model=None,
    seed: int = 0,
    phenotypes: dict[str, float] | torch.Tensor | None = None,
    pose: torch.Tensor | None = None,
    bend_stiffness: float = 2.0e-5,
    hem_up: float = 0.05,
    hem_widen: float = 0.1,
    spacing: float = 0.02,
    garment_points: int = 40000,
    body_points: int = 30000,
    noise: float = 0.003,
    hole_fraction: float = 0.1,
    underarm_holes: bool = True,
    missing_bottom: float = 0.0,
    simulator: str = "ours",
    waist_drop: float | None = None,
    floor: bool = True,
    newton_config=None,
) -> DrapedScan:
    """Drape a changed template on an Anny body and sample it like a real scan (see the module docstring).

    Args:
        template: a template name or GarmentCode JSON path (`pattern.resolve_pattern`).
        anny_model: from `body.anny_model.load_anny` (default: loaded here, float32).
        seed: seed of everything random.
        phenotypes: dict by name or (1, 6) tensor in [0, 1] (default: random, uniform in
            `DEFAULT_PHENOTYPE_RANGE`: a template is made for a size range, and a garment too small for
            its body cannot be sewn on it).
        pose: (1, K, 3) axis-angle of `BodyModel.pose_bones` [rad] (default: the A-pose).
        bend_stiffness: true bending stiffness [N·m]. spacing: drape mesh spacing [m] (finer than a fit's).
        hem_up [m], hem_widen [-]: the design change (`changed_pattern`).
        garment_points, body_points: samples on the cloth and on the uncovered skin (before holes). A
            real scanner gives far more; the cloth's 40k (about one per 4 mm on a dress) keep the scan ↔
            drape Chamfer's own floor from the point spacing near the noise (14k: a 6 mm floor).
        simulator: ``"ours"`` or ``"newton"``; waist_drop [m], newton_config (how VBD steps): `_final_drape`.
        floor: our drape and sewing on a floor at the soles (`DrapeConfig.floor`; else `below_floor_note`).
        noise: Gaussian noise sigma [m]. hole_fraction: fraction of the points cut away in round holes.
        underarm_holes: a 7 cm hole under each arm too. missing_bottom: none under this height [m] (0: off).

    Raises:
        SimulationError: the drape failed (the message says why). InputError: bad settings / no Newton.
    """
    from torch_diffavatar.body.anny_model import load_anny
    from torch_diffavatar.pattern.library import resolve_pattern

    capture = _Capture(garment_points, body_points, noise, hole_fraction, underarm_holes, missing_bottom)
    _check_settings(spacing, bend_stiffness, simulator, waist_drop, capture, newton_config)
    t0 = time.perf_counter()
    rng, gen = np.random.default_rng(seed), torch.Generator().manual_seed(seed)
    anny_model = load_anny(dtype=torch.float32) if anny_model is None else anny_model
    body, out, normals, height = _posed_body(anny_model, phenotypes, pose, gen)
    pattern = changed_pattern(resolve_pattern(template), hem_up, hem_widen)
    garment, result = _drape_on_body(pattern, body, out, spacing, bend_stiffness, floor)
    result.x, material, newton_info = _final_drape(
        simulator, garment, result, out, body, seed, bend_stiffness, waist_drop, newton_config
    )
    cloth, cloth_faces = result.x.double().numpy(), garment.sim_faces.numpy()
    bv, bf, bn = out.vertices[0].double().numpy(), body.faces.numpy(), normals.double().numpy()
    armpits = _armpits(out.joints[0].double().numpy(), anny_model.bone_labels)
    points, labels = capture.scan(cloth, cloth_faces, bv, bf, bn, armpits, rng)
    info = _truth_info(
        template, seed, hem_up, hem_widen, bend_stiffness, spacing, capture, body, height, labels, result, t0
    )
    return DrapedScan(
        points=points,
        labels=labels,
        pattern=pattern,
        garment=garment,
        cloth_x=cloth,
        body_vertices=bv,
        body_faces=bf,
        body_params=body.parameters_dict(),
        height=height,
        bend_stiffness=float(material.bend_stiffness),
        info=info | newton_info,  # with the Newton truth's keys ("simulator", "material", "newton")
        material=material,
    )


def below_floor_note(info: dict) -> str | None:
    """What a user should know when a truth's cloth (``truth.json``'s ``info``) hangs below the soles, else
    None. Drapes without a floor (``make_draped_scan(floor=False)``, `make-scan --no-floor`) let a garment
    too long for its body hang through it, and a capture, the floor in view, shows it cut off at the floor,
    shorter than its pattern. Trousers on a 1.32 m body hung 16.6 cm through it, and their fits shrank the
    body by 3.7-6.1 cm and the legs by 7 cm to match (docs/BENCHMARKS.md, "Trousers through the floor")."""
    below = float(info.get("drape", {}).get("below_floor_m", 0.0))
    if below <= 0.0:
        return None
    return (
        f"the draped {info['template']} hangs {below * 100:.1f} cm below the soles, through the floor "
        "(draped without one): a scan shows it cut off there, shorter than its pattern; drop --no-floor to "
        "drape on the floor"
    )


def _check_settings(
    spacing: float,
    bend_stiffness: float,
    simulator: str,
    waist_drop: float | None,
    capture,
    newton_config=None,
):
    """InputError for a bad setting of `make_draped_scan` (``capture``: its `_Capture`), or Newton missing
    (checked before any work)."""
    capture.check()
    for name, value in (("spacing", spacing), ("bend_stiffness", bend_stiffness)):
        if not value > 0:
            raise InputError(f"{name} must be > 0, got {value}")
    if simulator not in SIMULATORS:
        raise InputError(f"unknown simulator {simulator!r}; use one of {', '.join(SIMULATORS)}")
    if waist_drop is not None and (simulator != "newton" or not 0.0 <= waist_drop <= 0.3):
        raise InputError(
            f"waist_drop needs simulator='newton' and 0 <= waist_drop <= 0.3 m, got {waist_drop}"
        )
    if newton_config is not None and simulator != "newton":
        raise InputError(f"newton_config needs simulator='newton', got simulator={simulator!r}")
    if simulator == "newton":
        from torch_diffavatar.sim_newton import import_newton

        import_newton()


def _material_summary(material) -> dict:
    """``{field: float}`` of a `ClothMaterial`."""
    from torch_diffavatar.assets import material_dict

    return {k: v["value"] for k, v in material_dict(material).items()}


def _final_drape(
    simulator: str,
    garment,
    result,
    out,
    body,
    seed: int,
    bend_stiffness: float,
    waist_drop: float | None,
    newton_config=None,
):
    """The truth's final drape. ``"ours"``: our drape ``result`` of ``garment`` as it is, with our material
    of stiffness ``bend_stiffness`` [N·m]. ``"newton"``: it settled again on the `BodyModel` ``body``
    (``out``: its output) by Newton's VBD with a random material about ``bend_stiffness`` (`sim_newton`),
    drawn from ``seed`` + `NEWTON_SEED_OFFSET`; ``waist_drop`` [m]: how much lower a waist-held garment
    sits (None: random in `WAIST_DROP_RANGE`; 0 for other garments); ``newton_config``: how Newton's VBD
    steps (None: `sim_newton.NewtonDrapeConfig`'s defaults).

    Returns:
        (Vs, 3) float32 drape [m], the true `ClothMaterial` (our units), the extra ``truth.json`` keys.
    """
    from torch_diffavatar.sim.material import ClothMaterial

    if simulator == "ours":
        return result.x, ClothMaterial(bend_stiffness=bend_stiffness), {}
    from torch_diffavatar import sim_newton as sn
    from torch_diffavatar.chamfer import sample_surface, surface_chamfer_m

    rng = np.random.default_rng(seed + NEWTON_SEED_OFFSET)
    config = sn.NewtonDrapeConfig() if newton_config is None else newton_config
    body_verts, body_faces = out.vertices[0], body.faces
    model, uv = result.model, garment.vert_uv
    material, factors = sn.draw_material(rng, bend_stiffness)
    held = model.attach_vertices
    if waist_drop is None:
        waist_drop = float(rng.uniform(*WAIST_DROP_RANGE)) if len(held) else 0.0
    weight, length = sn.edge_geometry(model, uv)
    newton_material = sn.material_to_newton(material, weight, length)
    x0 = sn.lower_onto_body(result.x, waist_drop, body_verts, body_faces, material.thickness)
    # the waistband pinned where the lowered drape has it, as long as the pattern makes it (`sim_newton`)
    targets = x0[held.cpu()].numpy() if len(held) else None
    drape = sn.newton_drape(
        model, uv, x0, body_verts, body_faces, newton_material, config,
        attach_vertices=held, attach_targets=targets,
    )  # fmt: skip
    strain_newton = sn.pattern_edge_strain(drape.x, model, uv)
    strain_ours = sn.pattern_edge_strain(result.x, model, uv)
    faces = garment.sim_faces
    ours_samples = sample_surface(
        result.x.double(), faces, 20000, generator=torch.Generator().manual_seed(seed)
    )
    chamfer = surface_chamfer_m(drape.x, faces, ours_samples)["symmetric"]
    record = {
        "raw": newton_material.summary(),
        "conversion": "torch_diffavatar.sim_newton: k_uu = k_vv = tri_ka + 2 tri_ke, k_uv = tri_ke, "
        "poisson = tri_ka / (tri_ka + 2 tri_ke); bend_stiffness = edge_ke |e| / (3|e|^2/(A1+A2))",
        "solver": "SolverVBD (stable Neo-Hookean membrane, dihedral bending, penalty contact + friction)",
        "steps": {"substeps_per_frame": config.substeps, "iterations_per_step": config.iterations},
        "draws": factors,
        "waist_drop_m": waist_drop,
        "waist_pinned_vertices": int(len(held)),
        "drape": drape.diagnostics(),
        "edge_strain": {"newton": sn.strain_summary(strain_newton), "ours": sn.strain_summary(strain_ours)},
        "chamfer_to_ours_drape_m": float(chamfer),
    }
    info = {"simulator": "newton", "material": dict(_material_summary(material), unit="SI (ClothMaterial)")}
    return drape.x.float(), material, dict(info, newton=record)


@dataclass(frozen=True)
class _Capture:
    """How the synthetic scanner samples and degrades the draped scene (see `make_draped_scan`).

    Attributes:
        garment_points, body_points: samples on the cloth and on the uncovered skin, before holes.
        noise: Gaussian noise sigma [m].
        hole_fraction: fraction of the points cut away in round holes, in [0, 1).
        underarm_holes: also cut a 7 cm hole under each arm.
        missing_bottom: drop points below this height [m] (0: keep all).
    """

    garment_points: int
    body_points: int
    noise: float
    hole_fraction: float
    underarm_holes: bool
    missing_bottom: float

    def check(self) -> None:
        """InputError for a setting out of its range."""
        if not 0.0 <= self.hole_fraction < 1.0 or self.noise < 0 or self.missing_bottom < 0:
            raise InputError("need 0 <= hole_fraction < 1, noise >= 0 and missing_bottom >= 0")
        for name, value in (("garment_points", self.garment_points), ("body_points", self.body_points)):
            if not (isinstance(value, int) and value >= 100):
                raise InputError(f"{name} must be an integer >= 100, got {value!r}")

    def scan(
        self,
        cloth: np.ndarray,
        cloth_faces: np.ndarray,
        body_vertices: np.ndarray,
        body_faces: np.ndarray,
        body_normals: np.ndarray,
        armpits: np.ndarray,
        rng: np.random.Generator,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Sample the cloth (C, 3) [m] (faces (Fc, 3)) and the skin it does not cover (body (Vb, 3) [m],
        faces (Fb, 3), unit vertex normals (Vb, 3)), cut the holes (the underarm ones about ``armpits``
        (2, 3) [m]) and add the noise; every draw from ``rng``.

        Returns:
            (N, 3) float64 points [m]; (N,) int64 labels, 1 = garment, 0 = skin.
        """
        from torch_diffavatar.body.synthetic import hole_mask

        points, labels = _sample_surfaces(
            cloth,
            cloth_faces,
            body_vertices,
            body_faces,
            body_normals,
            self.garment_points,
            self.body_points,
            rng,
        )
        keep = (
            hole_mask(points, self.hole_fraction, rng)
            if self.hole_fraction > 0
            else np.ones(len(points), bool)
        )
        if self.underarm_holes:
            for armpit in armpits:
                keep &= np.linalg.norm(points - armpit, axis=1) > 0.07
        if self.missing_bottom > 0:
            keep &= points[:, 1] > self.missing_bottom
        points, labels = points[keep], labels[keep]
        return points + rng.normal(0.0, self.noise, points.shape), labels

    def info(self) -> dict:
        """The settings recorded in ``truth.json`` (after the spacing, before the point counts)."""
        return {
            "noise_sigma_m": self.noise,
            "hole_fraction": self.hole_fraction,
            "underarm_holes": self.underarm_holes,
            "missing_bottom_m": self.missing_bottom,
        }


def _posed_body(anny_model, phenotypes, pose: torch.Tensor | None, gen: torch.Generator):
    """The true body (``phenotypes`` and ``pose`` as in `make_draped_scan`; random phenotypes drawn
    from ``gen``), feet on the floor.

    Returns:
        the `BodyModel`, its output (vertices (1, Vb, 3) [m], joints), (Vb, 3) unit vertex normals and
        its standing height [m].
    """
    from torch_diffavatar.body.geometry import vertex_normals
    from torch_diffavatar.body.model import BodyModel

    body = BodyModel(anny_model=anny_model)
    if phenotypes is None:
        lo, hi = DEFAULT_PHENOTYPE_RANGE
        phenotypes = (lo + (hi - lo) * torch.rand(1, 6, generator=gen)).float()
    body.set_phenotypes(phenotypes)
    with torch.no_grad():
        if pose is not None:
            body.pose.copy_(pose.to(body.pose))
        verts = body().vertices[0]
        body.translation[0, 1] -= verts[:, 1].min()  # feet on the floor
        out = body()
        normals = vertex_normals(out.vertices[0], body.faces)
        height = float(body.standing_height()[0])
    return body, out, normals, height


def _drape_on_body(pattern, body, out, spacing: float, bend_stiffness: float, floor: bool):
    """Mesh ``pattern`` at ``spacing`` [m], place it on the posed ``body`` (``out``: its output), sew and
    drape it with ``bend_stiffness`` [N·m] (on a floor at the soles with ``floor``). Returns (the placed
    `GarmentMesh`, the drape's result)."""
    from torch_diffavatar.pattern import mesh_pattern
    from torch_diffavatar.sim.forward_drape import DrapeConfig, sew_and_drape
    from torch_diffavatar.sim.material import ClothMaterial
    from torch_diffavatar.sim.placement import a_pose_route, place_garment

    verts = out.vertices[0]
    mesh = mesh_pattern(pattern, spacing=spacing)
    garment = place_garment(mesh, verts.double(), body.faces, arm_joints=body.arm_joints(out.joints[0]))
    material = ClothMaterial(bend_stiffness=bend_stiffness)
    route = a_pose_route(mesh, body)
    result = sew_and_drape(
        garment, body_verts=verts, body_faces=body.faces, fallback=route, material=material,
        config=DrapeConfig(floor=floor),
    )  # fmt: skip
    return garment, result


def _sample_surfaces(
    cloth: np.ndarray,
    cloth_faces: np.ndarray,
    body_vertices: np.ndarray,
    body_faces: np.ndarray,
    body_normals: np.ndarray,
    garment_points: int,
    body_points: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform samples of the cloth and of the skin it does not cover (`covered_by`); see
    `_Capture.scan` for the arguments. Returns (N, 3) points [m], cloth first, and (N,) int64 labels."""
    from torch_diffavatar.body.synthetic import sample_surface

    g_pts, _, _ = sample_surface(cloth, cloth_faces, garment_points, rng)
    b_pts, b_face, _ = sample_surface(body_vertices, body_faces, 2 * body_points, rng)
    b_n = body_normals[body_faces[b_face]].mean(1)
    b_n /= np.linalg.norm(b_n, axis=1, keepdims=True)
    b_pts = b_pts[~covered_by(b_pts, b_n, cloth)][:body_points]
    points = np.concatenate([g_pts, b_pts])
    labels = np.concatenate([np.ones(len(g_pts), np.int64), np.zeros(len(b_pts), np.int64)])
    return points, labels


def _armpits(joints: np.ndarray, bone_labels: list[str]) -> np.ndarray:
    """(2, 3) [m] the centres of the holes under the left and the right arm, below and behind the
    shoulders (``joints`` (J, 3) [m], named by ``bone_labels``)."""
    out = []
    for side in ("L", "R"):
        shoulder = joints[bone_labels.index(f"upperarm01.{side}")]
        out.append(shoulder + np.array([-0.03 * np.sign(shoulder[0]), -0.08, 0.0]))
    return np.stack(out)


def _truth_info(
    template: str,
    seed: int,
    hem_up: float,
    hem_widen: float,
    bend_stiffness: float,
    spacing: float,
    capture: _Capture,
    body,
    height: float,
    labels: np.ndarray,
    result,
    t0: float,
) -> dict:
    """The settings and the drape's diagnostics of `make_draped_scan` (``truth.json``): its arguments,
    the true `BodyModel` ``body`` and its ``height`` [m], the scan's (N,) ``labels``, the drape's
    ``result`` and ``t0``, the `time.perf_counter` at its start."""
    return {
        "template": template,
        "seed": seed,
        "design_change": {"hem_up_m": hem_up, "hem_widen": hem_widen},
        "phenotypes": dict(zip(body.phenotype_labels, body.phenotypes[0].tolist())),
        # The bones off the A-pose, axis-angle [rad] (`BodyModel`'s pose convention).
        "pose_rad": {b: r for b, r in zip(body.pose_bones, body.pose[0].tolist()) if any(r)},
        "height_m": height,
        "material": {"bend_stiffness": bend_stiffness, "unit": "N*m"},
        "spacing_m": spacing,
        **capture.info(),
        "points": {"garment": int(labels.sum()), "body": int((labels == 0).sum())},
        "drape": {
            "frames": int(result.steps + result.diagnostics.get("sew_steps", 0)),
            "converged": bool(result.converged),
            "max_stitch_gap_m": float(result.diagnostics.get("max_stitch_gap_m", 0.0)),
            "penetrating_count": int(result.diagnostics.get("penetrating_count", 0)),
            # sewn on the body's A-pose and carried to its pose, after sewing on the pose failed
            "sewn_in_a_pose": "fallback_after" in result.diagnostics,
            # how far the cloth hangs below the soles (y = 0): through the floor, when our drape has none
            "below_floor_m": max(0.0, -float(result.x[:, 1].min())),
            "floor": bool(result.diagnostics.get("floor", False)),
        },
        "seconds": round(time.perf_counter() - t0, 2),
    }


def write_scan(scan: DrapedScan, out_dir, *, capture=None) -> dict[str, str]:
    """Write ``scan.ply`` and ``truth/`` (see the module docstring) into ``out_dir``; returns the paths.

    ``capture``: a `capture.CapturedScan` of ``scan`` (`captured_scans.capture_draped_scan`), written as
    ``scan.ply`` instead of ``scan.points`` (binary, with colours and normals, in its own units and axes).
    """
    from torch_diffavatar.assets import material_dict
    from torch_diffavatar.mesh_io import write_obj
    from torch_diffavatar.pattern import save_pattern
    from torch_diffavatar.scan import save_ply
    from torch_diffavatar.sim.material import ClothMaterial

    out = Path(out_dir)
    truth = out / "truth"
    truth.mkdir(parents=True, exist_ok=True)
    paths = {
        "scan": out / "scan.ply",
        "pattern": truth / "pattern.json",
        "body_obj": truth / "body.obj",
        "body_json": truth / "body.json",
        "material": truth / "material.json",
        "draped_obj": truth / "draped.obj",
        "truth": truth / "truth.json",
    }
    if capture is None:
        save_ply(paths["scan"], scan.points, int_properties={"label": scan.labels})
    else:
        labels = {"label": capture.labels}
        save_ply(
            paths["scan"],
            capture.points,
            colors=capture.colors,
            normals=capture.normals,
            int_properties=labels,
            binary=True,
        )
    save_pattern(scan.pattern, paths["pattern"])
    write_obj(paths["body_obj"], scan.body_vertices, scan.body_faces)
    write_json(paths["body_json"], scan.body_params)
    material = ClothMaterial(bend_stiffness=scan.bend_stiffness) if scan.material is None else scan.material
    write_json(paths["material"], material_dict(material))
    write_obj(paths["draped_obj"], scan.cloth_x, scan.garment.sim_faces.numpy())
    write_json(paths["truth"], scan.info)
    return {k: str(v) for k, v in paths.items()}
