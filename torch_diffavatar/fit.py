"""The fit (paper §4.2): pattern cage, body and bending stiffness optimised through the differentiable drape.

A standard ``torch.optim.Adam`` loop over `FitParameters` (control-cage handles ζ, body phenotypes /
translation / pose, log bending stiffness; one parameter group and learning rate each). Every iteration
drapes the garment with `torch_diffavatar.sim.differentiable.drape`, warm-started from the previous
equilibrium (the very first start state is a full `sew_and_drape` of the placed template; with several
``first_bend_scales`` the template is sewn once per scale, and the first drape's loss, or a race of
``first_race_iterations`` from each, picks the one the fit continues), computes

    loss = ρ·boundary + σ·interior + α·seam_length + β·curvature  (+ a weak phenotype prior)

(`LossWeights`, terms of `torch_diffavatar.losses`), backpropagates through the drape and steps. The
terms of the rest pattern alone (seam length, curvature, rest area and shape) are cheap and known in closed
form, so the cage's step is proximal for them: Adam steps on the rest, and L-BFGS minimises them around
its result (`Fitter.rest_prox`, ``FitConfig.rest_prox_iterations``).

Guards: non-finite gradient entries are zeroed (counted, never reach the parameters); a step that would
shrink a rest triangle below ``min_rest_area_ratio`` of its template area (inverting it), make a
parameter non-finite, or blow up the drape (`SimulationError`, non-finite positions, a vertex jumping
more than ``max_drape_jump``) is rejected and retried at half the size (``max_retries`` times; then the
step is dropped and the learning rates halved). TensorBoard (``<out>/tb``): every loss term, Chamfer
distance, rest/draped mesh quality, bending stiffness, body parameters, pictures of the pattern and the
drape, the draped mesh. A tqdm bar on stderr. A checkpoint (``<out>/checkpoint.pt``, atomic) after every
iteration; ``resume=True`` continues from it bit for bit.

Units: metres, kilograms, seconds; the report's Chamfer distance is measured on the draped *surface*
(`chamfer.surface_chamfer_m`, [m], not squared: the symmetric average of scan → surface and surface
samples → scan), so it does not depend on the mesh's resolution; the boundary Chamfers and the logged
``chamfer/interior_m`` are vertex-based mean nearest-neighbour distances [m]; loss terms are in the units
of `torch_diffavatar.losses` times their weights.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
import re
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from torch import nn

from torch_diffavatar.cage import ControlCage, FreeVertices, seam_segments
from torch_diffavatar.chamfer import ROBUST_KERNELS, nearest_indices, surface_chamfer_m
from torch_diffavatar.errors import InputError, SimulationError
from torch_diffavatar.losses import (
    boundary_loss,
    curvature_loss,
    folded_collar_loop,
    interior_loss,
    rest_area_loss,
    rest_area_ratio,
    rest_distortion_loss,
    seam_length_loss,
    signed_rest_areas,
    skin_loss,
    template_edge_inverse,
)
from torch_diffavatar.metrics import triangle_quality
from torch_diffavatar.pattern.garment_mesh import BoundaryLoop, GarmentMesh
from torch_diffavatar.sim.drape import SEW_MAX_STRAIN, DrapeConfig, PoseRoute
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.model import ClothModel, ClothModelBuilder
from torch_diffavatar.sim.solver import XPBDConfig
from torch_diffavatar.sim.state import ClothState

CONFIG_DIR = Path(__file__).resolve().parent / "configs"  # shipped in the package (wheel included)
CHECKPOINT = "checkpoint.pt"
SETUP = "setup.pt"
# strain limit of every drape of a fit, the sewing's (see `Fitter.drape_config` for why it is above the
# solver's 3)
FIT_MAX_STRAIN = SEW_MAX_STRAIN
# a draped triangle below this quality (`metrics.triangle_quality`) is flagged in the fit's report: the
# evaluation's target for a simulation-ready drape (docs/RESULTS.md)
DRAPED_QUALITY_FLOOR = 0.3

# ---------------------------------------------------------------------------------------------------------
# Configuration


@dataclass(frozen=True)
class LossWeights:
    """Weights of the fit loss terms (paper §4.2.5). Each weight times its term is dimensionless-ish.

    Attributes:
        boundary: ρ [1/m²], times `boundary_loss` (mean squared distance of the openings) [m²].
        interior: σ [1/m²], times `interior_loss` (two-sided squared Chamfer) [m²].
        seam_length: α [1/m⁴], times `seam_length_loss` (squared differences of squared lengths) [m⁴].
        curvature: β [1/m²], times `curvature_loss` (boundary Laplacian residual) [m²].
        phenotype_prior: [-], times the squared distance of the phenotypes from the initial body fit's.
        rest_shape: [-], times `rest_distortion_loss` (rest triangles sheared beyond a conformal
            distortion of 0.25 against the template).
        skin: [1/m²], times `skin_loss` (mean squared distance of the scan's skin points to the body),
            when the body is optimized and the target has skin points.
        rest_area: [-], times `rest_area_loss` (rest triangles shrinking below half their template
            area).
    """

    boundary: float = 1.0e4
    interior: float = 1.0e4
    seam_length: float = 1.0e7
    curvature: float = 1.0e5
    phenotype_prior: float = 1.0
    rest_area: float = 1.0e3
    rest_shape: float = 100.0
    skin: float = 3.0e5

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"LossWeights.{f.name} must be a finite number >= 0, got {value!r}")


@dataclass(frozen=True)
class FitConfig:
    """Everything a fit needs besides its inputs (YAML files in ``configs/`` fill it, see `load_config`).

    Attributes:
        template: garment template to start from (`torch_diffavatar.pattern.list_templates`).
        spacing: mesh edge length [m] of the fitted garment.
        arms_low_spacing: mesh edge length [m] used instead of ``spacing`` when the fitted body holds an
            upper arm within ``arms_low_angle`` degrees of its torso (`BodyModel.upper_arm_angles`; None:
            never). A lowered arm presses the cloth against it flat, and a 2.5 cm mesh there crushes
            triangles: on four tops with arms held low, draped quality 0.07-0.24 at 2.5 cm, 0.13-0.54 at
            2 cm (three of four above 0.3), and three of the four end closer to the scan
            (docs/BENCHMARKS.md, "Arms held low"). Not used in the A-pose (42°), where the finer mesh
            is no closer, and slower.
        arms_low_angle: the threshold of ``arms_low_spacing`` [degrees].
        iterations: optimisation iterations (one drape + one backward each).
        lr_cage: Adam step of the cage handles [m].
        lr_phenotypes: Adam step of the body phenotype logits [-] (0 freezes the body shape).
        lr_translation: Adam step of the body translation [m] (0 freezes it).
        lr_pose: Adam step of the body pose [rad] (0 freezes it).
        lr_log_bend_stiffness: Adam step of log k_b [-] (0 freezes the material).
        initial_bend_stiffness: k_b at the start [N·m]. Set it near the fabric's when known: Adam's steps
            of ``lr_log_bend_stiffness`` (0.15, decaying) move log k_b by about 2.5 (×12) in 30 iterations
            at most. A dress 20× stiffer than 5e-6 moved ×5.6 and ended at 0.28× its k_b, 13.1 mm from the
            scan; started at its k_b, at 6.0 mm (docs/BENCHMARKS.md, "A stiff dress").
        weights: the loss weights.
        adjoint: ``"trajectory"`` or ``"equilibrium"`` (see `sim.differentiable.drape`).
        drape_steps: frames of every warm-started drape [-]. Trajectory adjoint: exactly this many (the
            drape is a function of the parameters, not of a stopping test; the adjoint replays every
            substep of every frame, so its cost is ∝ ``drape_steps · drape_substeps``). Equilibrium
            adjoint: at most this many, stopping once the drape has settled (``DrapeConfig`` speed test).
        polish_iterations: equilibrium adjoint only: Newton steps that polish the drape to the energy's
            minimiser before the solve (0: the XPBD drape as it settled) [-].
        adjoint_hessian: equilibrium adjoint only: ``"projected"`` (PSD element Hessians, solvable on
            drapes that are not exact minimisers) or ``"exact"`` (`EquilibriumOptions.hessian`).
        drape_substeps: XPBD substeps per frame of the fit's drapes [-].
        first_max_steps: frames at most of the first (sew and) drape [-].
        first_bend_scales: the first drape is sewn and draped once per entry, with the bending stiffness
            scaled by it, then each is settled at the fit's own stiffness; the one with the lowest loss
            (or the race's winner, ``first_race_iterations``) starts the fit [-]. Cloth that hangs loose
            on a body rests in more than one fold state, and which one a sewing reaches depends on its
            path: stiffer cloth while sewing reaches other fold states. Measured on the tops' true
            patterns (docs/RESULTS_HISTORY.md): the lowest-loss candidate of (1, 3, 10) landed 0.9-8.0 mm
            closer to the true drape than the plain sewing. ``(1.0,)``: one sewing.
        first_race_iterations: with several ``first_bend_scales``, the fit runs this many iterations from
            every candidate sewing and continues from the one whose lowest loss is the lowest [-]. A fold
            state and the pattern that suits it are found together, so the first drape's loss alone can
            pick the wrong one (measured: the T-shirt's 10× sewing starts at a higher loss than the 1×
            one, and its fit ends lower, 13.2 against 15.8). The cost is one fit of this length per extra
            sewing. 0: the first drape's loss decides.
        max_scan_points: scan garment points used by the interior loss, and skin points used by the skin
            loss (a fixed random subset of each) [-].
        interior_to_surface: the interior loss's scan → garment direction measures the distance to the
            draped surface (`interior_loss` with ``garment_faces``), not to the nearest vertex [-].
        boundary_robust, interior_robust: penalty kernel of the point distances in the boundary and in
            the interior loss (``"l2"``, ``"huber"`` or ``"geman_mcclure"``, `chamfer.robust_penalty`);
            robust_scale: the kernels' scale [m].
        boundary_trim: fraction of the largest point distances left out of each direction of each
            opening's Chamfer (`boundary_loss` ``trim``): scan openings pick up the rims of nearby holes [-].
        boundary_samples: points per loop edge of the boundary loss (`boundary_loss` samples_per_edge).
        min_rest_area_ratio: a step is rejected when a rest triangle's signed area falls below this
            fraction of its template area [-].
        max_drape_jump: a step is rejected when a cloth vertex moves more than this between two
            successive drapes [m].
        max_retries: halvings of a rejected step before it is dropped [-].
        max_loss_rise: a step is rejected when the total loss after it exceeds the loss before it by more
            than this fraction [-] (``inf``: no check). Adam's first steps move every handle by about its
            learning rate whatever its gradient, far beyond the range where the drape is linear in the
            pattern (measured on the T-shirt: the loss 35 → 2,870 after one step); a step accepted only
            after halvings also shrinks the later steps (``lr_scale``), which regrows by 1.25× per step
            accepted whole, up to 1. When every halving fails the step is dropped, and the next step's
            trials drape from the accepted drape's start instead of its end state (``trial_from_start``).
        lr_final: every learning rate decays along a cosine from its value at the first iteration to
            ``lr_final`` times that value at the last one [-] (1: constant).
        rest_prox_iterations: L-BFGS iterations of the proximal step of the cage handles (`Fitter.step`):
            Adam steps on the drape's terms only, and the terms of the rest pattern alone (seam length,
            curvature, rest area and shape) are then minimised around Adam's result, in Adam's own
            metric [-]. 0: one Adam step on the whole loss. Adam's first step moves every handle by its
            learning rate, whatever its gradient; the curvature term, which has no gradient at the
            template, then rose 17× the whole loss on a T-shirt fit and stalled it (docs/RESULTS_HISTORY.md).
        keep_best: the fit's result is the iteration with the lowest loss (its drape reproduced from its
            own start), not the last one. ``max_loss_rise`` lets single steps raise the loss, and a drape
            can jump to another rest state on a small pattern change (measured: a T-shirt fit's loss
            14.3 → 16.1 in one accepted step, and it ended at 15.6).
        cage: parameterise the pattern by a `ControlCage` (the method); False optimises every panel
            vertex's rest coordinate directly (`cage.FreeVertices`, the paper's "w/o cage" ablation).
        tie_mirrored, tie_seams: `ControlCage` tying options (ignored without the cage).
        tie_close: consecutive cage handles of a panel closer than this move together
            (`ControlCage` ``tie_close``) [m]; 0 leaves them free.
        image_every: iterations between TensorBoard pictures (0: only first and last).
        seed: seed of the scan subsampling.
    """

    template: str = "dress"
    spacing: float = 0.025
    arms_low_spacing: float | None = None
    arms_low_angle: float = 30.0
    iterations: int = 20
    lr_cage: float = 0.004
    lr_phenotypes: float = 0.02
    lr_translation: float = 0.002
    lr_pose: float = 0.0
    lr_log_bend_stiffness: float = 0.1
    initial_bend_stiffness: float = 5.0e-6
    weights: LossWeights = field(default_factory=LossWeights)
    adjoint: str = "trajectory"
    drape_steps: int = 3
    polish_iterations: int = 0
    adjoint_hessian: str = "projected"
    drape_substeps: int = 10
    first_max_steps: int = 400
    first_bend_scales: tuple[float, ...] = (1.0,)
    first_race_iterations: int = 0
    max_scan_points: int = 4000
    interior_to_surface: bool = True
    boundary_robust: str = "l2"
    interior_robust: str = "l2"
    robust_scale: float = 0.01
    boundary_trim: float = 0.0
    boundary_samples: int = 2
    min_rest_area_ratio: float = 0.1
    max_drape_jump: float = 0.15
    max_retries: int = 3
    max_loss_rise: float = 0.1
    lr_final: float = 1.0
    rest_prox_iterations: int = 50
    keep_best: bool = True
    cage: bool = True
    tie_mirrored: bool = True
    tie_seams: bool = True
    tie_close: float = 0.01
    image_every: int = 5
    seed: int = 0

    def __post_init__(self):
        from torch_diffavatar.sim.adjoint import ADJOINTS
        from torch_diffavatar.sim.adjoint.equilibrium import HESSIANS

        if not isinstance(self.weights, LossWeights):
            raise ValueError(f"FitConfig.weights must be a LossWeights, got {type(self.weights).__name__}")
        if self.adjoint not in ADJOINTS:
            raise ValueError(f"FitConfig.adjoint must be one of {sorted(ADJOINTS)}, got {self.adjoint!r}")
        if self.adjoint_hessian not in HESSIANS:
            raise ValueError(f"FitConfig.adjoint_hessian must be one of {HESSIANS}: {self.adjoint_hessian!r}")
        if not self.spacing > 0:
            raise ValueError(f"FitConfig.spacing must be a positive length [m], got {self.spacing}")
        if self.arms_low_spacing is not None and not self.arms_low_spacing > 0:
            raise ValueError(
                f"FitConfig.arms_low_spacing must be > 0 [m] or null, got {self.arms_low_spacing}"
            )
        if not 0 <= self.arms_low_angle <= 180:
            raise ValueError(f"FitConfig.arms_low_angle must be in [0, 180] [deg], got {self.arms_low_angle}")
        if not self.initial_bend_stiffness > 0:
            raise ValueError(
                f"FitConfig.initial_bend_stiffness must be > 0 [N·m], got {self.initial_bend_stiffness}"
            )
        for name in (
            "iterations",
            "drape_steps",
            "drape_substeps",
            "first_max_steps",
            "max_scan_points",
            "polish_iterations",
            "boundary_samples",
            "rest_prox_iterations",
            "first_race_iterations",
        ):
            value = getattr(self, name)
            zero_ok = ("iterations", "polish_iterations", "rest_prox_iterations", "first_race_iterations")
            low = 0 if name in zero_ok else 1
            if not isinstance(value, int) or value < low:
                raise ValueError(f"FitConfig.{name} must be an integer >= {low}")
        scales = self.first_bend_scales
        if isinstance(scales, int | float) and not isinstance(scales, bool):
            scales = (scales,)
        if (
            not isinstance(scales, list | tuple)
            or not scales
            or not all(
                isinstance(s, int | float) and not isinstance(s, bool) and 0 < s < math.inf for s in scales
            )
        ):
            raise ValueError(
                f"FitConfig.first_bend_scales must be a non-empty list of positive numbers, got {scales!r}"
            )
        object.__setattr__(self, "first_bend_scales", tuple(float(s) for s in scales))  # YAML gives a list
        for name in ("boundary_robust", "interior_robust"):
            kernel = getattr(self, name)
            if kernel not in ROBUST_KERNELS:
                raise ValueError(f"FitConfig.{name} must be one of {ROBUST_KERNELS}, got {kernel!r}")
        if not 0.0 <= self.boundary_trim < 1.0:
            raise ValueError(f"FitConfig.boundary_trim must be in [0, 1), got {self.boundary_trim}")
        if not self.robust_scale > 0:
            raise ValueError(f"FitConfig.robust_scale must be a positive length [m], got {self.robust_scale}")
        if not 0 <= self.tie_close < math.inf:
            raise ValueError(f"FitConfig.tie_close must be a length >= 0 [m], got {self.tie_close}")
        if not self.max_loss_rise > 0:
            raise ValueError(f"FitConfig.max_loss_rise must be > 0 (inf: no check), got {self.max_loss_rise}")
        if not 0 < self.lr_final <= 1:
            raise ValueError(f"FitConfig.lr_final must be in (0, 1], got {self.lr_final}")
        for name in ("lr_cage", "lr_phenotypes", "lr_translation", "lr_pose", "lr_log_bend_stiffness"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"FitConfig.{name} must be >= 0 (0 freezes the parameter)")


def with_fit_strain_limit(config: DrapeConfig) -> DrapeConfig:
    """``config`` with the strain limit of a fit's drapes, `FIT_MAX_STRAIN`, while sewing and draping (a
    seam-corner triangle of a sewn template can pass the solver's default for a few frames)."""
    return replace(
        config,
        xpbd=replace(config.xpbd, max_strain=FIT_MAX_STRAIN),
        sew_xpbd=replace(config.sew_xpbd, max_strain=FIT_MAX_STRAIN),
    )


def _field_names(cls) -> list[str]:
    return [f.name for f in dataclasses.fields(cls)]


def config_from_dict(data: dict, base: FitConfig | None = None, source: str = "config") -> FitConfig:
    """A `FitConfig` from a (YAML) dict: keys are `FitConfig` fields, ``weights`` a dict of `LossWeights`.

    Raises:
        InputError: unknown keys (the message lists the valid ones) or invalid values.
    """
    base = FitConfig() if base is None else base
    if not isinstance(data, dict):
        raise InputError(f"{source}: expected a mapping of FitConfig fields, got {type(data).__name__}")
    unknown = sorted(set(data) - set(_field_names(FitConfig)))
    if unknown:
        raise InputError(f"{source}: unknown key(s) {unknown}; valid keys: {_field_names(FitConfig)}")
    values = dict(data)
    if "weights" in values:
        w = values["weights"] or {}
        if not isinstance(w, dict):
            raise InputError(f"{source}: 'weights' must be a mapping of {_field_names(LossWeights)}")
        bad = sorted(set(w) - set(_field_names(LossWeights)))
        if bad:
            raise InputError(
                f"{source}: unknown weights key(s) {bad}; valid keys: {_field_names(LossWeights)}"
            )
        try:
            values["weights"] = replace(base.weights, **{k: float(v) for k, v in w.items()})
        except (TypeError, ValueError) as exc:
            raise InputError(f"{source}: {exc}") from exc
    for f in dataclasses.fields(FitConfig):  # YAML gives ints for floats like 1; keep the field's type
        if f.name in values and f.name != "weights" and isinstance(getattr(base, f.name), float):
            if isinstance(values[f.name], int | float) and not isinstance(values[f.name], bool):
                values[f.name] = float(values[f.name])
    try:
        return replace(base, **values)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{source}: {exc}") from exc


def config_to_dict(config: FitConfig) -> dict:
    """Plain dict of a config (``weights`` nested), the inverse of `config_from_dict`."""
    return dataclasses.asdict(config)


def default_config_path(garment: str) -> Path | None:
    """The bundled config of a garment: ``configs/<garment>.yaml``; for a bundled template without one,
    the config of its kind (``dress_pencil`` → ``dress.yaml``, ``shorts`` → ``pants.yaml``: the bare
    `FitConfig` defaults are a quick, weak fit); else None."""
    from torch_diffavatar.pattern.library import list_templates, load_template

    own = CONFIG_DIR / f"{garment}.yaml"
    if own.is_file():
        return own
    if garment in list_templates():
        kind = CONFIG_DIR / f"{load_template(garment).garment_type}.yaml"
        if kind.is_file():
            return kind
    return None


def load_config(
    path: str | os.PathLike | None = None, *, garment: str | None = None, **overrides
) -> FitConfig:
    """Resolve a fit configuration.

    Args:
        path: a YAML file; when None, `default_config_path` of ``garment`` (with ``template = garment``),
            else the `FitConfig` defaults with ``template = garment``.
        garment: the garment type / template name (used when ``path`` is None).
        overrides: fields set last (e.g. ``iterations=5``; None values are ignored).

    Raises:
        InputError: missing file, malformed YAML, unknown keys, invalid values.
    """
    import yaml

    base = FitConfig() if garment is None else FitConfig(template=garment)
    if path is None and garment is not None:
        path = default_config_path(garment)
        if path is not None and path.stem != garment and overrides.get("template") is None:
            overrides["template"] = garment  # the config of its kind names that kind's template
    config = base
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise InputError(f"--config {path}: file not found")
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise InputError(f"{path}: malformed YAML ({exc})") from exc
        config = config_from_dict(data, base, source=str(path))
    overrides = {k: v for k, v in overrides.items() if v is not None}
    return config_from_dict(overrides, config, source="overrides") if overrides else config


# ---------------------------------------------------------------------------------------------------------
# Targets, parameters, guards


@dataclass
class ScanTarget:
    """What the garment is fitted to (world frame, metres).

    Attributes:
        garment_points: (P, 3) scan points of the garment.
        boundaries: garment opening name (``GarmentMesh.boundary_loops`` names) -> (k, 3) scan points.
        body_points: (Q, 3) the other scan points (skin), may be empty.
    """

    garment_points: torch.Tensor
    boundaries: dict[str, torch.Tensor] = field(default_factory=dict)
    body_points: torch.Tensor | None = None

    def __post_init__(self):
        g = self.garment_points
        if not isinstance(g, torch.Tensor) or g.dim() != 2 or g.shape[1] != 3 or g.shape[0] < 1:
            raise ValueError("ScanTarget.garment_points must be a (P, 3) tensor with P >= 1")
        if not torch.isfinite(g).all():
            raise ValueError("ScanTarget.garment_points hold NaN or infinite values")


class FitParameters(nn.Module):
    """The fit variables: a `ControlCage` (pattern), an optional `BodyModel`, the log bending stiffness.

    Args:
        cage: the pattern's control cage, or `FreeVertices` (its ``handles`` parameter is optimised).
        body: a `BodyModel` (batch 1) whose vertices are the drape's body, or None for a fixed body.
        log_bend_stiffness: initial log k_b (k_b in [N·m]).

    ``forward()`` returns ``(rest_uv (V, 2) [m], body_verts (Vb, 3) [m] or None, bend_stiffness () [N·m])``.
    """

    def __init__(self, cage: ControlCage, body: nn.Module | None, log_bend_stiffness: float):
        super().__init__()
        self.cage = cage
        self.body = body
        dtype = cage.handles.dtype
        self.log_bend_stiffness = nn.Parameter(torch.tensor(float(log_bend_stiffness), dtype=dtype))

    def forward(self):
        rest_uv = self.cage()
        body_verts = None if self.body is None else self.body().vertices[0]
        return rest_uv, body_verts, self.log_bend_stiffness.exp()


def param_groups(params: FitParameters, config: FitConfig) -> list[dict]:
    """Adam parameter groups (name, params, lr) of the parameters with a positive learning rate; the
    others are frozen (``requires_grad=False``)."""
    spec = [("cage", [params.cage.handles], config.lr_cage)]
    if params.body is not None:
        spec += [
            ("phenotypes", [params.body.phenotype_logits], config.lr_phenotypes),
            ("translation", [params.body.translation], config.lr_translation),
            ("pose", [params.body.pose], config.lr_pose),
        ]
    spec.append(("log_bend_stiffness", [params.log_bend_stiffness], config.lr_log_bend_stiffness))
    for p in params.parameters():
        p.requires_grad_(False)
    groups = []
    for name, ps, lr in spec:
        if lr > 0:
            for p in ps:
                p.requires_grad_(True)
            groups.append({"name": name, "params": ps, "lr": lr})
    return groups


def chamfer_m(x: torch.Tensor, y: torch.Tensor) -> float:
    """Symmetric mean nearest-neighbour distance [m] ``(mean_x d(x, Y) + mean_y d(y, X)) / 2``."""
    x, y = x.detach().double().cpu(), y.detach().double().cpu()
    dxy = (x - y[torch.from_numpy(nearest_indices(x, y))]).norm(dim=1).mean()
    dyx = (y - x[torch.from_numpy(nearest_indices(y, x))]).norm(dim=1).mean()
    return float(0.5 * (dxy + dyx))


# ---------------------------------------------------------------------------------------------------------
# The loop


@dataclass
class Evaluation:
    """One drape and its loss at the current parameters."""

    loss: torch.Tensor
    terms: dict[str, torch.Tensor]
    x: torch.Tensor
    rest_uv: torch.Tensor
    body_verts: torch.Tensor | None
    bend_stiffness: torch.Tensor
    stats: dict
    openings: list[BoundaryLoop]  # the garment's openings matched to the scan's, on x (`Fitter.openings`)


@dataclass
class FitResult:
    """Outcome of `Fitter.run`.

    Attributes:
        params: the fitted `FitParameters`; x: (Vs, 3) final drape [m]; rest_uv: (V, 2) [m];
        body_verts: (Vb, 3) [m] or None; history: one dict of scalars per iteration;
        report: the metrics (see `Fitter.report`).
    """

    params: FitParameters
    x: torch.Tensor
    rest_uv: torch.Tensor
    body_verts: torch.Tensor | None
    history: list[dict]
    report: dict


def _atomic_save(obj, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


class Fitter:
    """Runs the fit loop on one garment / body / scan target (see the module docstring).

    Args:
        garment: the meshed and placed template (float64 as built is fine; cast inside).
        target: the scan target.
        config: the fit configuration.
        body: a float32 `BodyModel` initialised to the scan (fitted in place), or None with
            ``body_mesh`` for a fixed body (or no body at all).
        body_mesh: (verts (Vb, 3), faces (Fb, 3)) of a fixed body, or None; with ``body``, only the faces
            are taken from ``body.faces``.
        material: the base cloth material (its bending stiffness is replaced by the fitted one).
        start_state: the first warm start (e.g. a `sew_and_drape` result's state); None runs
            `sew_and_drape` from the placement.
        sewing_fallback: how to dress the body when sewing the placed garment on it fails
            (`sew_and_drape`'s ``fallback``; `sim.placement.a_pose_route` for a posed body).
        out_dir: where checkpoints and TensorBoard logs go (None: nowhere).
        progress: show a tqdm bar on stderr.
        dtype: float32 for fits (float64 for tiny tests).
    """

    def __init__(
        self,
        garment: GarmentMesh,
        target: ScanTarget,
        config: FitConfig,
        *,
        body: nn.Module | None = None,
        body_mesh: tuple[torch.Tensor, torch.Tensor] | None = None,
        material: ClothMaterial | None = None,
        start_state: ClothState | None = None,
        sewing_fallback: PoseRoute | None = None,
        out_dir: str | os.PathLike | None = None,
        progress: bool = True,
        tensorboard: bool = True,
        dtype: torch.dtype = torch.float32,
    ):
        self.config = config
        self.dtype = dtype
        self.garment = garment
        self.template_uv = garment.vert_uv.to(dtype)
        # template constants of the rest-shape terms, evaluated ~60 times per step by `rest_prox`
        self._template_area = signed_rest_areas(self.template_uv, garment.tri_vertices)
        self._template_inverse = template_edge_inverse(self.template_uv, garment.tri_vertices)
        self.material = material if material is not None else ClothMaterial()
        self.model: ClothModel = ClothModelBuilder(self.material).add_garment(garment).finalize(dtype=dtype)
        if config.cage:
            cage = ControlCage(
                garment,
                tie_mirrored=config.tie_mirrored,
                tie_seams=config.tie_seams,
                tie_close=config.tie_close,
            )
        else:
            cage = FreeVertices(garment)
        cage = cage.to(dtype)
        self.params = FitParameters(cage, body, math.log(config.initial_bend_stiffness))
        if body is not None:
            self.body_faces = body.faces
            self.fixed_body = None
        elif body_mesh is not None:
            self.fixed_body = body_mesh[0].to(dtype)
            self.body_faces = body_mesh[1].to(torch.int64)
        else:
            self.fixed_body, self.body_faces = None, None
        self.phenotypes0 = None if body is None else body.phenotypes.detach().clone()
        self.seam_segments = seam_segments(garment)
        self.target = target
        gen = torch.Generator().manual_seed(config.seed)

        def subset(points: torch.Tensor) -> torch.Tensor:  # a fixed random subset of max_scan_points
            points = points.to(dtype)
            if points.shape[0] > config.max_scan_points:
                points = points[torch.randperm(points.shape[0], generator=gen)[: config.max_scan_points]]
            return points

        self.scan_points = subset(target.garment_points)
        skin = target.body_points
        self.skin_points = None if body is None or skin is None or skin.shape[0] == 0 else subset(skin)
        self.scan_boundaries = {k: v.to(dtype) for k, v in target.boundaries.items()}
        self.loops = [lp for lp in garment.boundary_loops if lp.name in self.scan_boundaries]
        self.out_dir = None if out_dir is None else Path(out_dir)
        self.progress = progress
        self.tensorboard = tensorboard and self.out_dir is not None
        self.groups = param_groups(self.params, config)
        for g in self.groups:
            g["base_lr"] = g["lr"]
        self.optimizer = torch.optim.Adam(self.groups)
        self.lr_scale = 1.0  # shrunk by rejected steps, regrown by steps accepted whole (see step)
        self.trial_from_start = False  # after a dropped step, trials drape from the accepted drape's start
        self.start_state = start_state
        self.sewing_fallback = sewing_fallback
        self.iteration = 0
        self.history: list[dict] = []
        self.rejected_steps = 0
        self.rejection_reasons: dict[str, int] = {}  # why steps were rejected: reason -> count
        self.nan_gradients = 0
        self.adjoint_failures = 0
        self.first: dict | None = None  # x, body_verts, loss terms, chamfer of the first evaluation
        self.best: dict | None = None  # iteration, loss, params and drape start of the lowest loss so far
        self.result_iteration = 0  # the iteration whose evaluation `run` returned (see `keep_best`)
        self.first_candidates: list[dict] = []  # bend scale and loss of each first drape (`_first_state`)
        self.seconds = 0.0

    # -- one evaluation ------------------------------------------------------------------------------------

    def _body(self):
        rest_uv, body_verts, kb = self.params()
        if body_verts is None:
            body_verts = self.fixed_body
        return rest_uv, body_verts, kb

    def drape_config(self, steps: int | None = None) -> DrapeConfig:
        """The fit's drape options: ``drape_steps`` frames (or ``steps``) of ``drape_substeps`` substeps;
        with the equilibrium adjoint, at most that many (it stops once the drape has settled)."""
        n = self.config.drape_steps if steps is None else steps
        # A few small triangles at a seam corner can sit far beyond the solver's default strain limit (3)
        # in a sane drape and would then reject every step: E = 3.0 on the 2 cm dress, E = 10-12 at the
        # shoulder tips of the long-sleeve shirt and the T-shirt, where four panels meet at 6 mm pattern
        # edges (72-81 rejections in 30 iterations at a limit of 10). The fit catches real blow-ups by
        # the speed limit and the `max_drape_jump` guard instead.
        xpbd = XPBDConfig(substeps=self.config.drape_substeps, iterations=1, max_strain=FIT_MAX_STRAIN)
        if self.config.adjoint == "equilibrium":
            return DrapeConfig(xpbd=xpbd, min_steps=min(5, n), max_steps=n)
        return DrapeConfig(xpbd=xpbd, min_steps=n, max_steps=n)

    def _first_drape_config(self) -> DrapeConfig:
        """Options of the first sew and drape: the defaults, with the fit's strain limit (see
        `drape_config`): sewing a template onto a fitted body can pull a seam-corner triangle past the
        default limit for a few frames (measured: E = 3.7 on a long-sleeve shirt) without a blow-up."""
        return with_fit_strain_limit(DrapeConfig(max_steps=self.config.first_max_steps))

    def adjoint_options(self):
        """`EquilibriumOptions` from the config (equilibrium adjoint), else None (the adjoint's defaults)."""
        if self.config.adjoint != "equilibrium":
            return None
        from torch_diffavatar.sim.adjoint import EquilibriumOptions

        cfg = self.config
        polish = cfg.polish_iterations > 0
        return EquilibriumOptions(
            newton_iterations=cfg.polish_iterations,
            active_set_rounds=EquilibriumOptions.active_set_rounds if polish else 1,
            hessian=cfg.adjoint_hessian,
            # measured on the 2k-vertex dress: sparse LU 0.26 s vs CG 0.83 s on the projected H
            solve_method="direct" if cfg.adjoint_hessian == "projected" else EquilibriumOptions.solve_method,
        )

    def evaluate(self, start: ClothState) -> Evaluation:
        """Drape from ``start`` at the current parameters and compute the loss (graph kept for backward).

        Raises:
            SimulationError: the drape blew up.
        """
        from torch_diffavatar.sim.differentiable import drape

        cfg = self.config
        rest_uv, body_verts, kb = self._body()
        material = replace(self.material, bend_stiffness=kb)
        stats: dict = {}
        x = drape(
            rest_uv,
            self.model,
            body_verts,
            material,
            body_faces=None if body_verts is None else self.body_faces,
            state=start,
            config=self.drape_config(),
            adjoint=cfg.adjoint,
            options=self.adjoint_options(),
            stats=stats,
        )
        w = cfg.weights
        faces = self.garment.sim_faces if cfg.interior_to_surface else None
        terms = {
            "interior": interior_loss(
                x, self.scan_points, garment_faces=faces, robust=cfg.interior_robust, scale=cfg.robust_scale
            )
        }
        openings = self.openings(x)
        if openings:
            terms["boundary"] = boundary_loss(
                x,
                openings,
                self.scan_boundaries,
                samples_per_edge=cfg.boundary_samples,
                robust=cfg.boundary_robust,
                scale=cfg.robust_scale,
                trim=cfg.boundary_trim,
            )
        terms.update(self.rest_terms(rest_uv))
        if self.phenotypes0 is not None and self.params.body.phenotype_logits.requires_grad:
            terms["phenotype_prior"] = ((self.params.body.phenotypes - self.phenotypes0) ** 2).sum()
        if self.skin_points is not None and w.skin > 0:
            terms["skin"] = skin_loss(
                body_verts,
                self.body_faces,
                self.skin_points,
                robust=cfg.interior_robust,
                scale=cfg.robust_scale,
            )
        loss = sum(getattr(w, k) * v for k, v in terms.items())
        return Evaluation(loss, terms, x, rest_uv, body_verts, kb, stats, openings)

    def openings(self, x: torch.Tensor) -> list[BoundaryLoop]:
        """The garment's openings matched to the scan's, on the drape ``x`` (Vs, 3): the loops, but a neck
        that a folded collar covers is its fold (`folded_collar_loop`), the top edge the scan shows."""
        return [folded_collar_loop(x, lp) if lp.name == "neck" else lp for lp in self.loops]

    def rest_terms(self, rest_uv: torch.Tensor) -> dict[str, torch.Tensor]:
        """The loss terms of the rest pattern alone, unweighted: seam length, curvature, and rest area and
        rest shape when their weights are positive. ``rest_uv``: (V, 2) [m]."""
        w = self.config.weights
        terms = {
            "seam_length": seam_length_loss(rest_uv, self.garment, segments=self.seam_segments),
            "curvature": curvature_loss(rest_uv, self.template_uv, self.garment),
        }
        tri = self.garment.tri_vertices
        if w.rest_area > 0:
            terms["rest_area"] = rest_area_loss(
                rest_uv, self.template_uv, tri, template_area=self._template_area
            )
        if w.rest_shape > 0:
            terms["rest_shape"] = rest_distortion_loss(
                rest_uv, self.template_uv, tri, template_inverse=self._template_inverse
            )
        return terms

    def rest_loss(self, handles: torch.Tensor | None = None) -> torch.Tensor:
        """The weighted sum of `rest_terms` at the cage ``handles`` (default: the parameter)."""
        w = self.config.weights
        return sum(getattr(w, k) * v for k, v in self.rest_terms(self.params.cage(handles)).items())

    def _cage_group(self) -> dict | None:
        """The cage's Adam group when the proximal rest step is on, else None."""
        if self.config.rest_prox_iterations == 0:
            return None
        return next((g for g in self.optimizer.param_groups if g["name"] == "cage"), None)

    def _drop_rest_gradient(self, handles: torch.Tensor) -> None:
        """Take the rest terms' gradient out of the handles' gradient: the proximal step handles them."""
        with torch.enable_grad():
            (grad,) = torch.autograd.grad(self.rest_loss(), handles)
        handles.grad = handles.grad - grad

    def rest_prox(self, group: dict) -> None:
        """Move the cage handles from Adam's result ĉ to argmin_c R(c) + ½ Σ m (c − ĉ)², R = `rest_loss`.

        m = (√v̂ + ε) / lr is the metric in which Adam's step is a gradient step (v̂ its bias-corrected second
        moment), so coordinates with a steady drape gradient keep Adam's move, and those Adam moved by
        its learning rate on a negligible gradient go where the rest terms want them. Solved by L-BFGS
        (``rest_prox_iterations``); a non-finite solution leaves Adam's result.
        """
        handles = group["params"][0]
        state = self.optimizer.state[handles]
        beta2 = group["betas"][1]
        vhat = state["exp_avg_sq"] / (1.0 - beta2 ** float(state["step"]))
        metric = (vhat.sqrt() + group["eps"]) / group["lr"]
        target = handles.detach().clone()
        c = target.clone().requires_grad_(True)
        lbfgs = torch.optim.LBFGS(
            [c],
            max_iter=self.config.rest_prox_iterations,
            line_search_fn="strong_wolfe",
            tolerance_grad=1e-9,
            tolerance_change=1e-12,
        )

        def closure():
            lbfgs.zero_grad()
            with torch.enable_grad():
                value = self.rest_loss(c) + 0.5 * (metric * (c - target) ** 2).sum()
                value.backward()
            return value

        lbfgs.step(closure)
        if torch.isfinite(c).all():
            with torch.no_grad():
                handles.copy_(c.detach())

    def _checked_evaluate(self, start: ClothState) -> Evaluation | None:
        """`evaluate`, or None when the drape blew up, jumped too far or gave non-finite values (the
        reason is counted in `rejection_reasons`)."""
        try:
            ev = self.evaluate(start)
        except SimulationError as exc:
            # the message without its advice and numbers, so that reasons of one kind count together
            reason = re.sub(r" [-+0-9.e]+(?= |$)", "", str(exc).split(" (")[0])
            return self._reject(f"drape failed: {reason}")
        if not (torch.isfinite(ev.x).all() and torch.isfinite(ev.loss)):
            return self._reject("non-finite drape or loss")
        if float((ev.x.detach() - start.x).norm(dim=1).max()) > self.config.max_drape_jump:
            return self._reject("drape jumped more than max_drape_jump")
        return ev

    def _loss_rose(self, before: Evaluation, after: Evaluation) -> bool:
        """True (and counted) when the loss of ``after`` exceeds that of ``before`` by more than allowed."""
        if float(after.loss.detach()) <= (1.0 + self.config.max_loss_rise) * float(before.loss.detach()):
            return False
        self._reject("loss rose more than max_loss_rise")
        return True

    def _reject(self, reason: str) -> None:
        self.rejection_reasons[reason] = self.rejection_reasons.get(reason, 0) + 1
        return None

    def _rest_ok(self) -> bool:
        with torch.no_grad():
            rest_uv = self.params.cage()
            if not torch.isfinite(rest_uv).all():
                return False
            ratio = rest_area_ratio(rest_uv, self.template_uv, self.garment.tri_vertices)
            return bool((ratio > self.config.min_rest_area_ratio).all())

    def _params_finite(self) -> bool:
        return all(bool(torch.isfinite(p).all()) for p in self.params.parameters())

    def _sanitize_grads(self) -> None:
        for g in self.groups:
            for p in g["params"]:
                if p.grad is not None and not torch.isfinite(p.grad).all():
                    self.nan_gradients += 1
                    p.grad = torch.nan_to_num(p.grad, nan=0.0, posinf=0.0, neginf=0.0)

    def _backward(self, ev: Evaluation, start: ClothState) -> Evaluation:
        """Backpropagate ``ev.loss``; if the adjoint fails, retry once with the trajectory adjoint."""
        self.optimizer.zero_grad(set_to_none=True)
        try:
            ev.loss.backward()
            return ev
        except SimulationError:
            self.adjoint_failures += 1
            if self.config.adjoint == "trajectory":
                raise
        self.optimizer.zero_grad(set_to_none=True)
        saved = self.config
        # a short trajectory replay: its cost grows with the frames, which the equilibrium mode does not cap
        self.config = replace(saved, adjoint="trajectory", drape_steps=min(saved.drape_steps, 3))
        try:
            ev = self.evaluate(start)
            ev.loss.backward()
        finally:
            self.config = saved
        return ev

    def lr_schedule(self, iteration: int) -> float:
        """Learning-rate factor of iteration ``iteration`` (0-based): a cosine from 1 to ``lr_final``."""
        total = max(self.config.iterations - 1, 1)
        t = min(iteration / total, 1.0)
        return self.config.lr_final + (1.0 - self.config.lr_final) * 0.5 * (1.0 + math.cos(math.pi * t))

    def step(self, ev: Evaluation, start: ClothState) -> tuple[Evaluation, ClothState, int]:
        """Backward, Adam step (the cage's with its `rest_prox`) and the guards; returns (next evaluation,
        its start state, rejections)."""
        ev = self._backward(ev, start)
        cage_group = self._cage_group()
        if cage_group is not None and cage_group["params"][0].grad is not None:
            self._drop_rest_gradient(cage_group["params"][0])
        else:
            cage_group = None
        self._sanitize_grads()
        for g in self.optimizer.param_groups:
            g["lr"] = g["base_lr"] * self.lr_scale * self.lr_schedule(self.iteration)
        params = [p for g in self.groups for p in g["params"]]
        before = [p.detach().clone() for p in params]
        self.optimizer.step()
        if cage_group is not None:
            self.rest_prox(cage_group)
        delta = [p.detach() - b for p, b in zip(params, before)]
        # trials continue from the accepted drape's end state, except after a dropped step: then they start
        # where the reproduced drape started, so the halvings probe the very map (start -> drape) whose
        # gradient was taken (on a T-shirt fit that stalls, rejected trials 95 -> 61 in 30 iterations; it
        # still stalls: docs/RESULTS_HISTORY.md)
        if self.trial_from_start:
            next_start = start
        else:
            next_start = ClothState(ev.x.detach(), torch.zeros_like(ev.x.detach()))
        rejected = 0
        scale = 1.0
        for _ in range(self.config.max_retries + 1):
            with torch.no_grad():
                for p, b, d in zip(params, before, delta):
                    p.copy_(b + scale * d)
            if not self._params_finite():
                self._reject("non-finite parameters")
            elif not self._rest_ok():
                self._reject("rest triangle below min_rest_area_ratio")
            else:
                new = self._checked_evaluate(next_start)
                if new is not None and not self._loss_rose(ev, new):
                    self.lr_scale = min(1.0, self.lr_scale * (1.25 if scale == 1.0 else scale))
                    self.trial_from_start = False
                    return new, next_start, rejected
            rejected += 1
            scale *= 0.5
        # every retry failed: drop the step, halve the learning rates, and drape the last accepted
        # parameters from that drape's own start, which gives the same drape again (a fresh graph for the
        # next backward). Continuing from its end state instead can land elsewhere when it had not settled
        # (measured: a T-shirt fit's loss 11.7 -> 14.5 there, with no step taken).
        with torch.no_grad():
            for p, b in zip(params, before):
                p.copy_(b)
        self.lr_scale *= 0.5
        self.trial_from_start = True
        new = self._checked_evaluate(start)
        if new is None:
            raise SimulationError("the drape fails even at the last accepted parameters")
        return new, start, rejected

    # -- logging -------------------------------------------------------------------------------------------

    def _scalars(self, ev: Evaluation) -> dict:
        w = self.config.weights
        out = {"loss/total": float(ev.loss.detach())}
        for k, v in ev.terms.items():
            out[f"loss/{k}"] = float(v.detach())
            out[f"loss_weighted/{k}"] = float(getattr(w, k) * v.detach())
        out["chamfer/interior_m"] = chamfer_m(ev.x, self.scan_points)
        for loop in ev.openings:
            out[f"chamfer/boundary_{loop.name}_m"] = chamfer_m(
                ev.x[loop.vertices], self.scan_boundaries[loop.name]
            )
        with torch.no_grad():
            q_rest = triangle_quality(ev.rest_uv.detach(), self.garment.tri_vertices)
            q_drape = triangle_quality(ev.x.detach(), self.garment.sim_faces)
            ratio = rest_area_ratio(ev.rest_uv.detach(), self.template_uv, self.garment.tri_vertices)
        out["quality/rest_min"] = float(q_rest.min())
        out["quality/rest_mean"] = float(q_rest.mean())
        out["quality/draped_min"] = float(q_drape.min())
        out["quality/draped_mean"] = float(q_drape.mean())
        out["quality/inverted_rest_triangles"] = int((ratio <= 0).sum())
        out["material/bend_stiffness"] = float(ev.bend_stiffness.detach())
        out["material/log_bend_stiffness"] = float(self.params.log_bend_stiffness.detach())
        body = self.params.body
        if body is not None:
            for label, value in zip(body.phenotype_labels, body.phenotypes[0].detach().tolist()):
                out[f"body/{label}"] = value
            for axis, value in zip("xyz", body.translation[0].detach().tolist()):
                out[f"body/translation_{axis}"] = value
        out["steps/rejected_total"] = self.rejected_steps
        out["steps/nan_gradients"] = self.nan_gradients
        for k in ("newton_force_residual", "forward_seconds", "backward_seconds"):
            if isinstance(ev.stats.get(k), int | float):
                out[f"drape/{k}"] = float(ev.stats[k])
        return out

    def _log(self, writer, ev: Evaluation, scalars: dict, it: int, images: bool) -> None:
        if writer is None:
            return
        for k, v in scalars.items():
            writer.add_scalar(k, v, it)
        if images:
            try:
                writer.add_image("drape", self._drape_image(ev), it, dataformats="HWC")
                writer.add_image("pattern", self._pattern_image(ev.rest_uv.detach()), it, dataformats="HWC")
                faces = self.garment.sim_faces
                writer.add_mesh(
                    "draped_mesh",
                    vertices=ev.x.detach()[None].float(),
                    faces=faces[None].int(),
                    global_step=it,
                )
            except Exception as exc:  # pictures are diagnostics: never let them stop a fit
                print(f"fit: could not log images ({exc})", file=sys.stderr)
        writer.flush()

    def _drape_image(self, ev: Evaluation) -> np.ndarray:
        from torch_diffavatar.render import CLOTH_COLOR, CLOTH_DEPTH_BIAS, RenderMesh, render_views

        meshes = [RenderMesh(ev.x.detach().cpu(), self.garment.sim_faces, CLOTH_COLOR, CLOTH_DEPTH_BIAS)]
        if ev.body_verts is not None:
            meshes.insert(0, RenderMesh(ev.body_verts.detach().cpu(), self.body_faces.cpu()))
        return render_views(meshes, views=("front", "back"), width=256, height=320)

    def _pattern_image(self, rest_uv: torch.Tensor, size: int = 512) -> np.ndarray:
        """The rest mesh of every panel, side by side, drawn with Pillow ((H, W, 3) uint8)."""
        from PIL import Image, ImageDraw

        uv = rest_uv.cpu().double().numpy()
        vert_panel = self.garment.vert_panel.cpu().numpy()
        offsets, x0 = [], 0.0
        for pid in range(len(self.garment.panel_names)):
            p = uv[vert_panel == pid]
            offsets.append((x0 - p[:, 0].min(), -p[:, 1].min()))
            x0 += p[:, 0].max() - p[:, 0].min() + 0.05
        pos = uv + np.array(offsets)[vert_panel]
        extent = max(pos[:, 0].max(), pos[:, 1].max(), 1e-6)
        s = (size - 20) / extent
        img = Image.new("RGB", (size, size), (255, 255, 255))
        draw = ImageDraw.Draw(img)
        for tri in self.garment.tri_vertices.cpu().numpy():
            pts = [(10 + s * pos[i, 0], size - 10 - s * pos[i, 1]) for i in tri]
            draw.polygon(pts, outline=(70, 110, 190))
        return np.asarray(img)

    # -- checkpoints ---------------------------------------------------------------------------------------

    def state_dict(self, start: ClothState) -> dict:
        return {
            "iteration": self.iteration,
            "params": self.params.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "start_x": start.x.detach().clone(),
            "start_v": start.v.detach().clone(),
            "history": list(self.history),
            "rejected_steps": self.rejected_steps,
            "rejection_reasons": dict(self.rejection_reasons),
            "nan_gradients": self.nan_gradients,
            "adjoint_failures": self.adjoint_failures,
            "lr_scale": self.lr_scale,
            "trial_from_start": self.trial_from_start,
            "first": self.first,
            "best": self.best,
            "first_candidates": self.first_candidates,
            "seconds": self.seconds,
            "config": config_to_dict(self.config),
        }

    def load_state_dict(self, state: dict) -> ClothState:
        self.params.load_state_dict(state["params"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.iteration = int(state["iteration"])
        self.history = list(state["history"])
        self.rejected_steps = int(state["rejected_steps"])
        self.rejection_reasons = dict(state.get("rejection_reasons", {}))
        self.nan_gradients = int(state["nan_gradients"])
        self.adjoint_failures = int(state.get("adjoint_failures", 0))
        self.lr_scale = float(state.get("lr_scale", 1.0))
        self.trial_from_start = bool(state.get("trial_from_start", False))
        self.first = state["first"]
        self.best = state.get("best")
        self.first_candidates = list(state.get("first_candidates", []))
        self.seconds = float(state.get("seconds", 0.0))
        return ClothState(state["start_x"].to(self.dtype), state["start_v"].to(self.dtype))

    def save_checkpoint(self, start: ClothState) -> None:
        if self.out_dir is not None:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            _atomic_save(self.state_dict(start), self.out_dir / CHECKPOINT)

    # -- the run -------------------------------------------------------------------------------------------

    def _settled(self, state: ClothState, rest_uv, body_verts, material) -> ClothState:
        """``state`` draped to rest with the fit's own substeps (at least 10 frames, `first_max_steps` at
        most), its velocities zeroed."""
        from torch_diffavatar.sim.drape import drape_to_equilibrium

        res = drape_to_equilibrium(
            self.model,
            rest_uv,
            body_verts=body_verts,
            body_faces=None if body_verts is None else self.body_faces,
            material=material,
            state=state,
            config=replace(self.drape_config(), min_steps=10, max_steps=self.config.first_max_steps),
        )
        return ClothState(res.x, torch.zeros_like(res.x))

    def _first_states(self) -> list[tuple[float, ClothState, dict]]:
        """The first warm starts, each settled with the fit's own substeps and stiffness (`_settled`), as
        (loss, state, its entry of ``first_candidates``), lowest loss first: ``start_state`` alone, or the
        template sewn and draped once per ``first_bend_scales`` (the bending stiffness scaled by it). With
        one start the loss is NaN (not evaluated). Each sewing's scale and loss (or error) go to
        ``first_candidates``.

        Raises:
            SimulationError: the sewing or the drape blew up (of every candidate, when there are several).
        """
        from torch_diffavatar.sim.drape import sew_and_drape

        scales = self.config.first_bend_scales
        with torch.no_grad():
            rest_uv, body_verts, kb = self._body()
            material = replace(self.material, bend_stiffness=float(kb))
            if self.start_state is not None:
                start = ClothState(self.start_state.x.to(self.dtype), self.start_state.v.to(self.dtype))
                return [(math.nan, self._settled(start, rest_uv, body_verts, material), {})]
            states, self.first_candidates = [], []
            for scale in scales:
                candidate = {"bend_scale": scale}
                self.first_candidates.append(candidate)
                try:
                    res = sew_and_drape(
                        self.garment,
                        rest_uv=rest_uv,
                        body_verts=body_verts,
                        body_faces=None if body_verts is None else self.body_faces,
                        fallback=self.sewing_fallback,
                        material=replace(material, bend_stiffness=float(kb) * scale),
                        config=self._first_drape_config(),
                        dtype=self.dtype,
                    )
                    if "fallback_after" in res.diagnostics:
                        candidate["sewn_in_a_pose"] = True
                    state = self._settled(res.state, rest_uv, body_verts, material)
                    if len(scales) == 1:  # nothing to choose; `run` evaluates it anyway
                        return [(math.nan, state, candidate)]
                    loss = candidate["loss"] = float(self.evaluate(state).loss)
                except SimulationError as exc:
                    if len(scales) == 1:
                        raise
                    candidate["error"] = str(exc)
                    continue
                if math.isfinite(loss):
                    states.append((loss, state, candidate))
        if not states:
            raise SimulationError(f"every first sewing of the template failed: {self.first_candidates}")
        return sorted(states, key=lambda ls: ls[0])

    def _first_state(self) -> ClothState:
        """The first warm start of the lowest loss (`_first_states`)."""
        return self._first_states()[0][1]

    def run(self, iterations: int | None = None, *, resume: bool = False) -> FitResult:
        """Run the loop up to ``iterations`` completed iterations (default ``config.iterations``).

        With ``resume``, continue from ``out_dir/checkpoint.pt`` when it exists (a fit stopped during
        ``first_race_iterations`` continues with the candidate it was fitting).
        """
        total = self.config.iterations if iterations is None else iterations
        t0 = time.perf_counter()
        start, starts = None, None
        if resume and self.out_dir is not None and (self.out_dir / CHECKPOINT).is_file():
            state = torch.load(self.out_dir / CHECKPOINT, weights_only=False)
            start = self.load_state_dict(state)
        if start is None:
            starts = self._first_states()
            start = starts[0][1]
        race = 0 if starts is None or len(starts) < 2 else min(self.config.first_race_iterations, total)
        writer = None
        if self.tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            writer = SummaryWriter(log_dir=str(self.out_dir / "tb"))
            writer.add_text("config", "```\n" + _yaml_dump(config_to_dict(self.config)) + "\n```", 0)
        bar = None
        if self.progress:
            from tqdm import tqdm

            runs = (len(starts) - 1) * race if race else 0
            bar = tqdm(
                total=total + runs, initial=min(self.iteration, total), desc="fit", unit="it", file=sys.stderr
            )
        try:
            if race:
                start = self._race(starts, race, bar)
                if writer is not None:  # the winner's iterations, which the race did not log
                    for entry in self.history:
                        for k, v in entry.items():
                            if k != "iteration":
                                writer.add_scalar(k, v, entry["iteration"])
            ev = self._checked_evaluate(start)
            if ev is None:
                raise SimulationError("the first drape of the fit failed (blow-up or non-finite values)")
            if self.first is None:
                self.first = self._summary(ev)
                self._log(writer, ev, self._scalars(ev), 0, images=True)
            elif race:  # the winner's pictures where its race ended
                self._log(writer, ev, self._scalars(ev), self.iteration, images=True)
            self._note_best(ev, start)
            self.seconds += time.perf_counter() - t0
            ev, start = self._iterate(ev, start, total, writer, bar)
        finally:
            if bar is not None:
                bar.close()
            if writer is not None:
                writer.close()
        t0 = time.perf_counter()
        ev = self._restore_best(ev)
        self.seconds += time.perf_counter() - t0
        final = self._summary(ev)
        return FitResult(
            params=self.params,
            x=ev.x.detach(),
            rest_uv=ev.rest_uv.detach(),
            body_verts=None if ev.body_verts is None else ev.body_verts.detach(),
            history=self.history,
            report=self.report(final),
        )

    def _iterate(self, ev: Evaluation, start: ClothState, until: int, writer=None, bar=None):
        """Fit steps until ``until`` iterations are done, logging, checkpointing and updating ``bar`` after
        each; returns the last (evaluation, start)."""
        t0 = time.perf_counter()
        while self.iteration < until:
            ev, start, rejected = self.step(ev, start)
            self.rejected_steps += rejected
            self.iteration += 1
            self._note_best(ev, start)
            scalars = self._scalars(ev)
            scalars["steps/rejected"] = rejected
            self.history.append({"iteration": self.iteration, **scalars})
            every = self.config.image_every
            last = self.iteration == until
            self._log(
                writer, ev, scalars, self.iteration, last or (every > 0 and self.iteration % every == 0)
            )
            self.seconds += time.perf_counter() - t0
            t0 = time.perf_counter()
            self.save_checkpoint(start)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(
                    loss=f"{scalars['loss/total']:.4g}",
                    chamfer_mm=f"{1e3 * scalars['chamfer/interior_m']:.2f}",
                )
        return ev, start

    def _race(self, starts: list[tuple[float, ClothState, dict]], iterations: int, bar=None) -> ClothState:
        """Fit ``iterations`` iterations from each start of ``starts`` (`_first_states`), from the same
        parameters and optimizer, then take on the whole state of the one whose lowest loss is the lowest;
        returns its drape start. Each start's lowest loss goes to its ``first_candidates`` entry
        (``race_loss``)."""
        candidates = self.first_candidates  # `load_state_dict` replaces the list by a snapshot's copy
        initial = copy.deepcopy(self.state_dict(starts[0][1]))
        best = None
        for _, state, candidate in starts:
            self.load_state_dict(copy.deepcopy(initial))
            ev = self._checked_evaluate(state)
            if ev is None:
                candidate["race_loss"] = None
                continue
            self.first = self._summary(ev)
            self._note_best(ev, state)
            ev, start = self._iterate(ev, state, iterations, bar=bar)
            candidate["race_loss"] = self.best["loss"]
            if best is None or self.best["loss"] < best[0]:
                best = (self.best["loss"], copy.deepcopy(self.state_dict(start)))
        if best is None:
            raise SimulationError("the first drape of every candidate failed (blow-up or non-finite values)")
        start = self.load_state_dict(best[1])
        self.first_candidates = candidates  # with every race loss, not the winner's copy
        self.seconds = 0.0  # `run` counts the race's time
        self.save_checkpoint(start)
        return start

    def _note_best(self, ev: Evaluation, start: ClothState) -> None:
        """Remember the parameters and the drape start of ``ev`` when its loss is the lowest so far."""
        loss = float(ev.loss.detach())
        if self.best is None or loss < self.best["loss"]:
            self.best = {
                "iteration": self.iteration,
                "loss": loss,
                "params": {k: v.detach().clone() for k, v in self.params.state_dict().items()},
                "start_x": start.x.detach().clone(),
                "start_v": start.v.detach().clone(),
            }

    def _restore_best(self, ev: Evaluation) -> Evaluation:
        """With ``keep_best``: the evaluation of the lowest-loss iteration (``ev`` when that is the last),
        its parameters loaded into `params`. The checkpoint keeps the last iteration, so a resumed run
        continues from there."""
        best = self.best
        self.result_iteration = self.iteration
        if not self.config.keep_best or best is None or float(ev.loss.detach()) <= best["loss"]:
            return ev
        last = {k: v.detach().clone() for k, v in self.params.state_dict().items()}
        self.params.load_state_dict(best["params"])
        again = self._checked_evaluate(ClothState(best["start_x"], best["start_v"]))
        if again is None:  # cannot happen for a deterministic drape; keep the last iteration then
            self.params.load_state_dict(last)
            return ev
        self.result_iteration = best["iteration"]
        return again

    def _summary(self, ev: Evaluation) -> dict:
        """Numbers and tensors of one evaluation kept for the report and the before/after picture."""
        return {
            "x": ev.x.detach().clone(),
            "body_verts": None if ev.body_verts is None else ev.body_verts.detach().clone(),
            "loss": float(ev.loss.detach()),
            "terms": {k: float(v.detach()) for k, v in ev.terms.items()},
            "chamfer_m": surface_chamfer_m(ev.x, self.garment.sim_faces, self.target.garment_points)[
                "symmetric"
            ],
            "boundary_chamfer_m": {
                lp.name: chamfer_m(ev.x[lp.vertices], self.scan_boundaries[lp.name]) for lp in ev.openings
            },
            "bend_stiffness": float(ev.bend_stiffness.detach()),
            "phenotypes": None
            if self.params.body is None
            else dict(
                zip(self.params.body.phenotype_labels, self.params.body.phenotypes[0].detach().tolist())
            ),
            "rest_uv": ev.rest_uv.detach().clone(),
        }

    def report(self, final: dict) -> dict:
        """The metrics of the fit: initial vs final Chamfer [m], loss terms, material, body, quality."""
        first = self.first
        with torch.no_grad():
            q_rest = triangle_quality(final["rest_uv"], self.garment.tri_vertices)
            q_drape = triangle_quality(final["x"], self.garment.sim_faces)
            ratio = rest_area_ratio(final["rest_uv"], self.template_uv, self.garment.tri_vertices)
        return {
            "units": "m",
            "chamfer_definition": "symmetric mean surface distance, not squared: (mean distance of the scan "
            "garment points to the draped surface + mean distance of 50k area samples of the draped surface "
            "to the nearest scan garment point) / 2; boundary chamfers: mean nearest-neighbour distance "
            "between loop vertices and scan loop points, (a->b + b->a) / 2 (a neck under a folded collar: "
            "its fold, losses.folded_collar_loop)",
            "template": self.config.template,
            "chamfer_initial": first["chamfer_m"],
            "chamfer_final": final["chamfer_m"],
            "boundary_chamfer_initial": first["boundary_chamfer_m"],
            "boundary_chamfer_final": final["boundary_chamfer_m"],
            "iterations": self.iteration,
            "result_iteration": self.result_iteration,
            "seconds": round(self.seconds, 2),
            "loss_initial": first["loss"],
            "loss_final": final["loss"],
            "loss_terms_initial": first["terms"],
            "loss_terms_final": final["terms"],
            "material": {
                "bend_stiffness_initial": first["bend_stiffness"],
                "bend_stiffness_final": final["bend_stiffness"],
                "unit": "N*m",
            },
            "body_phenotypes_initial": first["phenotypes"],
            "body_phenotypes_final": final["phenotypes"],
            "rest_quality": {"min": float(q_rest.min()), "mean": float(q_rest.mean())},
            "draped_quality": {"min": float(q_drape.min()), "mean": float(q_drape.mean())},
            "inverted_rest_triangles": int((ratio <= 0).sum()),
            "min_rest_area_ratio": float(ratio.min()),
            "rejected_steps": self.rejected_steps,
            "rejection_reasons": dict(self.rejection_reasons),
            "nan_gradients": self.nan_gradients,
            "adjoint_failures": self.adjoint_failures,
            "adjoint": self.config.adjoint,
            "vertices": self.garment.sim_vert_count,
            "faces": self.garment.tri_count,
            "matched_boundaries": [lp.name for lp in self.loops],
            "first_drape_candidates": list(self.first_candidates),
            "warnings": result_warnings(final["x"], self.garment.sim_faces, ratio, self.config.spacing),
        }


def result_warnings(
    x: torch.Tensor, sim_faces: torch.Tensor, area_ratio: torch.Tensor, spacing: float
) -> list[str]:
    """What a user should know about a fit's result before simulating it (empty when nothing).

    Args:
        x: (Vs, 3) draped positions [m]; sim_faces: (F, 3) int64; area_ratio: (F,) rest areas over the
            template's (`losses.rest_area_ratio`); spacing: the mesh spacing [m].
    """
    warnings = []
    q = triangle_quality(x, sim_faces)
    bad = q < DRAPED_QUALITY_FLOOR
    if bool(bad.any()):
        worst = int(q.argmin())
        where = [round(float(c), 3) for c in x[sim_faces[worst]].mean(0)]
        # measured on tops fitted on arms held low: slivers pressed flat on the upper arm and held there
        # by friction (docs/BENCHMARKS.md, "Arms held low"); at 2 cm instead of 2.5, gone on three of four
        warnings.append(
            f"{int(bad.sum())} draped triangles have quality below {DRAPED_QUALITY_FLOOR} (min "
            f"{float(q.min()):.2f}, at {where} m): crushed cloth, e.g. pressed flat on the body where a mesh "
            f"this coarse does not fold; a finer spacing than {spacing:g} m (e.g. --spacing "
            f"{0.8 * spacing:.3g}) usually removes them"
        )
    inverted = int((area_ratio <= 0).sum())
    if inverted:
        warnings.append(f"{inverted} rest triangles are inverted: the pattern cannot be cut as it is")
    return warnings


def _yaml_dump(data: dict) -> str:
    import yaml

    return yaml.safe_dump(data, sort_keys=False)


def write_resolved_config(config: FitConfig, out_dir: str | os.PathLike) -> Path:
    """Write the resolved config as ``<out_dir>/config.yaml`` (also into the TensorBoard text)."""
    path = Path(out_dir) / "config.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(_yaml_dump(config_to_dict(config)))
    return path
