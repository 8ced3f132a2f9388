"""The fit (paper §4.2): pattern cage, body and material optimised through the differentiable drape.

`Fitter` is the driver of a ``torch.optim.Adam`` loop over `FitParameters` (control-cage handles ζ, body
phenotypes / translation / pose, log bending stiffness, log membrane stretch scale; one parameter group and
learning rate each) and a
`FitObjective` (the loss, `torch_diffavatar.objective`). Every iteration drapes the garment, warm-started
from the previous equilibrium (the very first start state is a full `sew_and_drape` of the placed template,
or the winner of several, `torch_diffavatar.fit_start` and `fit_race`), backpropagates through the drape
and steps. The terms of the rest pattern alone (seam length, curvature, rest area and shape) are cheap and
known in closed form, so the cage's step is proximal for them: Adam steps on the rest, and L-BFGS minimises
them around its result (`rest_prox`, ``FitConfig.rest_prox_iterations``). ``scripts/fit_loop.py`` is the same
fit as a plain loop, without the guards.

Guards: non-finite gradient entries are zeroed (counted, never reach the parameters); a step that would
shrink a rest triangle below ``min_rest_area_ratio`` of its template area (inverting it), make a
parameter non-finite, or blow up the drape (`SimulationError`, non-finite positions, a vertex jumping
more than ``max_drape_jump``) is rejected and retried at half the size (``max_retries`` times; then the
step is dropped and the learning rates halved). TensorBoard (``<out>/tb``, `torch_diffavatar.fit_logging`):
every loss term, Chamfer distance, rest/draped mesh quality, the material, body parameters, pictures of
the pattern and the drape, the draped mesh. A tqdm bar on stderr. A checkpoint (``<out>/checkpoint.pt``,
atomic) after every iteration; ``resume=True`` continues from it bit for bit. The report:
`torch_diffavatar.fit_report` (Chamfer distances [m]; loss terms in the units of `torch_diffavatar.losses`
times their weights).

The configuration (`FitConfig`, `LossWeights`, `load_config` …) lives in `torch_diffavatar.fit_config` and
is re-exported here.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from torch_diffavatar.errors import InputError, SimulationError
from torch_diffavatar.fit_checkpoint import (
    CHECKPOINT,
    SETUP,
    atomic_save,
    load_progress,
    progress_state,
    start_from,
    start_state,
    upgraded,
)
from torch_diffavatar.fit_config import (
    BEND_STIFFNESS_RANGE,
    CONFIG_DIR,
    FIT_MAX_STRAIN,
    FitConfig,
    LossWeights,
    config_from_dict,
    config_to_dict,
    default_config_path,
    load_config,
    with_fit_strain_limit,
    write_resolved_config,
)
from torch_diffavatar.fit_logging import (
    fit_scalars,
    log_evaluation,
    log_scalars,
    open_writer,
    progress_bar,
    update_bar,
)
from torch_diffavatar.fit_race import bar_span, opening, race
from torch_diffavatar.fit_report import fit_report, result_warnings, summarize
from torch_diffavatar.fit_start import Start, first_states, resew
from torch_diffavatar.losses import rest_area_ratio
from torch_diffavatar.objective import FitObjective, FitParameters, FitVariables, ObjectiveOutput, ScanTarget
from torch_diffavatar.pattern.garment_mesh import GarmentMesh
from torch_diffavatar.sim.forward_drape import PoseRoute
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.state import ClothState

__all__ = [
    "CHECKPOINT",
    "CONFIG_DIR",
    "FIT_MAX_STRAIN",
    "SETUP",
    "FitConfig",
    "FitObjective",
    "FitParameters",
    "FitResult",
    "FitVariables",
    "Fitter",
    "LossWeights",
    "ObjectiveOutput",
    "ScanTarget",
    "config_from_dict",
    "config_to_dict",
    "default_config_path",
    "load_config",
    "lr_factor",
    "param_groups",
    "rest_prox",
    "result_warnings",
    "with_fit_strain_limit",
    "write_resolved_config",
]


def param_groups(params: FitParameters, config: FitConfig) -> list[dict]:
    """Adam parameter groups (name, params, lr) of the parameters with a positive learning rate; the
    others are frozen (``requires_grad=False``). InputError when there is none."""
    spec = [("cage", [params.cage.handles], config.lr_cage)]
    if params.body is not None:
        spec += [
            ("phenotypes", [params.body.phenotype_logits], config.lr_phenotypes),
            ("translation", [params.body.translation], config.lr_translation),
            ("pose", [params.body.pose], config.lr_pose),
        ]
    spec.append(("log_bend_stiffness", [params.log_bend_stiffness], config.lr_log_bend_stiffness))
    spec.append(("log_stretch", [params.log_stretch], config.lr_log_stretch))
    spec.append(("waist_shift", [params.raw_waist_shift], config.lr_waist_shift))
    for p in params.parameters():
        p.requires_grad_(False)
    groups = []
    for name, ps, lr in spec:
        if lr > 0:
            for p in ps:
                p.requires_grad_(True)
            groups.append({"name": name, "params": ps, "lr": lr})
    if not groups:  # the body's learning rates alone above 0, and no body to fit: Adam would fail
        raise InputError("nothing to fit: every variable with a learning rate above 0 is held fixed")
    return groups


def pattern_held(iteration: int, config: FitConfig) -> bool:
    """Whether iteration ``iteration`` (0-based) is one of the first ``config.pattern_delay``, in which the
    pattern stays as it is while the physical variables move."""
    return iteration < config.pattern_delay


def lr_factor(iteration: int, config: FitConfig, group: str = "") -> float:
    """Learning-rate factor of iteration ``iteration`` (0-based): a cosine from 1 to ``config.lr_final``
    over ``config.iterations``; 0 for the ``"cage"`` group while `pattern_held`."""
    if group == "cage" and pattern_held(iteration, config):
        return 0.0
    total = max(config.iterations - 1, 1)
    t = min(iteration / total, 1.0)
    return config.lr_final + (1.0 - config.lr_final) * 0.5 * (1.0 + math.cos(math.pi * t))


def rest_prox(
    optimizer: torch.optim.Adam,
    group: dict,
    rest_loss: Callable[[torch.Tensor], torch.Tensor],
    iterations: int,
    shift: torch.Tensor | None = None,
) -> torch.Tensor | None:
    """Move the cage handles from Adam's result ĉ to argmin_c R(c) + ½ Σ m (c − ĉ)², R = ``rest_loss``.

    m = (√v̂ + ε) / lr is the metric in which Adam's step is a gradient step (v̂ its bias-corrected second
    moment), so coordinates with a steady drape gradient keep Adam's move, and those Adam moved by
    its learning rate on a negligible gradient go where the rest terms want them. Solved by L-BFGS
    (``iterations``); a non-finite solution leaves Adam's result.

    ``shift``: the last step's correction c − ĉ, (H, 2) [m]. The rest terms pull the handles much the same
    way from one iteration to the next, so L-BFGS starts from ĉ + ``shift`` when that is the lower of the
    two: on the demo's fit it then reached in 25 iterations the objective that 50 reached from ĉ (lower, or
    within 3e-5 of it, from its tenth iteration on; docs/BENCHMARKS.md, "The proximal step started where the
    last one went").

    Args:
        optimizer: the Adam that just stepped; group: its cage group (``params``: the (H, 2) handles [m]);
        rest_loss: handles -> () weighted rest terms (`FitObjective.rest_loss` of the cage's rest_uv).

    Returns:
        this step's correction c − ĉ (H, 2) [m], for the next step's ``shift``; None when non-finite.
    """
    handles = group["params"][0]
    state = optimizer.state[handles]
    beta2 = group["betas"][1]
    vhat = state["exp_avg_sq"] / (1.0 - beta2 ** float(state["step"]))
    metric = (vhat.sqrt() + group["eps"]) / group["lr"]
    target = handles.detach().clone()

    def objective(c):
        return rest_loss(c) + 0.5 * (metric * (c - target) ** 2).sum()

    start = target
    if shift is not None and shift.shape == target.shape and torch.isfinite(shift).all():
        with torch.no_grad():
            if objective(target + shift) < objective(target):
                start = target + shift
    c = start.clone().requires_grad_(True)
    lbfgs = torch.optim.LBFGS(
        [c], max_iter=iterations, line_search_fn="strong_wolfe", tolerance_grad=1e-9, tolerance_change=1e-12
    )

    def closure():
        lbfgs.zero_grad()
        with torch.enable_grad():
            value = objective(c)
            value.backward()
        return value

    lbfgs.step(closure)
    if not torch.isfinite(c).all():
        return None
    with torch.no_grad():
        handles.copy_(c.detach())
    return c.detach() - target


def sanitize_grads(groups: list[dict]) -> int:
    """Zero the non-finite entries of the gradients of ``groups``' parameters; returns how many gradients
    had some."""
    count = 0
    for g in groups:
        for p in g["params"]:
            if p.grad is not None and not torch.isfinite(p.grad).all():
                count += 1
                p.grad = torch.nan_to_num(p.grad, nan=0.0, posinf=0.0, neginf=0.0)
    return count


def drape_rejection(out: ObjectiveOutput, start: ClothState, max_jump: float) -> str | None:
    """Why the drape of ``out`` cannot be accepted (non-finite, or a vertex moved more than ``max_jump``
    [m] from ``start``), or None."""
    if not (torch.isfinite(out.x).all() and torch.isfinite(out.loss)):
        return "non-finite drape or loss"
    if float((out.x.detach() - start.x).norm(dim=1).max()) > max_jump:
        return "drape jumped more than max_drape_jump"
    return None


def carried_trials(fitter, ev, start: ClothState, params: list, before: list) -> tuple:
    """(a no-argument trial for `backtrack`, the list of the starts it drapes from): ``fitter._trial(ev,
    s)`` with ``s`` = ``start``, or with ``config.carry_cloth_with_body`` ``start`` moved rigidly by the
    body's translation since ``before`` (``params``' values at which ``start`` lies on the body,
    `Fitter.step`'s), so that a trial drape starts with the cloth where it rested on the body. Left where
    the old drape was, a body moved 0.3 mm into a stiff T-shirt resting on its shoulders raised the loss by
    3.5 % (1 mm: 28 %) where the gradient promised a fall (docs/BENCHMARKS.md, "The cloth carried with the
    body"). Unmoved: a start with a linearization (its predicted equilibrium moves with the body already),
    or no body translation fitted."""
    body, trial = fitter.params.body, fitter._trial
    carry = fitter.config.carry_cloth_with_body and body is not None
    index = next((k for k, p in enumerate(params) if carry and p is body.translation), None)
    starts = []

    def carried() -> ObjectiveOutput | None:
        s = start
        if index is not None and start.linearization is None:
            shift = (params[index].detach() - before[index]).reshape(-1, 3)[0].to(start.x.dtype)
            s = ClothState(start.x + shift, start.v, None) if bool(shift.any()) else start
        starts.append(s)
        return trial(ev, s)

    return carried, starts


def backtrack(
    params: list[torch.Tensor],
    before: list[torch.Tensor],
    delta: list[torch.Tensor],
    trial: Callable[[], ObjectiveOutput | None],
    retries: int,
) -> tuple[ObjectiveOutput | None, float, int]:
    """Set ``params`` to ``before + scale · delta`` for scale 1, ½, ¼ … (``retries`` halvings) until
    ``trial()`` accepts them; returns (its evaluation or None when none was accepted, the last scale, the
    rejected trials)."""
    scale = 1.0
    for rejected in range(retries + 1):
        scale = 0.5**rejected
        with torch.no_grad():
            for p, b, d in zip(params, before, delta):
                p.copy_(b + scale * d)
        new = trial()
        if new is not None:
            return new, scale, rejected
    return None, scale, retries + 1


@torch.no_grad()
def parameter_rejection(params: FitParameters, objective: FitObjective, min_ratio: float) -> str | None:
    """Why ``params`` cannot be tried (a non-finite parameter, a bending stiffness outside
    `BEND_STIFFNESS_RANGE`, or a rest triangle of the cage that keeps no more than ``min_ratio`` of its
    template area), or None."""
    if not all(bool(torch.isfinite(p).all()) for p in params.parameters()):
        return "non-finite parameters"
    low, high = BEND_STIFFNESS_RANGE
    if not low <= float(params.log_bend_stiffness.exp()) <= high:
        return "bending stiffness outside its physical range"
    rest_uv = params.cage()
    if torch.isfinite(rest_uv).all():
        ratio = rest_area_ratio(rest_uv, objective.template_uv, objective.garment.tri_vertices)
        if bool((ratio > min_ratio).all()):
            return None
    return "rest triangle below min_rest_area_ratio"


def failure_reason(exc: SimulationError) -> str:
    """A failed drape's message without its advice and numbers, so that reasons of one kind count together."""
    return "drape failed: " + re.sub(r" [-+0-9.e]+(?= |$)", "", str(exc).split(" (")[0])


def _params_copy(params: nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in params.state_dict().items()}


def best_snapshot(iteration: int, loss: float, params: FitParameters, start: ClothState) -> dict:
    """What `Fitter.run` keeps of its lowest-loss iteration: iteration, loss, parameters, drape start."""
    return {"iteration": iteration, "loss": loss, "params": _params_copy(params), **start_state(start)}


def restore_best(
    ev: ObjectiveOutput,
    iteration: int,
    best: dict | None,
    params: FitParameters,
    evaluate: Callable[[ClothState], ObjectiveOutput | None],
) -> tuple[ObjectiveOutput, int]:
    """The evaluation of the lowest-loss iteration (`best_snapshot` ``best``) and that iteration, its
    parameters loaded into ``params``; ``ev`` (of ``iteration``) when that is the last. The checkpoint keeps
    the last iteration, so a resumed run continues from there."""
    if best is None or float(ev.loss.detach()) <= best["loss"]:
        return ev, iteration
    last = _params_copy(params)
    params.load_state_dict(best["params"])
    again = evaluate(start_from(best, best["start_x"].dtype))
    if again is None:  # cannot happen for a deterministic drape; keep the last iteration then
        params.load_state_dict(last)
        return ev, iteration
    return again, best["iteration"]


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


class Fitter:
    """Runs the fit loop on one garment / body / scan target (see the module docstring).

    Args:
        garment: the meshed and placed template (float64 as built is fine; cast inside).
        target: the scan target.
        config: the fit configuration.
        body: a float32 `BodyModel` initialised to the scan (fitted in place), or None with ``body_mesh``
            for a fixed body (or no body at all).
        body_mesh: (verts (Vb, 3), faces (Fb, 3)) of a fixed body, or None (ignored with ``body``).
        material: the base cloth material (its bending stiffness is replaced by the fitted one, and its
            membrane stiffnesses are scaled by the fitted stretch factor).
        start_state: the first warm start (e.g. a `sew_and_drape` result's state); None runs
            `sew_and_drape` from the placement.
        sewing_fallback: how to dress the body when sewing the placed garment on it fails
            (`sew_and_drape`'s ``fallback``; `sim.placement.a_pose_route` for a posed body).
        out_dir: where checkpoints and TensorBoard logs go (None: nowhere).
        progress: show a tqdm bar on stderr.
        dtype: float32 for fits (float64 for tiny tests).

    Attributes: ``params`` (`FitParameters`), ``objective`` (`FitObjective`), ``optimizer`` (Adam), and
    the bookkeeping a checkpoint keeps (`fit_checkpoint.PROGRESS`: ``iteration``, ``history``, ``best`` …).
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
        out_dir: str | Path | None = None,
        progress: bool = True,
        tensorboard: bool = True,
        dtype: torch.dtype = torch.float32,
    ):
        self.config, self.dtype, self.garment, self.target = config, dtype, garment, target
        self.params = FitParameters.from_config(garment, config, body, dtype)
        self.objective = FitObjective.from_parameters(
            self.params, garment, target, config, body_mesh=body_mesh, material=material
        )
        self.out_dir, self.progress = None if out_dir is None else Path(out_dir), progress
        self.tensorboard = tensorboard and self.out_dir is not None
        self.groups = [dict(g, base_lr=g["lr"]) for g in param_groups(self.params, config)]
        self.optimizer = torch.optim.Adam(self.groups)
        self.start_state, self.sewing_fallback = start_state, sewing_fallback
        # iteration 0, no history, no rejections, lr_scale 1 (shrunk by rejected steps, regrown by steps
        # accepted whole), no first / best evaluation yet (`fit_checkpoint.PROGRESS`)
        load_progress(self, {})
        self.result_iteration = 0  # the iteration whose evaluation `run` returned (see `keep_best`)
        self.race: dict | None = None  # the race of first drapes while it runs (`fit_race.race_state`)

    # -- one evaluation ------------------------------------------------------------------------------------

    def evaluate(self, start: ClothState, **overrides) -> ObjectiveOutput:
        """`FitObjective` at the current parameters, draped from ``start`` (``overrides``: its ``adjoint`` /
        ``drape_steps``)."""
        return self.objective(self.params(), start, **overrides)

    def rest_loss(self, handles: torch.Tensor | None = None) -> torch.Tensor:
        """The weighted rest terms (`FitObjective.rest_loss`) at the cage ``handles`` (default: its own)."""
        return self.objective.rest_loss(self.params.cage(handles))

    def _checked_evaluate(self, start: ClothState) -> ObjectiveOutput | None:
        """`evaluate`, or None when the drape blew up, jumped too far or gave non-finite values (the
        reason is counted in `rejection_reasons`)."""
        try:
            ev = self.evaluate(start)
        except SimulationError as exc:
            return self._reject(failure_reason(exc))
        reason = drape_rejection(ev, start, self.config.max_drape_jump)
        return ev if reason is None else self._reject(reason)

    def _reject(self, reason: str) -> None:
        self.rejection_reasons[reason] = self.rejection_reasons.get(reason, 0) + 1

    def _backward(self, ev: ObjectiveOutput, start: ClothState) -> ObjectiveOutput:
        """Backpropagate ``ev.loss``; if the adjoint fails, retry once with a short trajectory replay (its
        cost grows with the frames, which the equilibrium mode does not cap)."""
        self.optimizer.zero_grad(set_to_none=True)
        try:
            ev.loss.backward()
            return ev
        except SimulationError:
            self.adjoint_failures += 1
            if self.config.adjoint == "trajectory":
                raise
        self.optimizer.zero_grad(set_to_none=True)
        ev = self.evaluate(start, adjoint="trajectory", drape_steps=min(self.config.drape_steps, 3))
        ev.loss.backward()
        return ev

    # -- one step ------------------------------------------------------------------------------------------

    def _prox_group(self) -> dict | None:
        """The cage's Adam group when the proximal rest step is on and the handles have a gradient, the rest
        terms' gradient taken out of it (the proximal step handles them); else None."""
        group = next((g for g in self.optimizer.param_groups if g["name"] == "cage"), None)
        off = self.config.rest_prox_iterations == 0 or pattern_held(self.iteration, self.config)
        if off or group is None or group["params"][0].grad is None:
            return None
        with torch.enable_grad():
            (grad,) = torch.autograd.grad(self.rest_loss(), group["params"][0])
        group["params"][0].grad = group["params"][0].grad - grad
        return group

    def step(self, ev: ObjectiveOutput, start: ClothState) -> tuple[ObjectiveOutput, ClothState, int]:
        """Backward, Adam step (the cage's with its `rest_prox`) and the guards; returns (next evaluation,
        its start state, rejections)."""
        ev = self._backward(ev, start)
        cage_group = self._prox_group()
        self.nan_gradients += sanitize_grads(self.groups)
        for g in self.optimizer.param_groups:
            g["lr"] = g["base_lr"] * self.lr_scale * lr_factor(self.iteration, self.config, g["name"])
        params = [p for g in self.groups for p in g["params"]]
        before = [p.detach().clone() for p in params]
        self.optimizer.step()
        if cage_group is not None:
            prox = (self.optimizer, cage_group, self.rest_loss, self.config.rest_prox_iterations)
            self.prox_shift = rest_prox(*prox, self.prox_shift)
        delta, retries = [p.detach() - b for p, b in zip(params, before)], self.config.max_retries
        # trials continue from the accepted drape's end state (with `predict_warm_starts`, from the
        # equilibrium its backward's linearization predicts), except after a dropped step: then they
        # start where the reproduced drape started, so the halvings probe the very map (start -> drape)
        # whose gradient was taken (on a T-shirt fit that stalls, rejected trials 95 -> 61 in 30
        # iterations; it still stalls: docs/RESULTS_HISTORY.md)
        x, lin = ev.x.detach(), ev.stats.get("linearization") if self.config.predict_warm_starts else None
        next_start = start if self.trial_from_start else ClothState(x, torch.zeros_like(x), lin)
        trial, starts = carried_trials(self, ev, next_start, params, before)
        new, scale, rejected = backtrack(params, before, delta, trial, retries)
        if new is not None:
            self.lr_scale = min(1.0, self.lr_scale * (1.25 if scale == 1.0 else scale))
            self.trial_from_start = False
            return new, starts[-1], rejected
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

    def _trial(self, ev: ObjectiveOutput, start: ClothState) -> ObjectiveOutput | None:
        """The evaluation at the trial parameters from ``start``, or None when a guard rejects them:
        non-finite parameters, a rest triangle below ``min_rest_area_ratio``, a failed drape, or a loss more
        than ``max_loss_rise`` above that of ``ev`` (the reason is counted)."""
        reason = parameter_rejection(self.params, self.objective, self.config.min_rest_area_ratio)
        new = self._checked_evaluate(start) if reason is None else self._reject(reason)
        if new is None:
            return None
        if not float(new.loss.detach()) <= (1.0 + self.config.max_loss_rise) * float(ev.loss.detach()):
            return self._reject("loss rose more than max_loss_rise")
        return new

    # -- the run -------------------------------------------------------------------------------------------

    def _first_states(self, workers: int = 1) -> list[Start]:
        """`fit_start.first_states` here, ``workers`` sewings at a time (recorded in ``first_candidates``)."""
        with torch.no_grad():
            variables = self.params()
        if self.start_state is None:
            self.first_candidates = []
        kw = dict(start_state=self.start_state, sewing_fallback=self.sewing_fallback, workers=workers)
        return first_states(self.objective, variables, self.evaluate, self.first_candidates, **kw)

    def _first_state(self) -> ClothState:
        """The first warm start of the lowest loss (`_first_states`)."""
        return self._first_states()[0][1]

    def run(self, iterations: int | None = None, *, resume: bool = False, race_workers: int = 1) -> FitResult:
        """Run the loop up to ``iterations`` completed iterations (default ``config.iterations``).

        With ``resume``, continue from ``out_dir/checkpoint.pt`` when it exists, to the result of an
        uninterrupted run (one stopped during the race of first drapes too: `fit_race.opening`).
        ``race_workers``: first sewings and race candidates run at a time, in forked processes (`fit_race`).
        """
        total = self.config.iterations if iterations is None else iterations
        t0 = time.perf_counter()
        start, raced = opening(self, total, resume, race_workers), self.race is not None
        writer = open_writer(self.out_dir, self.config) if self.tensorboard else None
        bar = progress_bar(*bar_span(self, total)) if self.progress else None
        try:
            if raced:
                start = race(self, start, bar, race_workers)
                if writer is not None:  # the winner's iterations, which the race did not log
                    log_scalars(writer, self.history)
            ev = self._first_evaluation(start, writer, raced=raced)
            self.seconds += time.perf_counter() - t0
            ev, start = self._iterate(ev, start, total, writer, bar)
        finally:
            for closable in (bar, writer):
                if closable is not None:
                    closable.close()
        t0 = time.perf_counter()
        self.result_iteration = self.iteration
        if self.config.keep_best:
            ev, self.result_iteration = restore_best(
                ev, self.iteration, self.best, self.params, self._checked_evaluate
            )
        self.seconds += time.perf_counter() - t0
        x, rest_uv, body_verts = (
            None if t is None else t.detach() for t in (ev.x, ev.rest_uv, ev.body_verts)
        )
        return FitResult(self.params, x, rest_uv, body_verts, self.history, self.report(self._summary(ev)))

    def _first_evaluation(self, start: ClothState, writer, raced: bool) -> ObjectiveOutput:
        """The evaluation at ``start`` that the iterations continue from, noted as the first (unless a
        resumed run has one) and logged with pictures (at the winner's last iteration after a race)."""
        ev = self._checked_evaluate(start)
        if ev is None:
            raise SimulationError("the first drape of the fit failed (blow-up or non-finite values)")
        if self.first is None:
            self.first = self._summary(ev)
            log_evaluation(writer, ev, self._scalars(ev), 0, True, self.objective)
        elif raced:
            log_evaluation(writer, ev, self._scalars(ev), self.iteration, True, self.objective)
        self._note_best(ev, start)
        return ev

    def _iterate(self, ev: ObjectiveOutput, start: ClothState, until: int, writer=None, bar=None):
        """Fit steps until ``until`` iterations are done, logging, checkpointing and updating ``bar`` after
        each; returns the last (evaluation, start)."""
        t0 = time.perf_counter()
        while self.iteration < until:
            ev, start, rejected = self.step(ev, start)
            self.rejected_steps += rejected
            self.iteration += 1
            if self.iteration in self.config.resew_at:
                ev, start = resew(self, ev, start)
            self._note_best(ev, start)
            scalars = self._scalars(ev)
            scalars["steps/rejected"] = rejected
            self.history.append({"iteration": self.iteration, **scalars})
            every = self.config.image_every
            images = self.iteration == until or (every > 0 and self.iteration % every == 0)
            log_evaluation(writer, ev, scalars, self.iteration, images, self.objective)
            self.seconds += time.perf_counter() - t0
            t0 = time.perf_counter()
            self.save_checkpoint(start)
            if bar is not None:
                update_bar(bar, scalars)
        return ev, start

    def _note_best(self, ev: ObjectiveOutput, start: ClothState) -> None:
        """Remember the parameters and the drape start of ``ev`` when its loss is the lowest so far."""
        loss = float(ev.loss.detach())
        if self.best is None or loss < self.best["loss"]:
            self.best = best_snapshot(self.iteration, loss, self.params, start)

    # -- logs, report, checkpoints -------------------------------------------------------------------------

    def _scalars(self, ev: ObjectiveOutput) -> dict:
        counts = dict(rejected_total=self.rejected_steps, nan_gradients=self.nan_gradients)
        return fit_scalars(ev, self.objective, self.params, **counts)

    def _summary(self, ev: ObjectiveOutput) -> dict:
        return summarize(ev, self.objective, self.target.garment_points, self.params.body)

    def report(self, final: dict) -> dict:
        """The metrics of the fit (`fit_report.fit_report`) from the first evaluation to ``final``."""
        run = dict(iterations=self.iteration, result_iteration=self.result_iteration, seconds=self.seconds)
        run.update({k: getattr(self, k) for k in ("rejected_steps", "rejection_reasons", "nan_gradients")})
        run.update(adjoint_failures=self.adjoint_failures, first_drape_candidates=self.first_candidates)
        run.update(resewings=self.resewings)
        return fit_report(self.first, final, self.objective, run)

    def state_dict(self, start: ClothState) -> dict:
        """Everything a resumed run needs: parameters, optimizer, the drape start, the bookkeeping."""
        return {
            "params": self.params.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            **start_state(start),
            **progress_state(self),
            "config": config_to_dict(self.config),
        }

    def load_state_dict(self, state: dict) -> ClothState:
        """Restore a `state_dict` (an older one too: `fit_checkpoint.upgraded`); returns its drape start."""
        state = upgraded(state)
        self.params.load_state_dict(state["params"])
        self.optimizer.load_state_dict(state["optimizer"])
        load_progress(self, state)
        return start_from(state, self.dtype)

    def save_checkpoint(self, start: ClothState) -> None:
        if self.out_dir is not None:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            race = {} if self.race is None else {"race": self.race}  # while it runs (`fit_race`)
            atomic_save({**self.state_dict(start), **race}, self.out_dir / CHECKPOINT)
