"""The fit's configuration: `LossWeights`, `FitConfig`, the YAML files that fill them (``configs/``), and the
simulator options that a config implies (`drape_config`, `first_drape_config`, `adjoint_options`).

Configs are frozen dataclasses; YAML only fills them in, unknown keys are an error (`config_from_dict`), and
the resolved config of a fit is written beside its results (`write_resolved_config`).
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

from torch_diffavatar.atomic_file import atomic_write_text
from torch_diffavatar.chamfer import ROBUST_KERNELS
from torch_diffavatar.errors import InputError
from torch_diffavatar.pattern.measurements import HEM_OPENINGS
from torch_diffavatar.sim.forward_drape import SEW_MAX_STRAIN, DrapeConfig
from torch_diffavatar.sim.solver import XPBDConfig

CONFIG_DIR = Path(__file__).resolve().parent / "configs"  # shipped in the package (wheel included)
# strain limit of every drape of a fit, the sewing's (see `drape_config` for why it is above the solver's 3)
FIT_MAX_STRAIN = SEW_MAX_STRAIN
# threads of the C++ substep op in a fit's drapes: 0, torch's intra-op setting (`torch.set_num_threads`),
# so that a pipeline that gives torch the machine's cores gives them to the drapes too (the op's Gauss–Seidel
# colours make every thread count give the same result). `diffavatar fit` runs on one thread.
FIT_THREADS = 0
# a fit's resolved config in its output folder (`write_resolved_config`)
RESOLVED_CONFIG = "config.yaml"
# [N·m] a fit's bending stiffness stays in here: fabrics span about 1e-7 (silk) to 1e-4 (denim, leather)
# (Kawabata B per unit width); a step beyond it is a runaway (lr_log_bend_stiffness: 1000 reached inf, and
# material.json then held Infinity), rejected like any other (`fit.parameter_rejection`)
BEND_STIFFNESS_RANGE = (1.0e-9, 1.0e-2)
# the fitted variables' Adam steps: 0 freezes one, and at least one must be free
LEARNING_RATES = (
    "lr_cage",
    "lr_phenotypes",
    "lr_translation",
    "lr_pose",
    "lr_log_bend_stiffness",
    "lr_log_stretch",
    "lr_waist_shift",
)
# guards that ``inf`` switches off; every other number of a config must be finite
INFINITY_MEANS_OFF = ("max_drape_jump", "max_loss_rise")
# how `FitConfig.opening_template_names` are held: no shorter than the template's, or at its length
OPENING_HOLDS = ("least", "exact")


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
        pattern_change: [1/m], times `pattern_change_loss` (the robust mean distance of the pattern from
            the template outside each panel's design changes, `design_modes`: moves, scales, shears and
            flares are free): the fit reshapes a panel only where the scan's evidence outweighs it. 0: off.
        opening_length: [-], times `opening_lengths.opening_length_loss` (the squared relative shortfall
            of the rest length of each opening of ``FitConfig.opening_length_names`` (the hems) below the
            length the scan's points of it trace, less ``FitConfig.opening_length_tolerance``): a hem is
            never narrower than the scan shows. 0: off.
        opening_split: [-], times `opening_lengths.opening_split_loss` (how far each panel's share of
            those openings' length moved from the template's): the scan shows a hem's length, not where
            its seams are, so the template's split stands. 0: off.
    """

    boundary: float = 1.0e4
    interior: float = 1.0e4
    seam_length: float = 1.0e7
    curvature: float = 1.0e5
    phenotype_prior: float = 1.0
    rest_area: float = 1.0e3
    rest_shape: float = 100.0
    skin: float = 3.0e5
    pattern_change: float = 0.0
    opening_length: float = 0.0
    opening_split: float = 0.0

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
        lr_log_stretch: Adam step of the log membrane stretch scale s [-]: the base material's k_uu, k_vv
            and k_uv are multiplied by exp(s) (bounded, ``stretch_bound``; `objective.stretch_material`).
            0 (the default, and every shipped config's) freezes it: the fit keeps the base membrane, bit
            for bit as before the variable existed. Measured (docs/BENCHMARKS.md, "Membrane stretch"): at
            40 substeps it recovers a skirt's 4× softer membrane (0.29 for 0.25), with the pattern frozen
            or free, but the free pattern did not end closer to the truth; on a dress, which barely
            stretches under its weight, it drifted to 0.80 on a scan made at the base membrane (Chamfer
            +0.5 mm) and reached only 0.75 on one made 4× softer. Fit it (e.g. 0.05-0.2) for scans of
            visibly stretchier cloth, with the fit's drapes at 40 substeps: at 10 the XPBD drape is far
            softer than its nominal membrane and the factor runs past the truth.
        stretch_bound: the fitted membrane factor stays within (1/``stretch_bound``, ``stretch_bound``)
            (a smooth bound, `objective.bounded_stretch`) [-]; must be > 1.
        initial_stretch: the membrane factor at the start [-], strictly inside the bound (the first
            sewings drape with it too).
        lr_waist_shift: Adam step of the waist's height change [m]: a skirt's or trousers' waist
            attachments are held that much above (below, negative) their placement height
            (`objective.bounded_shift`, ``waist_shift_bound``). A real waistband settles where the body
            and the fabric put it, often at the hips; held at the natural waist, the fit could only
            lengthen the panels to reach a lower hem. 0 freezes it (garments without waist attachments
            have nothing to move).
        waist_shift_bound: the waist's height change stays within ±``waist_shift_bound`` [m] (smooth bound).
        pattern_delay: iterations at the start in which the pattern stays as it is while the other
            variables (material, waist, body) move: physics that the start cannot model is explained by
            them before the pattern can absorb it.
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
        predict_warm_starts: equilibrium adjoint with the projected Hessian only: each drape starts from
            the previous one's end moved by the first-order prediction of its backward
            (`sim.adjoint.linearization`). Off by default: on the demo dress it saved 8-17 % of the frames
            but no CPU time, and its drapes ended 0.47-0.67 mm (mean) from 200-frame drapes of the same
            steps, against 0.17-0.27 mm without it (docs/BENCHMARKS.md, "Warm starts that land").
        carry_cloth_with_body: each trial drape starts from the last drape moved rigidly by the body's
            translation since then (`fit.carried_trials`), not where the old drape was. A body moved 0.3 mm
            into a stiff T-shirt resting on it raised the loss 3.5 % where the gradient promised a fall
            (a captured dress's fit: loss 26.0 -> 19.4, 10.2 -> 5.8 mm from its true drape with it); off by
            default: on 21 ring captures the fits moved by their scatter (outline median 3.1 -> 2.9 mm,
            mean 3.6 -> 3.7) and the demo ended 5.09 mm from its scan instead of 4.77
            (docs/BENCHMARKS.md, "The cloth carried with the body").
        drape_substeps: XPBD substeps per frame of the fit's drapes [-].
        drape_velocity_scale: velocity factor per frame of the fit's warm-started drapes (artificial
            damping; `DrapeConfig.drape_velocity_scale`) [-], in (0, 1].
        drape_contact_bounce: `XPBDConfig.contact_bounce` of the fit's drapes (1: contacts pushed out keep
            their outward velocity, as every drape; 0: inelastic) [-], in [0, 1].
        drape_settle_outliers: fraction of the vertices that the equilibrium adjoint's drapes let move
            faster than the settle speed when they stop (`DrapeConfig.settle_outliers`) [-], in [0, 1).
            All three as every drape by default: damping 0.9 with 1 % outliers took 44-59 % of the frames
            off five of six fits, the results moving by their noise, but Newton's T-shirt 382 ended
            1.75 mm farther from its true drape; bounce 0 saved 0-12 % of the frames, the drapes mixed
            (docs/BENCHMARKS.md, "Drapes that never settle").
        drape_valley_contacts: `XPBDConfig.valley_contacts` of the fit's drapes and of its first drape (a
            second contact where the body folds inward, so that the armpits' vertices stop jumping between
            the two sides). Off by default: on five held-out fits it took 31 % of the frames off the one whose
            armpits rocked, and moved the others by their path noise, one T-shirt 1.3 mm farther from its true
            drape (docs/BENCHMARKS.md, "Valley contacts").
        drape_floor: the fit's drapes, its first drape and its sewing have a floor at the body's soles
            (`DrapeConfig.floor`): trousers or a dress longer than the legs pile on it, as a captured one
            does, instead of hanging through it. A garment that never reaches the floor drapes as without.
        animation_check_s: after the fit, its assets walk this long [s] (`fit_report.animation_warnings`:
            a warning in report.json when they blow up; ~2 CPU s for 0.5 s at 2k vertices). 0: no check.
        hem_from_scan: before the fit, the template is sewn and draped once and its hem raised or lowered to
            the scan's hem height (measured from the waistband, for a garment with one: it may sit on the
            hips) and widened to the loop the scan's hem traces (`fit_design`): a template
            5 cm too long made the fit lift its hem by shrinking the neck (a T-shirt's 6.2 cm; from the hem
            set so, 1.6; docs/BENCHMARKS.md, "The hem from the scan before the fit"). Hems that the
            intake's floor removal cut off (trousers piled on the floor) are widened to the loops the legs
            trace above it and held there, their height left (`fit_design.floor_cut_hems`). False: the
            template as it is.
        first_max_steps: frames at most of the first (sew and) drape [-].
        first_bend_scales: the first drape is sewn and draped once per entry, with the bending stiffness
            scaled by it, then each is settled at the fit's own stiffness; the one with the lowest loss
            (or the race's winner, ``first_race_iterations``) starts the fit [-]. Cloth that hangs loose
            on a body rests in more than one fold state, and which one a sewing reaches depends on its
            path: stiffer cloth while sewing reaches other fold states. Measured on the tops' true
            patterns (docs/RESULTS_HISTORY.md): the lowest-loss candidate of (1, 3, 10) landed 0.9-8.0 mm
            closer to the true drape than the plain sewing. ``(1.0,)``: one sewing.
        first_stretch_scales: each first sewing is also made once per entry, with the membrane factor
            ``initial_stretch`` times it, and races from there (``first_race_iterations`` must be > 0) [-].
            Another simulator's cloth can rest where ours would with a far softer membrane than the
            nominal one, and a fit started at 1 does not find it (docs/BENCHMARKS.md, "Newton's drape is
            not an equilibrium of our cloth"). ``(1.0,)``: one membrane.
        first_fit_bend_scales: each first sewing is also made once per entry with the fit's bending
            stiffness (``initial_bend_stiffness``) times it, and its candidate in the race fits from that
            stiffness (``first_race_iterations`` must be > 0) [-]. A fit started soft can stay in the soft
            cloth's fold state whatever the scan's cloth is: three of ten captured dresses (true k_b 4x the
            start) ended at 0.22-0.35x the truth and 10.6-15.9 mm from their true drapes; raced from 1x and
            3x, at 0.67-1.24x and 4.7-6.3 mm (docs/BENCHMARKS.md, "A race of bending stiffnesses").
            ``(1.0,)``: the fit starts at ``initial_bend_stiffness`` alone.
        first_race_pairs: False: a sewing for every combination of ``first_stretch_scales`` and
            ``first_fit_bend_scales``; True: the two lists (of one length) paired entry by entry, one sewing
            per pair (the race's cost grows with its candidates: on two workers four take twice the time
            of two).
        first_race_iterations: with several ``first_bend_scales``, the fit runs this many iterations from
            every candidate sewing and continues from the one whose lowest loss is the lowest [-]. A fold
            state and the pattern that suits it are found together, so the first drape's loss alone can
            pick the wrong one (measured: the T-shirt's 10× sewing starts at a higher loss than the 1×
            one, and its fit ends lower, 13.2 against 15.8). The cost is one fit of this length per extra
            sewing. 0: the first drape's loss decides.
        resew_at: after each of these iterations (1-based counts of iterations done) the garment is
            sewn and draped afresh at the present parameters, once per ``first_bend_scales``
            (`fit_start.first_states`), and the fit goes on from the lowest-loss of those drapes and its
            own warm-started one [-]. Where cloth comes to rest depends on its path: a drape carried along
            from the template's keeps what the template's folds and friction gave it, and the pattern bends
            to undo that (measured: a fitted T-shirt's front neckline 2 cm lower in its own drape than in a
            fresh sewing of the same pattern). Off in the shipped configs: ``[3]`` on eight tops brought 6 of
            8 outlines closer but 3 of 8 drapes farther from the truth, at 23-45 s per fit
            (docs/BENCHMARKS.md, "What shrinks the tops' necks, and fresh sewings during the fit"). Empty:
            never.
        max_scan_points: scan garment points used by the interior loss, and skin points used by the skin
            loss (a fixed random subset of each) [-].
        interior_to_surface: the interior loss's scan → garment direction measures the distance to the
            draped surface (`interior_loss` with ``garment_faces``), not to the nearest vertex [-].
        boundary_robust, interior_robust: penalty kernel of the point distances in the boundary and in
            the interior loss (``"l2"``, ``"huber"`` or ``"geman_mcclure"``, `chamfer.robust_penalty`);
            robust_scale: the kernels' scale [m].
        boundary_trim: fraction of the largest point distances left out of each direction of each
            opening's Chamfer (`boundary_loss` ``trim``): scan openings pick up the rims of nearby holes [-].
        boundary_gap_bin: > 0: each opening's garment → scan distances only from the loop's sectors (about
            this long [m]) that the scan's opening covers (`losses.covered_loop_points`): a hole under the
            arm takes a cuff's underside, and the whole cuff was pulled onto the rest (a fit from the true
            T-shirt narrowed its cuffs by 4 cm). 0: off, every loop point.
        boundary_samples: points per loop edge of the boundary loss (`boundary_loss` samples_per_edge).
        opening_length_names: the openings (`GarmentMesh.boundary_loops` names) that
            ``weights.opening_length`` holds no shorter than the scan's points of them trace: the hems
            by default; a trouser config adds its ``waist`` (its waistband lies on the body, a ring the
            scan traces well: on a Newton-made pair the fit narrowed it by 11 cm without). With the cage's
            ``tie_mirrored``, a mirrored pair (``hem_left`` / ``hem_right``) is held to the better-seen
            one's trace (`opening_lengths.mirrored_lengths`).
        opening_template_names: openings that ``weights.opening_length`` holds to the template's length
            (as ``opening_template_hold`` says; and whose split between the panels ``weights.opening_split``
            holds), whatever the scan shows: openings the scan cannot measure. The tops' necks: the scan's
            points there are the neckline's and the skin's, and the fits shrank necks they started right by
            up to 4.7 cm through the curvature term's local scale (docs/BENCHMARKS.md, "What shrinks the
            tops' necks"); the dress's armholes, which the fits grew by 2-4 cm onto the rims of the holes
            that an arm leaves in a scan under it; a trouser's waistband, whose trace (a lower bound) came out
            3 cm short where it gathers (docs/BENCHMARKS.md, "Openings held at the template's"). An opening
            also in ``opening_length_names`` is held to the longer of the template's and the scan's trace.
        opening_template_hold: how: ``"least"``, no shorter than the template's (a neck may grow), or
            ``"exact"``, at the template's length, neither shorter nor longer (the dress and trouser
            configs: on the tops it changed nothing but one fit's path, docs/BENCHMARKS.md, "Openings held
            at the template's").
        opening_length_bin: the bin length [m] along a scan opening of `opening_lengths.scan_loop_length`.
        opening_length_tolerance: the fraction [0, 1) of a scan hem's traced length that a fitted hem may
            fall short of it before ``weights.opening_length`` holds it.
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
            Each step starts where the last one's correction went (`fit.rest_prox`): 30 then do what 50
            did from Adam's result (docs/BENCHMARKS.md, "The proximal step started where the last one went").
        keep_best: the fit's result is the iteration with the lowest loss (its drape reproduced from its
            own start), not the last one. ``max_loss_rise`` lets single steps raise the loss, and a drape
            can jump to another rest state on a small pattern change (measured: a T-shirt fit's loss
            14.3 → 16.1 in one accepted step, and it ended at 15.6).
        cage: parameterise the pattern by a `ControlCage` (the method); False optimises every panel
            vertex's rest coordinate directly (`cage.FreeVertices`, the paper's "w/o cage" ablation).
        tie_mirrored, tie_seams: `ControlCage` tying options (ignored without the cage).
        tie_symmetric: `ControlCage` ``tie_symmetric``: a panel that is its own mirror image (a skirt's
            front or back) stays symmetric. On in the dress config, where the fits had made the skirt
            panels lopsided; off for the skirt, whose fits it did not help (docs/BENCHMARKS.md, "The hem's
            split and lopsided skirt panels").
        tie_close: consecutive cage handles of a panel closer than this move together
            (`ControlCage` ``tie_close``) [m]; 0 leaves them free.
        image_every: iterations between TensorBoard pictures (0: only first and last).
        seed: seed of the scan subsampling.
        segment_colour: an unlabelled scan with colours is segmented by geometry and colour
            (`body.segment.segment_garment` ``use_colour``); False: by geometry alone.
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
    lr_log_stretch: float = 0.0
    stretch_bound: float = 30.0
    initial_stretch: float = 1.0
    lr_waist_shift: float = 0.0
    waist_shift_bound: float = 0.15
    pattern_delay: int = 0
    weights: LossWeights = field(default_factory=LossWeights)
    adjoint: str = "trajectory"
    drape_steps: int = 3
    polish_iterations: int = 0
    adjoint_hessian: str = "projected"
    predict_warm_starts: bool = False
    carry_cloth_with_body: bool = False
    drape_substeps: int = 10
    drape_velocity_scale: float = 0.97
    drape_contact_bounce: float = 1.0
    drape_settle_outliers: float = 0.0
    drape_valley_contacts: bool = False
    drape_floor: bool = True
    animation_check_s: float = 0.5
    hem_from_scan: bool = False
    first_max_steps: int = 400
    first_bend_scales: tuple[float, ...] = (1.0,)
    first_stretch_scales: tuple[float, ...] = (1.0,)
    first_fit_bend_scales: tuple[float, ...] = (1.0,)
    first_race_pairs: bool = False
    first_race_iterations: int = 0
    resew_at: tuple[int, ...] = ()
    max_scan_points: int = 4000
    interior_to_surface: bool = True
    boundary_robust: str = "l2"
    interior_robust: str = "l2"
    robust_scale: float = 0.01
    boundary_trim: float = 0.0
    boundary_gap_bin: float = 0.0
    boundary_samples: int = 2
    opening_length_names: tuple[str, ...] = HEM_OPENINGS
    opening_template_names: tuple[str, ...] = ()
    opening_template_hold: str = "least"
    opening_length_bin: float = 0.02
    opening_length_tolerance: float = 0.0
    min_rest_area_ratio: float = 0.1
    max_drape_jump: float = 0.15
    max_retries: int = 3
    max_loss_rise: float = 0.1
    lr_final: float = 1.0
    rest_prox_iterations: int = 30
    keep_best: bool = True
    cage: bool = True
    tie_mirrored: bool = True
    tie_symmetric: bool = False
    tie_seams: bool = True
    tie_close: float = 0.01
    image_every: int = 5
    seed: int = 0
    segment_colour: bool = True

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
        self._check_material()
        if not 1 < self.stretch_bound < math.inf:
            raise ValueError(f"FitConfig.stretch_bound must be a finite factor > 1, got {self.stretch_bound}")
        if not 1 / self.stretch_bound < self.initial_stretch < self.stretch_bound:
            raise ValueError(
                f"FitConfig.initial_stretch must be inside (1/stretch_bound, stretch_bound), got "
                f"{self.initial_stretch}"
            )
        if not 0 < self.waist_shift_bound < math.inf:
            raise ValueError(
                f"FitConfig.waist_shift_bound must be a finite length > 0 [m], got {self.waist_shift_bound}"
            )
        self._check_drape_options()
        self._check_counts()
        self._check_first_drapes()
        for name in ("boundary_robust", "interior_robust"):
            kernel = getattr(self, name)
            if kernel not in ROBUST_KERNELS:
                raise ValueError(f"FitConfig.{name} must be one of {ROBUST_KERNELS}, got {kernel!r}")
        if not 0.0 <= self.boundary_trim < 1.0:
            raise ValueError(f"FitConfig.boundary_trim must be in [0, 1), got {self.boundary_trim}")
        if not (math.isfinite(self.boundary_gap_bin) and self.boundary_gap_bin >= 0):
            raise ValueError(f"FitConfig.boundary_gap_bin must be >= 0 [m], got {self.boundary_gap_bin}")
        self._check_opening_lengths()
        if not self.robust_scale > 0:
            raise ValueError(f"FitConfig.robust_scale must be a positive length [m], got {self.robust_scale}")
        if not 0 <= self.tie_close < math.inf:
            raise ValueError(f"FitConfig.tie_close must be a length >= 0 [m], got {self.tie_close}")
        if not self.max_loss_rise > 0:
            raise ValueError(f"FitConfig.max_loss_rise must be > 0 (inf: no check), got {self.max_loss_rise}")
        if not 0 < self.lr_final <= 1:
            raise ValueError(f"FitConfig.lr_final must be in (0, 1], got {self.lr_final}")
        for name in LEARNING_RATES:
            if not getattr(self, name) >= 0:
                raise ValueError(f"FitConfig.{name} must be >= 0 (0 freezes the parameter)")
        if not any(getattr(self, name) > 0 for name in LEARNING_RATES):
            # the fit would set everything up and then fail in Adam ("an empty parameter list")
            raise ValueError(
                f"FitConfig: every learning rate ({', '.join(LEARNING_RATES)}) is 0, so nothing would be "
                "fitted; set one above 0 (`diffavatar drape` drapes a pattern as it is)"
            )
        self._check_numbers()

    def _check_first_drapes(self) -> None:
        """ValueError for bad settings of the first sewings and their race (``first_*_scales``,
        ``resew_at``); stores the lists as tuples."""
        for name in ("first_bend_scales", "first_stretch_scales", "first_fit_bend_scales"):
            self._positive_list(name)
        if len(self.first_stretch_scales) > 1 and self.first_race_iterations == 0:
            raise ValueError(
                "FitConfig.first_stretch_scales: several membranes need a race (first_race_iterations > 0): "
                "the first drape's loss is taken at one membrane"
            )
        if self.first_race_pairs and len(self.first_stretch_scales) != len(self.first_fit_bend_scales):
            raise ValueError(
                "FitConfig.first_race_pairs: first_stretch_scales and first_fit_bend_scales are paired entry "
                f"by entry and need the same length, got {len(self.first_stretch_scales)} and "
                f"{len(self.first_fit_bend_scales)}"
            )
        if len(self.first_fit_bend_scales) > 1 and self.first_race_iterations == 0:
            raise ValueError(
                "FitConfig.first_fit_bend_scales: several bending stiffnesses need a race "
                "(first_race_iterations > 0): a first drape's loss favours the stiffer cloth"
            )
        low, high = BEND_STIFFNESS_RANGE
        for s in self.first_fit_bend_scales:
            if not low <= self.initial_bend_stiffness * s <= high:
                raise ValueError(
                    f"FitConfig.first_fit_bend_scales: initial_bend_stiffness x {s} is outside "
                    f"[{low:g}, {high:g}] N·m"
                )
        for s in self.first_stretch_scales:
            if not 1 / self.stretch_bound < self.initial_stretch * s < self.stretch_bound:
                raise ValueError(
                    f"FitConfig.first_stretch_scales: initial_stretch x {s} is outside the stretch_bound"
                )
        resew = (self.resew_at,) if isinstance(self.resew_at, int) else self.resew_at
        if not all(isinstance(i, int) and not isinstance(i, bool) and i >= 1 for i in resew):
            raise ValueError(f"FitConfig.resew_at must list iteration counts >= 1, got {self.resew_at!r}")
        object.__setattr__(self, "resew_at", tuple(sorted(set(resew))))  # YAML gives a list

    def _check_opening_lengths(self) -> None:
        """ValueError for bad ``opening_length_*`` settings; stores the opening lists as tuples."""
        for field_name in ("opening_length_names", "opening_template_names"):
            names = getattr(self, field_name)
            if isinstance(names, list | tuple) and all(isinstance(n, str) and n for n in names):
                object.__setattr__(self, field_name, tuple(names))  # YAML gives a list
            else:
                raise ValueError(f"FitConfig.{field_name} must be a list of opening names, got {names!r}")
        if self.opening_template_hold not in OPENING_HOLDS:
            raise ValueError(
                f"FitConfig.opening_template_hold must be one of {OPENING_HOLDS}, "
                f"got {self.opening_template_hold!r}"
            )
        if not 0.0 <= self.opening_length_tolerance < 1.0:
            raise ValueError(
                f"FitConfig.opening_length_tolerance must be in [0, 1), got {self.opening_length_tolerance}"
            )
        if not 0 < self.opening_length_bin < math.inf:
            raise ValueError(
                f"FitConfig.opening_length_bin must be a length > 0 [m], got {self.opening_length_bin}"
            )

    def _positive_list(self, name: str) -> None:
        """ValueError unless field ``name`` is a positive number or a non-empty list of them; stores a tuple
        (YAML gives a list)."""
        scales = getattr(self, name)
        if isinstance(scales, int | float) and not isinstance(scales, bool):
            scales = (scales,)
        if (
            not isinstance(scales, list | tuple)
            or not scales
            or not all(
                isinstance(s, int | float) and not isinstance(s, bool) and 0 < s < math.inf for s in scales
            )
        ):
            raise ValueError(f"FitConfig.{name} must be a non-empty list of positive numbers, got {scales!r}")
        object.__setattr__(self, name, tuple(float(s) for s in scales))

    def _check_drape_options(self) -> None:
        """ValueError for a drape damping, contact bounce, settle share or check length out of its range."""
        for name, low, high, closed in (
            ("drape_velocity_scale", 0.0, 1.0, "(0, 1]"),
            ("drape_contact_bounce", 0.0, 1.0, "[0, 1]"),
            ("drape_settle_outliers", 0.0, 1.0, "[0, 1)"),
            ("animation_check_s", 0.0, math.inf, "[0, inf)"),
        ):
            value = getattr(self, name)
            low_ok = value >= low if closed[0] == "[" else value > low
            high_ok = value <= high if closed[-1] == "]" else value < high
            if not (low_ok and high_ok):
                raise ValueError(f"FitConfig.{name} must be in {closed}, got {value}")

    def _check_counts(self) -> None:
        """ValueError for a count that is not an integer >= its least value (0 or 1)."""
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
            "pattern_delay",
        ):
            value = getattr(self, name)
            zero_ok = (
                "iterations", "polish_iterations", "rest_prox_iterations", "first_race_iterations",
                "pattern_delay",
            )  # fmt: skip
            low = 0 if name in zero_ok else 1
            if not isinstance(value, int) or value < low:
                raise ValueError(f"FitConfig.{name} must be an integer >= {low}")

    def _check_material(self) -> None:
        """ValueError for an initial bending stiffness outside `BEND_STIFFNESS_RANGE`."""
        low, high = BEND_STIFFNESS_RANGE
        if not low <= self.initial_bend_stiffness <= high:
            span = ", ".join(f"{v:.0e}".replace("e-0", "e-") for v in BEND_STIFFNESS_RANGE)  # 1e-9, 1e-2
            raise ValueError(
                f"FitConfig.initial_bend_stiffness must be in [{span}] N·m (cloth), got "
                f"{self.initial_bend_stiffness}"
            )

    def _check_numbers(self) -> None:
        """ValueError for a NaN, an infinity where it means nothing, or a negative count."""
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, float):
                continue
            if math.isnan(value) or (math.isinf(value) and f.name not in INFINITY_MEANS_OFF):
                off = f" (inf only for {', '.join(INFINITY_MEANS_OFF)}: no check)"
                raise ValueError(f"FitConfig.{f.name} must be a finite number{off}, got {value}")
        for name in ("max_retries", "image_every", "seed"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise ValueError(f"FitConfig.{name} must be an integer >= 0, got {value!r}")


def with_fit_strain_limit(config: DrapeConfig) -> DrapeConfig:
    """``config`` with the strain limit of a fit's drapes, `FIT_MAX_STRAIN`, while sewing and draping (a
    seam-corner triangle of a sewn template can pass the solver's default for a few frames), and the
    substep op on torch's intra-op threads (`FIT_THREADS`)."""
    return replace(
        config,
        xpbd=replace(config.xpbd, max_strain=FIT_MAX_STRAIN, num_threads=FIT_THREADS),
        sew_xpbd=replace(config.sew_xpbd, max_strain=FIT_MAX_STRAIN, num_threads=FIT_THREADS),
    )


def _field_names(cls) -> list[str]:
    return [f.name for f in dataclasses.fields(cls)]


def _typed(name: str, kind: str, value, source: str):
    """``value`` of the config field ``name`` as its declared type ``kind`` ("bool", "int", "float",
    "float | None", "str", ...; other kinds pass unchanged to the dataclass's own checks).

    Strict where YAML is loose: a boolean is ``true`` or ``false`` (the string ``"no"`` is not false), an
    integer is not a float or a boolean, and a number may be a string that parses as one (YAML 1.1 reads
    ``1e-3`` as a string).

    Raises:
        InputError: the value is not of the field's type.
    """
    if value is None and kind.endswith("| None"):
        return None
    kind = kind.removesuffix(" | None")
    if kind == "bool":
        if isinstance(value, bool):
            return value
        raise InputError(f"{source}: {name} must be true or false, got {value!r}")
    if kind == "int":
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise InputError(f"{source}: {name} must be an integer, got {value!r}")
    if kind == "float":
        if isinstance(value, int | float) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str):
            try:
                return float(value)
            except ValueError:
                pass
        raise InputError(f"{source}: {name} must be a number, got {value!r}")
    if kind == "str" and not isinstance(value, str):
        raise InputError(f"{source}: {name} must be a string, got {value!r}")
    return value


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
        w = {k: _typed(f"weights.{k}", "float", v, source) for k, v in w.items()}
        try:
            values["weights"] = replace(base.weights, **w)
        except (TypeError, ValueError) as exc:
            raise InputError(f"{source}: {exc}") from exc
    for f in dataclasses.fields(FitConfig):
        if f.name in values and f.name != "weights":
            values[f.name] = _typed(f.name, str(f.type), values[f.name], source)
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


def yaml_dump(data: dict) -> str:
    """``data`` as YAML, keys in their order."""
    import yaml

    return yaml.safe_dump(data, sort_keys=False)


def write_resolved_config(config: FitConfig, out_dir: str | os.PathLike) -> Path:
    """Write the resolved config as ``<out_dir>/config.yaml`` (also into the TensorBoard text)."""
    path = Path(out_dir) / RESOLVED_CONFIG
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, yaml_dump(config_to_dict(config)))
    return path


# ---------------------------------------------------------------------------------------------------------
# Simulator options of a fit


def drape_config(config: FitConfig, steps: int | None = None, adjoint: str | None = None) -> DrapeConfig:
    """The options of a fit's differentiable drapes: ``config.drape_steps`` frames (or ``steps``) of
    ``config.drape_substeps`` substeps; with the equilibrium adjoint (``config.adjoint``, or ``adjoint``),
    at most that many (it stops once the drape has settled)."""
    n = config.drape_steps if steps is None else steps
    adjoint = config.adjoint if adjoint is None else adjoint
    # A few small triangles at a seam corner can sit far beyond the solver's default strain limit (3)
    # in a sane drape and would then reject every step: E = 3.0 on the 2 cm dress, E = 10-12 at the
    # shoulder tips of the long-sleeve shirt and the T-shirt, where four panels meet at 6 mm pattern
    # edges (72-81 rejections in 30 iterations at a limit of 10). The fit catches real blow-ups by
    # the speed limit and the `max_drape_jump` guard instead.
    xpbd = XPBDConfig(
        substeps=config.drape_substeps,
        iterations=1,
        max_strain=FIT_MAX_STRAIN,
        num_threads=FIT_THREADS,
        contact_bounce=config.drape_contact_bounce,
        valley_contacts=config.drape_valley_contacts,
    )
    damped = config.drape_velocity_scale
    if adjoint == "equilibrium":
        return DrapeConfig(
            xpbd=xpbd,
            min_steps=min(5, n),
            max_steps=n,
            drape_velocity_scale=damped,
            settle_outliers=config.drape_settle_outliers,
            floor=config.drape_floor,
        )
    return DrapeConfig(
        xpbd=xpbd, min_steps=n, max_steps=n, drape_velocity_scale=damped, floor=config.drape_floor
    )


def first_drape_config(config: FitConfig) -> DrapeConfig:
    """Options of a fit's first sew and drape: the defaults, with the fit's strain limit (see
    `drape_config`): sewing a template onto a fitted body can pull a seam-corner triangle past the default
    limit for a few frames (measured: E = 3.7 on a long-sleeve shirt) without a blow-up."""
    xpbd = XPBDConfig(valley_contacts=config.drape_valley_contacts)
    first = DrapeConfig(max_steps=config.first_max_steps, xpbd=xpbd, floor=config.drape_floor)
    return with_fit_strain_limit(first)


def adjoint_options(config: FitConfig, adjoint: str | None = None):
    """`EquilibriumOptions` from ``config`` when the adjoint (``config.adjoint``, or ``adjoint``) is the
    equilibrium one, else None (the adjoint's defaults)."""
    if (config.adjoint if adjoint is None else adjoint) != "equilibrium":
        return None
    from torch_diffavatar.sim.adjoint import EquilibriumOptions

    polish = config.polish_iterations > 0
    return EquilibriumOptions(
        newton_iterations=config.polish_iterations,
        active_set_rounds=EquilibriumOptions.active_set_rounds if polish else 1,
        hessian=config.adjoint_hessian,
        # measured on the 2k-vertex dress: sparse LU 0.26 s vs CG 0.83 s on the projected H
        solve_method="direct" if config.adjoint_hessian == "projected" else EquilibriumOptions.solve_method,
        keep_linearization=config.predict_warm_starts,
    )
