"""The fit's objective as a PyTorch module (paper §4.2.5), and the fit variables it is evaluated at.

`FitParameters` holds the fit variables (a `ControlCage`, an optional `BodyModel`, the log bending stiffness,
the log membrane stretch scale) and returns them as `FitVariables`. `FitObjective` holds the scan target and
the loss weights (buffers, so ``.to()`` and ``state_dict()`` carry them) and, called at the variables and a
start `ClothState`, drapes the garment with `torch_diffavatar.sim.differentiable.drape` and returns the loss
as `ObjectiveOutput`:

    loss = ρ·boundary + σ·interior + α·seam_length + β·curvature
           (+ rest area / shape, pattern change, hem length, skin, body prior)

A whole fit is then a plain ``torch.optim`` loop (``scripts/fit_loop.py``); `torch_diffavatar.fit.Fitter`
drives the same objective with guards, a proximal rest step, logging and checkpoints.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

import torch
from torch import nn

from torch_diffavatar.cage import ControlCage, FreeVertices, seam_segments
from torch_diffavatar.fit_config import FitConfig, LossWeights, adjoint_options, drape_config
from torch_diffavatar.losses import (
    REST_AREA_THRESHOLD,
    REST_DISTORTION_THRESHOLD,
    CurvatureFrames,
    boundary_loss,
    curvature_frames,
    curvature_loss,
    dart_triangles,
    design_modes,
    folded_collar_loop,
    interior_loss,
    pattern_change_loss,
    rest_area_loss,
    rest_distortion_loss,
    seam_length_loss,
    seen_side_weights,
    signed_rest_areas,
    skin_loss,
    template_edge_inverse,
)
from torch_diffavatar.opening_lengths import (
    mirrored_lengths,
    opening_length_loss,
    opening_split_loss,
    rest_loop_edges,
    rest_loop_length,
    rest_loop_panels,
    rest_loop_shares,
    scan_loop_length,
)
from torch_diffavatar.pattern.garment_mesh import BoundaryLoop, GarmentMesh
from torch_diffavatar.rest_terms import (
    RestKernelCall,
    fused_rest_terms,
    opening_slots,
    rest_kernels_available,
)
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.model import ClothModel, ClothModelBuilder
from torch_diffavatar.sim.state import ClothState

# the loss terms, in the order of `LossWeights`; each has a weight buffer ``weight_<term>``
TERM_NAMES = tuple(f.name for f in fields(LossWeights))
# the fraction of a dart's template opening below which the rest-area term holds it: a dart may narrow, not
# close past zero (fitted dresses had crossed their bodice darts' legs: docs/BENCHMARKS.md, "Darts that
# cross")
DART_KEEP = 0.2


@dataclass
class ScanTarget:
    """What the garment is fitted to (world frame, metres).

    Attributes:
        garment_points: (P, 3) scan points of the garment.
        boundaries: garment opening name (``GarmentMesh.boundary_loops`` names) -> (k, 3) scan points.
        body_points: (Q, 3) the other scan points (skin), may be empty.
        seen_sides: (S,) bool, the sides of the person the scan sees (`scan_intake.coverage`), or None
            (all: a full scan). With a side unseen, the garment on that side is not pulled toward the scan
            (`losses.seen_side_weights`).
        held_openings: openings the scan does not show whose length the set-up measured otherwise and
            gave the start pattern (hems the floor's removal cut off: `fit_design.floor_cut_hems`); the fit
            holds each at the start's length, neither shorter nor longer.
    """

    garment_points: torch.Tensor
    boundaries: dict[str, torch.Tensor] = field(default_factory=dict)
    body_points: torch.Tensor | None = None
    seen_sides: torch.Tensor | None = None
    held_openings: tuple[str, ...] = ()

    def __post_init__(self):
        g = self.garment_points
        if not isinstance(g, torch.Tensor) or g.dim() != 2 or g.shape[1] != 3 or g.shape[0] < 1:
            raise ValueError("ScanTarget.garment_points must be a (P, 3) tensor with P >= 1")
        if not torch.isfinite(g).all():
            raise ValueError("ScanTarget.garment_points hold NaN or infinite values")


@dataclass
class FitVariables:
    """The fit variables as the objective takes them (`FitParameters.forward`).

    Attributes:
        rest_uv: (V, 2) panel-vertex rest coordinates [m].
        body_verts: (Vb, 3) body vertices [m], or None (a fixed body, or none).
        bend_stiffness: () bending stiffness k_b [N·m].
        phenotypes: (1, P) the body's phenotypes [-] while they are fitted (their logits require grad),
            else None: the objective's phenotype prior holds fitted phenotypes only.
        stretch: () factor [-] of the base material's membrane stiffnesses k_uu, k_vv, k_uv
            (`stretch_material`), or None for the base material's.
        waist_shift: () height change [m] of the waist attachments (up positive; `FitObjective.drape`), or
            None for their placement height.
    """

    rest_uv: torch.Tensor
    body_verts: torch.Tensor | None
    bend_stiffness: torch.Tensor
    phenotypes: torch.Tensor | None = None
    stretch: torch.Tensor | None = None
    waist_shift: torch.Tensor | None = None


def bounded_stretch(log_stretch: torch.Tensor, bound: float) -> torch.Tensor:
    """The membrane stiffness factor exp(L·tanh(s/L)), L = log ``bound``, of the log stretch scale s.

    Near s = 0 it is exp(s); it never leaves [1/``bound``, ``bound``], and beyond the bound its gradient
    fades smoothly (tanh) instead of vanishing at once, so a fit that drives s far (the drape barely
    constrains the membrane where the cloth is slack) stays bounded and can come back, which a clamp's zero
    gradient would not allow.

    Args:
        log_stretch: () or (B,) s [-]; bound: > 1, the largest factor [-].

    Returns:
        a tensor shaped like ``log_stretch`` [-].
    """
    limit = math.log(bound)
    return torch.exp(limit * torch.tanh(log_stretch / limit))


def unbounded_stretch(factor: float, bound: float) -> float:
    """The log stretch scale s whose `bounded_stretch` (s, ``bound``) is ``factor`` [-] (inside the bound)."""
    limit = math.log(bound)
    return limit * math.atanh(math.log(factor) / limit)


def bounded_shift(shift: torch.Tensor, bound: float) -> torch.Tensor:
    """The waist height change ``bound``·tanh(t/``bound``) [m] of the unbounded variable t [m]: t near 0,
    never beyond ±``bound``, with a gradient that fades smoothly (as `bounded_stretch`)."""
    return bound * torch.tanh(shift / bound)


def membrane_stiffnesses(material: ClothMaterial, stretch: torch.Tensor | float | None) -> dict[str, float]:
    """The membrane stiffnesses [N/m] of `stretch_material` (``material``, …, ``stretch`` [-]) as floats:
    ``{"k_uu": …, "k_vv": …, "k_uv": …}`` (for logs and reports)."""
    factor = 1.0 if stretch is None else float(stretch.detach() if torch.is_tensor(stretch) else stretch)
    return {name: float(getattr(material, name)) * factor for name in ("k_uu", "k_vv", "k_uv")}


def stretch_material(material: ClothMaterial, bend_stiffness, stretch=None) -> ClothMaterial:
    """``material`` with bending stiffness ``bend_stiffness`` [N·m] and its membrane stiffnesses k_uu, k_vv
    and k_uv [N/m] times ``stretch`` [-] (() tensors or floats; None keeps them).

    One factor for all three (a softer or stiffer fabric of the same weave): the ratios of the orthotropic
    stiffness matrix stay the template fabric's. On a hanging skirt, warp and weft factors apart are not
    identifiable (docs/BENCHMARKS.md, "Membrane stretch"), and the shear, which a drape under gravity barely
    loads, follows them so that the factor scales the membrane energy as a whole.
    """
    if stretch is None:
        return replace(material, bend_stiffness=bend_stiffness)
    return replace(
        material,
        bend_stiffness=bend_stiffness,
        k_uu=material.k_uu * stretch,
        k_vv=material.k_vv * stretch,
        k_uv=material.k_uv * stretch,
    )


class FitParameters(nn.Module):
    """The fit variables: a `ControlCage` (pattern), an optional `BodyModel`, the log bending stiffness, the
    log membrane stretch scale s (the factor of the base material's k_uu, k_vv, k_uv is
    `bounded_stretch` (s, ``stretch_bound``)) and the waist's height change (`bounded_shift` of
    ``raw_waist_shift``, ``waist_shift_bound``; it moves a skirt's or trousers' waist attachments, and
    nothing on a garment without any).

    Args:
        cage: the pattern's control cage, or `FreeVertices` (its ``handles`` parameter is optimised).
        body: a `BodyModel` (batch 1) whose vertices are the drape's body, or None for a fixed body.
        log_bend_stiffness: initial log k_b (k_b in [N·m]).
        log_stretch: initial s [-] (0: the base material's membrane).
        stretch_bound: the factor stays within (1/``stretch_bound``, ``stretch_bound``) [-].
        waist_shift_bound: the waist's height change stays within ±``waist_shift_bound`` [m].

    ``forward()`` returns `FitVariables`.
    """

    def __init__(
        self,
        cage: ControlCage,
        body: nn.Module | None,
        log_bend_stiffness: float,
        log_stretch: float = 0.0,
        stretch_bound: float = 30.0,
        waist_shift_bound: float = 0.15,
    ):
        super().__init__()
        self.cage = cage
        self.body = body
        dtype = cage.handles.dtype
        self.log_bend_stiffness = nn.Parameter(torch.tensor(float(log_bend_stiffness), dtype=dtype))
        self.log_stretch = nn.Parameter(torch.tensor(float(log_stretch), dtype=dtype))
        self.stretch_bound = float(stretch_bound)
        self.raw_waist_shift = nn.Parameter(torch.zeros((), dtype=dtype))
        self.waist_shift_bound = float(waist_shift_bound)

    @classmethod
    def from_config(
        cls,
        garment: GarmentMesh,
        config: FitConfig,
        body: nn.Module | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> FitParameters:
        """The variables of a fit of ``garment``: its `ControlCage` with ``config``'s tying options (or
        `FreeVertices` when ``config.cage`` is False), ``body``, k_b = ``config.initial_bend_stiffness``, the
        base membrane times ``config.initial_stretch`` bounded by ``config.stretch_bound``, the waist at its
        placement height."""
        if config.cage:
            cage = ControlCage(
                garment,
                tie_mirrored=config.tie_mirrored,
                tie_symmetric=config.tie_symmetric,
                tie_seams=config.tie_seams,
                tie_close=config.tie_close,
            )
        else:
            cage = FreeVertices(garment)
        log_kb = math.log(config.initial_bend_stiffness)
        log_stretch = unbounded_stretch(config.initial_stretch, config.stretch_bound)
        return cls(
            cage.to(dtype),
            body,
            log_kb,
            log_stretch=log_stretch,
            stretch_bound=config.stretch_bound,
            waist_shift_bound=config.waist_shift_bound,
        )

    def forward(self) -> FitVariables:
        rest_uv = self.cage()
        body_verts = None if self.body is None else self.body().vertices[0]
        bend_stiffness = self.log_bend_stiffness.exp()
        fitted = self.body is not None and self.body.phenotype_logits.requires_grad
        phenotypes = self.body.phenotypes if fitted else None
        return FitVariables(
            rest_uv, body_verts, bend_stiffness, phenotypes, self.stretch(), self.waist_shift()
        )

    def stretch(self) -> torch.Tensor:
        """() the factor [-] of the base material's membrane stiffnesses (`bounded_stretch`)."""
        return bounded_stretch(self.log_stretch, self.stretch_bound)

    def waist_shift(self) -> torch.Tensor:
        """() the waist attachments' height change [m] (`bounded_shift`)."""
        return bounded_shift(self.raw_waist_shift, self.waist_shift_bound)


@dataclass
class ObjectiveOutput:
    """One drape and its loss (`FitObjective.forward`); the graph is kept for ``loss.backward()``.

    Attributes:
        loss: () the weighted sum of ``terms``.
        terms: term name (`TERM_NAMES`) -> () unweighted loss term, in the order they are summed.
        x: (Vs, 3) the drape [m].
        rest_uv: (V, 2) [m]; body_verts: (Vb, 3) [m] or None; bend_stiffness: () [N·m]: the variables.
        stretch: () the membrane stiffness factor [-] (`FitVariables.stretch`), or None (the base's).
        waist_shift: () the waist's height change [m] (`FitVariables.waist_shift`), or None (none).
        stats: the drape's diagnostics (`sim.differentiable.drape` ``stats``; the backward adds to it).
        openings: the garment's openings matched to the scan's, on ``x`` (`FitObjective.openings`).
    """

    loss: torch.Tensor
    terms: dict[str, torch.Tensor]
    x: torch.Tensor
    rest_uv: torch.Tensor
    body_verts: torch.Tensor | None
    bend_stiffness: torch.Tensor
    stretch: torch.Tensor | None
    waist_shift: torch.Tensor | None
    stats: dict
    openings: list[BoundaryLoop]


class FitObjective(nn.Module):
    """The fit loss of a garment against a scan target, through the differentiable drape (paper §4.2.5).

    Buffers (follow ``.to()``, in ``state_dict()``): ``scan_points`` (P, 3) [m], a fixed random subset of
    ``config.max_scan_points`` of the target's garment points (seeded by ``config.seed``); ``skin_points``
    (Q, 3) [m] likewise of its body points, only when the body is a fit variable (``body_faces`` given
    without ``fixed_body_verts``) and the target has some, else None; ``scan_boundary_<k>`` (n, 3) [m]
    per scan opening (its name, which may hold dots: ``boundary_names[k]``); ``weight_<term>`` () per
    loss term (`TERM_NAMES`, from ``config.weights``: the buffers are the weights used);
    ``initial_phenotypes`` (1, P) [-] (the prior's centre) or None; ``opening_least`` (K,) [m], the
    shortest openings the scan allows, and ``opening_most`` (K,) [m], the longest the fit allows (inf but for
    the openings held at the template's length; `_register_opening_lengths`). Non-persistent: the template's
    ``template_uv`` (V, 2) [m] and its rest areas and edge inverses, ``fixed_body_verts`` (Vb, 3) [m] or
    None, ``body_faces`` (Fb, 3) int64 or None.

    Attributes (not moved by ``.to()``): ``garment`` (`GarmentMesh`), ``config`` (`FitConfig`: robust
    kernels, samples, drape and adjoint options), ``material`` (`ClothMaterial`; k_b is the variable's, and
    k_uu, k_vv, k_uv are scaled by the stretch variable: `material_at`),
    ``cloth_model`` (the `ClothModel` on the CPU, rebuilt for the buffers' dtype when it changes).

    Args:
        garment: the meshed and placed template.
        target: the scan target.
        config: the fit configuration (default `FitConfig()`).
        material: the base cloth material (default `ClothMaterial()`).
        body_faces: (Fb, 3) int64 body triangles, with a body.
        fixed_body_verts: (Vb, 3) [m] the body when it is not a fit variable.
        initial_phenotypes: (1, P) phenotypes of the phenotype prior's centre (with a fitted body).
        dtype: of the buffers and the cloth model (float32 for fits, float64 for tiny tests).

    Limitations: one garment and one body (no batch).
    """

    def __init__(
        self,
        garment: GarmentMesh,
        target: ScanTarget,
        config: FitConfig | None = None,
        *,
        material: ClothMaterial | None = None,
        body_faces: torch.Tensor | None = None,
        fixed_body_verts: torch.Tensor | None = None,
        initial_phenotypes: torch.Tensor | None = None,
        dtype: torch.dtype = torch.float32,
    ):
        super().__init__()
        self.config = FitConfig() if config is None else config
        self.garment = garment
        self.material = material if material is not None else ClothMaterial()
        self._register_template(garment, dtype)
        self._register_target(
            target, fit_body=body_faces is not None and fixed_body_verts is None, dtype=dtype
        )
        for name in TERM_NAMES:
            self.register_buffer(
                f"weight_{name}", torch.tensor(getattr(self.config.weights, name), dtype=dtype)
            )
        fixed = None if fixed_body_verts is None else fixed_body_verts.to(dtype)
        self.register_buffer("fixed_body_verts", fixed, persistent=False)
        faces = None if body_faces is None else body_faces.to(torch.int64)
        self.register_buffer("body_faces", faces, persistent=False)
        self.register_buffer("initial_phenotypes", initial_phenotypes)
        self.seam_segments = seam_segments(garment)
        self.loops = [lp for lp in garment.boundary_loops if lp.name in self.boundary_names]
        self._register_opening_lengths(target, dtype)
        self._model: ClothModel = ClothModelBuilder(self.material).add_garment(garment).finalize(dtype=dtype)

    @classmethod
    def from_parameters(
        cls,
        params: FitParameters,
        garment: GarmentMesh,
        target: ScanTarget,
        config: FitConfig | None = None,
        *,
        body_mesh: tuple[torch.Tensor, torch.Tensor] | None = None,
        material: ClothMaterial | None = None,
    ) -> FitObjective:
        """The objective of a fit of ``params``, in their dtype: with their body (a fit variable: its faces,
        the skin term, the prior about its current phenotypes), else on the fixed ``body_mesh``
        (verts (Vb, 3) [m], faces (Fb, 3)) or on no body."""
        body = params.body
        fixed = body_mesh if body is None else None
        return cls(
            garment,
            target,
            config,
            material=material,
            body_faces=body.faces if body is not None else None if fixed is None else fixed[1],
            fixed_body_verts=None if fixed is None else fixed[0],
            initial_phenotypes=None if body is None else body.phenotypes.detach().clone(),
            dtype=params.cage.handles.dtype,
        )

    def _register_template(self, garment: GarmentMesh, dtype: torch.dtype) -> None:
        template_uv = garment.vert_uv.to(dtype)
        self.register_buffer("template_uv", template_uv, persistent=False)
        # template constants of the rest-shape terms, evaluated ~60 times per step by a proximal rest step
        tri = garment.tri_vertices
        self.register_buffer("template_area", signed_rest_areas(template_uv, tri), persistent=False)
        self.register_buffer("template_inverse", template_edge_inverse(template_uv, tri), persistent=False)
        self.register_buffer("design_modes", design_modes(template_uv, garment.vert_panel), persistent=False)
        for name, value in curvature_frames(template_uv, garment)._asdict().items():
            self.register_buffer(f"curvature_{name}", value, persistent=False)
        # triangles across the darts, held above `DART_KEEP` of their opening by the rest-area term
        self.register_buffer("dart_tri", dart_triangles(garment), persistent=False)
        self.register_buffer("dart_area", signed_rest_areas(template_uv, self.dart_tri), persistent=False)

    def _register_target(self, target: ScanTarget, fit_body: bool, dtype: torch.dtype) -> None:
        gen = torch.Generator().manual_seed(self.config.seed)
        limit = self.config.max_scan_points

        def subset(points: torch.Tensor) -> torch.Tensor:  # a fixed random subset of max_scan_points
            points = points.to(dtype)
            if points.shape[0] > limit:
                points = points[torch.randperm(points.shape[0], generator=gen)[:limit]]
            return points

        self.register_buffer("scan_points", subset(target.garment_points))
        skin = target.body_points
        use_skin = fit_body and skin is not None and skin.shape[0] > 0
        self.register_buffer("skin_points", subset(skin) if use_skin else None)
        seen = getattr(target, "seen_sides", None)  # absent from set-ups saved before it existed
        partial = seen is not None and not bool(seen.all())
        self.register_buffer("seen_sides", seen.bool() if partial else None, persistent=False)
        self.boundary_names = list(target.boundaries)
        for k, points in enumerate(target.boundaries.values()):
            self.register_buffer(f"scan_boundary_{k}", points.to(dtype))

    def _register_opening_lengths(self, target: ScanTarget, dtype: torch.dtype) -> None:
        """The K matched openings of ``config.opening_length_names`` held no shorter than the scan shows
        them, and those of ``config.opening_template_names`` no shorter than the template's (and no longer
        with ``config.opening_template_hold`` ``"exact"``):
        ``opening_names``, ``opening_traced`` (K floats [m]: the length the scan's points trace,
        `scan_loop_length` with the placed garment's opening its reference; nan where they trace none or
        are not asked), ``opening_seen`` (K floats: the share of the loop's angular bins that hold scan
        points; nan where not asked), ``opening_edges`` (their rest edges, `rest_loop_edges`) and the buffer
        ``opening_least`` (K,) [m], the traced lengths less ``config.opening_length_tolerance`` (with the
        mirrored panels tied, a mirrored pair's both at the better-seen one's, `mirrored_lengths`; whose
        traces: ``opening_held_to``, K lists of names, empty where none); on a
        partial scan (``seen_sides``), and for the template's openings, no less than the template's
        either; the buffer ``opening_most`` (K,) [m]: ``opening_least`` for the template's openings held
        ``"exact"``, inf for the others. ``opening_panels`` and ``opening_shares``: the panel of each rest
        edge and the template's split of each opening between its panels (`rest_loop_shares`)."""
        cfg = self.config
        self.opening_names, self.opening_traced, self.opening_seen, self.opening_edges = [], [], [], []
        self.opening_held_to = []
        traced = self._traced_openings(target)
        # hems cut off with the floor: their start is all the set-up could measure of them (the fits of piled
        # trousers widened such unheld hems 8.2 cm past it); `getattr`: older set-ups' targets
        cut_off = set(getattr(target, "held_openings", ()))
        # a pattern with its mirrored panels tied has one length for a mirrored pair (not for a cut-off hem)
        pairs = {name: v for name, v in traced.items() if name not in cut_off}
        held_to = mirrored_lengths(pairs) if cfg.cage and cfg.tie_mirrored else {}
        least, most = [], []
        for loop in self.garment.boundary_loops:
            measured = loop.name in traced
            cut = loop.name in cut_off
            held = loop.name in cfg.opening_template_names or cut
            if not (measured or held):
                continue
            length, seen = traced.get(loop.name, (math.nan, math.nan))
            hold, names = held_to.get(loop.name, (length, [loop.name]))
            edges = rest_loop_edges(self.garment, loop)
            bound = hold * (1.0 - cfg.opening_length_tolerance)
            if self.seen_sides is not None or held:
                # A scan from one side shows half a hem at most, and the fits narrowed what it did not show
                # (a front-only dress's hem 28.7 cm short, the template's 12.5): what the scan cannot show,
                # the fit does not take in.
                template = float(rest_loop_length(self.template_uv.double(), edges))
                bound = max(bound, template) if math.isfinite(bound) else template
            if math.isfinite(bound):
                self.opening_names.append(loop.name)
                self.opening_traced.append(length)
                self.opening_seen.append(seen)
                self.opening_edges.append(edges)
                self.opening_held_to.append(names if math.isfinite(hold) else [])
                least.append(bound)
                # the scan cannot measure these (a neck's trace 5.5 cm short to 4.2 cm long), and the fits
                # moved them whatever the truth: shrank necks, and grew a dress's armholes by 2-4 cm onto the
                # rims of holes under the arms (docs/BENCHMARKS.md, "Openings held at the template's")
                most.append(bound if cut or (held and cfg.opening_template_hold == "exact") else math.inf)
        self.register_buffer("opening_least", torch.tensor(least, dtype=dtype).reshape(-1))
        self.register_buffer("opening_most", torch.tensor(most, dtype=dtype).reshape(-1))
        # each opening's panels and the template's split of it between them (`opening_split_loss`)
        self.opening_panels = [rest_loop_panels(self.garment, e) for e in self.opening_edges]
        self.opening_shares = [
            rest_loop_shares(self.template_uv, e, p)
            for e, p in zip(self.opening_edges, self.opening_panels, strict=True)
        ]

    def _traced_openings(self, target: ScanTarget) -> dict[str, tuple[float, float]]:
        """Opening name -> ``(length [m], seen [0, 1])`` as the scan's points trace it (`scan_loop_length`),
        for the openings of ``config.opening_length_names`` that the scan shows: the placed garment's own
        opening bridges the gaps where the scan shows the loop in part (a hole over a hem)."""
        placed = self.garment.sim_positions().detach().double()
        return {
            loop.name: scan_loop_length(
                target.boundaries[loop.name],
                bin_length=self.config.opening_length_bin,
                reference=placed[loop.vertices],
            )
            for loop in self.garment.boundary_loops
            if loop.name in self.config.opening_length_names and loop.name in self.boundary_names
        }

    # -- the pieces ----------------------------------------------------------------------------------------

    @property
    def scan_boundaries(self) -> dict[str, torch.Tensor]:
        """Scan opening name -> (k, 3) scan points [m] (the ``scan_boundary_*`` buffers)."""
        return {name: getattr(self, f"scan_boundary_{k}") for k, name in enumerate(self.boundary_names)}

    @property
    def curvature_frames(self) -> CurvatureFrames:
        """The template's `curvature_frames` (the ``curvature_*`` buffers)."""
        return CurvatureFrames(*(getattr(self, f"curvature_{name}") for name in CurvatureFrames._fields))

    @property
    def weights(self) -> LossWeights:
        """The loss weights of the ``weight_*`` buffers."""
        return LossWeights(**{name: float(self.weight(name)) for name in TERM_NAMES})

    def weight(self, term: str) -> torch.Tensor:
        """() the weight buffer of loss term ``term``."""
        return getattr(self, f"weight_{term}")

    def weighted_sum(self, terms: dict[str, torch.Tensor]) -> torch.Tensor:
        """() Σ weight · term over ``terms`` (term name -> () value)."""
        return sum(self.weight(k) * v for k, v in terms.items())

    @property
    def cloth_model(self) -> ClothModel:
        """The garment's `ClothModel` in the buffers' dtype, on the CPU: the simulator runs there whatever
        the buffers' device (`drape` returns the drape on the variables' device)."""
        if self._model.dtype != self.template_uv.dtype:
            builder = ClothModelBuilder(self.material).add_garment(self.garment)
            self._model = builder.finalize(device="cpu", dtype=self.template_uv.dtype)
        return self._model

    def body_or_fixed(self, body_verts: torch.Tensor | None) -> torch.Tensor | None:
        """``body_verts``, or the fixed body (None when there is none) when it is None."""
        return self.fixed_body_verts if body_verts is None else body_verts

    def openings(self, x: torch.Tensor) -> list[BoundaryLoop]:
        """The garment's openings matched to the scan's, on the drape ``x`` (Vs, 3): the loops, but a neck
        that a folded collar covers is its fold (`folded_collar_loop`), the top edge the scan shows."""
        return [folded_collar_loop(x, lp) if lp.name == "neck" else lp for lp in self.loops]

    def rest_terms(self, rest_uv: torch.Tensor) -> dict[str, torch.Tensor]:
        """The loss terms of the rest pattern alone, unweighted: seam length, curvature, and rest area (the
        mesh's triangles, and those across its darts: `dart_triangles`), rest shape, pattern change and the
        openings' length and split when their weights are positive. ``rest_uv``: (V, 2) [m]."""
        terms = {
            "seam_length": seam_length_loss(rest_uv, self.garment, segments=self.seam_segments),
            "curvature": curvature_loss(
                rest_uv, self.template_uv, self.garment, frames=self.curvature_frames
            ),
        }
        tri = self.garment.tri_vertices
        if self.weight_rest_area > 0:
            terms["rest_area"] = rest_area_loss(
                rest_uv, self.template_uv, tri, template_area=self.template_area
            )
            if len(self.dart_tri):
                terms["rest_area"] = terms["rest_area"] + rest_area_loss(
                    rest_uv,
                    self.template_uv,
                    self.dart_tri,
                    threshold=DART_KEEP,
                    template_area=self.dart_area,
                )
        if self.weight_rest_shape > 0:
            terms["rest_shape"] = rest_distortion_loss(
                rest_uv, self.template_uv, tri, template_inverse=self.template_inverse
            )
        if self.weight_pattern_change > 0:
            terms["pattern_change"] = self._pattern_change(rest_uv)
        if self.weight_opening_length > 0 and self.opening_edges:
            terms["opening_length"] = opening_length_loss(
                rest_uv, self.opening_edges, self.opening_least, self.opening_most
            )
        if self.weight_opening_split > 0 and self.opening_edges:
            terms["opening_split"] = opening_split_loss(
                rest_uv, self.opening_edges, self.opening_panels, self.opening_shares
            )
        return terms

    def _pattern_change(self, rest_uv: torch.Tensor) -> torch.Tensor:
        panel = self.garment.vert_panel
        return pattern_change_loss(rest_uv, self.template_uv, panel, modes=self.design_modes)

    def rest_loss(self, rest_uv: torch.Tensor) -> torch.Tensor:
        """() the weighted sum of `rest_terms` at ``rest_uv`` (V, 2) [m]. Where `rest_kernels_available`,
        all but the pattern change come from the C++ kernels as one autograd node (`fused_rest_terms`: the
        same value and gradient to rounding, at a fraction of the cost; a fit's proximal step evaluates this
        ~40 times an iteration)."""
        if not rest_kernels_available(rest_uv):
            return self.weighted_sum(self.rest_terms(rest_uv))
        fused = fused_rest_terms(rest_uv, self._rest_kernel_calls(rest_uv.dtype))
        if self.weight_pattern_change > 0:
            fused = fused + self.weight_pattern_change * self._pattern_change(rest_uv)
        return fused

    def _rest_kernel_calls(self, dtype: torch.dtype) -> list[RestKernelCall]:
        """The `rest_terms` of the mesh as `fused_rest_terms`' kernel calls (weights and means folded in);
        kept while the dtype, the weights and the buffers (``.to()`` replaces them) stay the same."""
        names = ("seam_length", "curvature", "rest_area", "rest_shape", "opening_length", "opening_split")
        weights = tuple(float(self.weight(k)) for k in names)
        key = (dtype, weights, self.template_area.data_ptr())
        cache = self.__dict__.setdefault("_rest_kernel_cache", {})
        if key not in cache:
            cache.clear()
            cache[key] = self._build_rest_kernel_calls(dtype, *weights)
        return cache[key]

    def _build_rest_kernel_calls(self, dtype, w_seam, w_curvature, w_area, w_shape, w_length, w_split):
        def cpu(t: torch.Tensor, floating: bool = True) -> torch.Tensor:
            return t.to(device="cpu", dtype=dtype if floating else torch.int64).contiguous()

        seg, frames = self.seam_segments, self.curvature_frames
        calls = []
        if len(seg):
            calls.append(("rest_seam_length", (cpu(seg, False), w_seam / len(seg))))
        if len(frames.triplets):
            triplets = cpu(frames.triplets, False)
            tables = (cpu(frames.edges), cpu(frames.edges_perp), cpu(frames.norm))
            calls.append(("rest_curvature", (triplets, *tables, w_curvature / len(frames.triplets))))
        w_area, w_shape = max(w_area, 0.0), max(w_shape, 0.0)
        no_shape = torch.zeros(0, 2, 2, dtype=dtype)
        if w_area > 0 or w_shape > 0:
            inverse = cpu(self.template_inverse) if w_shape > 0 else no_shape
            area = (cpu(self.template_area), REST_AREA_THRESHOLD, w_area)
            shape = (inverse, REST_DISTORTION_THRESHOLD, w_shape)
            calls.append(("rest_triangle_hinges", (cpu(self.garment.tri_vertices, False), *area, *shape)))
        if w_area > 0 and len(self.dart_tri):
            darts = (cpu(self.dart_tri, False), cpu(self.dart_area), DART_KEEP, w_area, no_shape, 0.0, 0.0)
            calls.append(("rest_triangle_hinges", darts))
        w_length, w_split = max(w_length, 0.0), max(w_split, 0.0)
        if self.opening_edges and (w_length > 0 or w_split > 0):
            edges, slot, slot_opening, shares = opening_slots(
                self.opening_edges, self.opening_panels, self.opening_shares
            )
            index = [cpu(t, False) for t in (edges, slot, slot_opening)]
            tables = (cpu(self.opening_least), cpu(self.opening_most), cpu(shares))
            calls.append(("rest_openings", (*index, *tables, w_length, w_split)))
        return calls

    def drape(
        self,
        rest_uv: torch.Tensor,
        body_verts: torch.Tensor | None,
        bend_stiffness: torch.Tensor,
        start: ClothState,
        *,
        stretch: torch.Tensor | None = None,
        waist_shift: torch.Tensor | None = None,
        adjoint: str | None = None,
        drape_steps: int | None = None,
        stats: dict | None = None,
    ) -> torch.Tensor:
        """(Vs, 3) the differentiable drape [m] from ``start`` (`sim.differentiable.drape`) at `material_at`
        (``bend_stiffness``, ``stretch``), the waist attachments ``waist_shift`` [m] above their placement
        height (None: at it), with ``config``'s adjoint and frames, or ``adjoint`` / ``drape_steps``
        instead."""
        from torch_diffavatar.sim.differentiable import drape

        adjoint = self.config.adjoint if adjoint is None else adjoint
        return drape(
            rest_uv,
            self.cloth_model,
            body_verts,
            self.material_at(bend_stiffness, stretch),
            body_faces=None if body_verts is None else self.body_faces,
            state=start,
            config=drape_config(self.config, drape_steps, adjoint),
            adjoint=adjoint,
            options=adjoint_options(self.config, adjoint),
            stats=stats,
            attach_height=self.attach_height(waist_shift),
        )

    def attach_height(self, waist_shift: torch.Tensor | None) -> torch.Tensor | None:
        """(A,) the waist attachments' target heights [m] ``waist_shift`` [m] above their placement, or
        None (the model's own) without a shift or without attachments."""
        model = self.cloth_model
        if waist_shift is None or model.attach_vertices.numel() == 0:
            return None
        return model.attach_height + waist_shift.to(model.attach_height.dtype)

    def material_at(self, bend_stiffness, stretch=None) -> ClothMaterial:
        """The base ``material`` at the fit's material variables (`stretch_material`): k_b
        ``bend_stiffness`` [N·m], the membrane times ``stretch`` [-] (None: the base's)."""
        return stretch_material(self.material, bend_stiffness, stretch)

    # -- the loss ------------------------------------------------------------------------------------------

    def forward(
        self,
        variables: FitVariables | torch.Tensor,
        start: ClothState,
        *,
        body_verts: torch.Tensor | None = None,
        bend_stiffness: torch.Tensor | None = None,
        phenotypes: torch.Tensor | None = None,
        stretch: torch.Tensor | None = None,
        waist_shift: torch.Tensor | None = None,
        adjoint: str | None = None,
        drape_steps: int | None = None,
    ) -> ObjectiveOutput:
        """Drape from ``start`` at the fit variables and compute the loss (graph kept for backward).

        Args:
            variables: `FitVariables` (`FitParameters` output), or the rest coordinates (V, 2) [m] with the
                other variables as keywords.
            start: the drape's start (warm start: the previous drape, velocities zeroed).
            body_verts: (Vb, 3) [m] (default: the fixed body); bend_stiffness: () [N·m] (required with
                a tensor ``variables``); phenotypes: (1, P) fitted phenotypes (the prior), or None;
                stretch: () membrane stiffness factor [-] or None (the base material's); waist_shift: ()
                the waist's height change [m] or None.
            adjoint, drape_steps: override ``config.adjoint`` / ``config.drape_steps`` for this drape
                (e.g. a short trajectory replay when the equilibrium adjoint fails).

        Raises:
            SimulationError: the drape blew up.
        """
        if isinstance(variables, FitVariables):
            rest_uv, body_verts = variables.rest_uv, variables.body_verts
            bend_stiffness, phenotypes = variables.bend_stiffness, variables.phenotypes
            stretch, waist_shift = variables.stretch, variables.waist_shift
        else:
            rest_uv = variables
            if bend_stiffness is None:
                raise ValueError("FitObjective: pass bend_stiffness () [N·m] with a rest_uv tensor")
        body_verts = self.body_or_fixed(body_verts)
        stats: dict = {}
        x = self.drape(
            rest_uv, body_verts, bend_stiffness, start, stretch=stretch, waist_shift=waist_shift,
            adjoint=adjoint, drape_steps=drape_steps, stats=stats,
        )  # fmt: skip
        openings = self.openings(x)
        terms = self.drape_terms(x, openings)
        terms.update(self.rest_terms(rest_uv))
        terms.update(self.body_terms(body_verts, phenotypes))
        loss = self.weighted_sum(terms)
        return ObjectiveOutput(
            loss, terms, x, rest_uv, body_verts, bend_stiffness, stretch, waist_shift, stats, openings
        )

    def drape_terms(self, x: torch.Tensor, openings: list[BoundaryLoop]) -> dict[str, torch.Tensor]:
        """The unweighted terms of the drape ``x`` (Vs, 3) [m]: ``interior``, and ``boundary`` over the
        matched ``openings`` (`openings`) when there are any."""
        cfg = self.config
        faces = self.garment.sim_faces if cfg.interior_to_surface else None
        seen = None
        if self.seen_sides is not None:  # a partial scan: only the cloth on the sides it sees is pulled
            seen = seen_side_weights(x, self.garment.sim_faces, self.seen_sides)
        terms = {
            "interior": interior_loss(
                x,
                self.scan_points,
                garment_faces=faces,
                robust=cfg.interior_robust,
                scale=cfg.robust_scale,
                weights=seen,
            )
        }
        if openings:
            terms["boundary"] = boundary_loss(
                x,
                openings,
                self.scan_boundaries,
                samples_per_edge=cfg.boundary_samples,
                robust=cfg.boundary_robust,
                scale=cfg.robust_scale,
                trim=cfg.boundary_trim,
                gap_bin=cfg.boundary_gap_bin,
                seen=seen,
            )
        return terms

    def body_terms(
        self, body_verts: torch.Tensor | None, phenotypes: torch.Tensor | None
    ) -> dict[str, torch.Tensor]:
        """The unweighted terms of the body: ``phenotype_prior`` (squared distance of the fitted
        ``phenotypes`` (1, P) from ``initial_phenotypes``) and ``skin`` (`skin_loss` of ``body_verts``
        (Vb, 3) [m] to ``skin_points``, when its weight is positive); each only when its data is there."""
        terms = {}
        if self.initial_phenotypes is not None and phenotypes is not None:
            terms["phenotype_prior"] = ((phenotypes - self.initial_phenotypes) ** 2).sum()
        if self.skin_points is not None and self.weight_skin > 0:
            terms["skin"] = skin_loss(
                body_verts,
                self.body_faces,
                self.skin_points,
                robust=self.config.interior_robust,
                scale=self.config.robust_scale,
            )
        return terms
