"""Where a fit starts: the first drape, and the race between several first sewings.

Cloth that hangs loose on a body rests in more than one fold state, and which one a sewing reaches depends
on its path: the template is sewn and draped once per ``FitConfig.first_bend_scales`` (the bending
stiffness scaled), each settled at the fit's own stiffness (`first_states`); the first drape's loss, or a
race of ``first_race_iterations`` fit iterations from each (`fit_race.race`), picks the one the fit
continues. During the fit, the garment can be sewn afresh at the parameters it has reached (`resew`,
``FitConfig.resew_at``).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import replace

import torch

from torch_diffavatar.errors import SimulationError
from torch_diffavatar.fit_config import drape_config, first_drape_config
from torch_diffavatar.forked import side_by_side
from torch_diffavatar.objective import FitObjective, FitVariables, ObjectiveOutput
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.state import ClothState

# (loss, start state, its entry of the candidates) of one first drape
Start = tuple[float, ClothState, dict]


def settled(
    objective: FitObjective,
    state: ClothState,
    rest_uv: torch.Tensor,
    body_verts: torch.Tensor | None,
    material: ClothMaterial,
) -> ClothState:
    """``state`` draped to rest with the fit's own substeps (`settle` on the objective's cloth model, body
    faces and config). ``rest_uv``: (V, 2) [m]; ``body_verts``: (Vb, 3) [m] or None."""
    faces = objective.body_faces
    return settle(objective.cloth_model, state, rest_uv, body_verts, faces, material, objective.config)


def settle(model, state: ClothState, rest_uv, body_verts, body_faces, material, config) -> ClothState:
    """``state`` of the cloth ``model`` draped to rest on the body (``body_verts`` (Vb, 3) [m] and
    ``body_faces``, or None) with a fit's own substeps (``config``'s `drape_config`; at least 10 frames,
    ``first_max_steps`` at most), its velocities zeroed: how a fit settles a first sewing."""
    from torch_diffavatar.sim.forward_drape import drape_to_equilibrium

    res = drape_to_equilibrium(
        model,
        rest_uv,
        body_verts=body_verts,
        body_faces=None if body_verts is None else body_faces,
        material=material,
        state=state,
        config=replace(drape_config(config), min_steps=10, max_steps=config.first_max_steps),
    )
    return ClothState(res.x, torch.zeros_like(res.x))


@torch.no_grad()
def first_states(
    objective: FitObjective,
    variables: FitVariables,
    evaluate: Callable[[ClothState], ObjectiveOutput],
    candidates: list[dict],
    *,
    start_state: ClothState | None = None,
    sewing_fallback=None,
    fit_bend_scales: tuple[float, ...] | None = None,
    workers: int = 1,
) -> list[Start]:
    """The first warm starts, each settled with the fit's own substeps and stiffness (`settled`), as
    (loss, state, its entry of ``candidates``), lowest loss first: ``start_state`` alone, or the template
    sewn and draped once per ``first_bend_scales`` (the bending stiffness scaled by it for the sewing),
    ``first_stretch_scales`` (the membrane scaled by it: the entry's ``stretch_scale``) and
    ``fit_bend_scales`` (default ``first_fit_bend_scales``: the fit's bending stiffness scaled by it, for
    the sewing and the settling: the entry's ``fit_bend_scale``), every combination or, with the config's
    ``first_race_pairs`` and no ``fit_bend_scales`` given, paired entry by entry; the race gives each
    candidate's fit its entry's membrane and stiffness (`fit_race.candidate_material`). With one start the
    loss is NaN (not evaluated). Each sewing's scales and loss (or error) are appended to ``candidates``.

    Args:
        objective: the fit's objective (garment, config, material, body faces, the fixed body).
        variables: the fit variables to sew and drape at (`FitParameters` output).
        evaluate: the fit's evaluation at its variables, from a start state (its loss ranks the starts).
        candidates: where each sewing's entry goes.
        start_state: the first warm start (e.g. a `sew_and_drape` result's state), or None to sew.
        sewing_fallback: `sew_and_drape`'s ``fallback`` (`sim.placement.a_pose_route` for a posed body).
        workers: sewings made at a time, all but one in forked workers (`forked.side_by_side`; the same
            results on any number).

    Raises:
        SimulationError: the sewing or the drape blew up (of every candidate, when there are several).
    """
    body_verts = objective.body_or_fixed(variables.body_verts)
    stretch = None if variables.stretch is None else float(variables.stretch)
    if start_state is not None:
        material = objective.material_at(float(variables.bend_stiffness), stretch)
        dtype = objective.template_uv.dtype
        start = ClothState(start_state.x.to(dtype), start_state.v.to(dtype))
        return [(math.nan, settled(objective, start, variables.rest_uv, body_verts, material), {})]
    config = objective.config
    stretches, bends = config.first_stretch_scales, config.first_bend_scales
    if fit_bend_scales is None and config.first_race_pairs:
        physics = list(zip(stretches, config.first_fit_bend_scales, strict=True))
    else:
        fit_bend_scales = config.first_fit_bend_scales if fit_bend_scales is None else fit_bend_scales
        physics = [(m, k) for k in fit_bend_scales for m in stretches]
    pairs = [(b, m, k) for m, k in physics for b in bends]
    entries = [_candidate_entry(*pair) for pair in pairs]
    candidates.extend(entries)
    sew = functools.partial(_sewn, objective, variables, body_verts, stretch, sewing_fallback)
    if len(pairs) == 1:  # nothing to choose; the fit evaluates it anyway
        state, _ = sew(pairs[0], entries[0], None)
        return [(math.nan, state, entries[0])]
    states = []
    sewings = side_by_side(functools.partial(_sewing, sew, evaluate), list(zip(pairs, entries)), workers)
    for entry, sewing in zip(entries, sewings, strict=True):
        entry.update(sewing["entry"])
        loss = sewing.get("loss", math.nan)
        if "error" not in entry:
            # report.json is strict JSON: a non-finite loss is recorded as an error, not as NaN
            entry.update({"loss": loss} if math.isfinite(loss) else {"error": f"loss {loss}"})
        if math.isfinite(loss):
            states.append((loss, ClothState(sewing["x"], sewing["v"]), entry))
    if not states:
        raise SimulationError(f"every first sewing of the template failed: {candidates}")
    return sorted(states, key=lambda ls: ls[0])


def _candidate_entry(scale: float, membrane: float, stiffer: float) -> dict:
    """A first sewing's entry of the candidates: its scales, those at 1 left out."""
    candidate = {"bend_scale": scale} | ({"stretch_scale": membrane} if membrane != 1.0 else {})
    return candidate | ({"fit_bend_scale": stiffer} if stiffer != 1.0 else {})


def _sewn(objective, variables, body_verts, stretch, sewing_fallback, pair, candidate, evaluate):
    """One first sewing (`first_states`): the template sewn and draped at ``pair`` = (bend scale, membrane
    scale, fit bend scale), settled at the fit's stiffness times the last; notes a sewing finished in the
    A-pose in ``candidate``. Returns (state, its loss by ``evaluate``, NaN when None).

    Raises:
        SimulationError: the sewing or the drape blew up.
    """
    from torch_diffavatar.sim.forward_drape import sew_and_drape

    scale, membrane, stiffer = pair
    bend_stiffness = float(variables.bend_stiffness) * stiffer
    mat = objective.material_at(bend_stiffness, (stretch or 1.0) * membrane)
    res = sew_and_drape(
        objective.garment,
        rest_uv=variables.rest_uv,
        body_verts=body_verts,
        body_faces=None if body_verts is None else objective.body_faces,
        fallback=sewing_fallback,
        material=replace(mat, bend_stiffness=bend_stiffness * scale),
        config=first_drape_config(objective.config),
        dtype=objective.template_uv.dtype,
    )
    if "fallback_after" in res.diagnostics:
        candidate["sewn_in_a_pose"] = True
    state = settled(objective, res.state, variables.rest_uv, body_verts, mat)
    return state, (math.nan if evaluate is None else float(evaluate(state).loss))


def _sewing(sew, evaluate, pair_entry: tuple) -> dict:
    """One first sewing by ``sew`` (`_sewn`) as plain data, as a worker sends it (`forked.side_by_side`): the
    state's ``x`` and ``v``, the ``loss`` and the ``entry`` with its notes; a sewing that blew up, the entry
    with its ``error``."""
    pair, entry = pair_entry
    entry = dict(entry)
    try:
        state, loss = sew(pair, entry, evaluate)
    except SimulationError as exc:
        return {"entry": entry | {"error": str(exc)}}
    return {"x": state.x, "v": state.v, "loss": loss, "entry": entry}


def first_drape(
    objective: FitObjective, variables: FitVariables, *, sewing_fallback=None, start_state=None
) -> ClothState:
    """The start of a fit's first drape at ``variables``: the template sewn onto the body and settled, the
    sewing of the lowest loss with several ``first_bend_scales`` (no race); see `first_states`."""

    def evaluate(state: ClothState) -> ObjectiveOutput:
        return objective(variables, state)

    kw = dict(start_state=start_state, sewing_fallback=sewing_fallback)
    return first_states(objective, variables, evaluate, [], **kw)[0][1]


def resew(fitter, ev: ObjectiveOutput, start: ClothState) -> tuple[ObjectiveOutput, ClothState]:
    """The evaluation and drape start ``fitter`` goes on from after an iteration in ``resew_at``: the
    garment sewn and draped afresh at the present parameters (`first_states`, once per
    ``first_bend_scales``), the lowest-loss of those drapes when its loss is below ``ev``'s, else ``ev``
    and ``start`` as they are. A drape carried along from the template's keeps the folds and the friction
    hold that the template's shape gave it; the scan's garment was put on as it is. Appends the losses
    to ``fitter.resewings`` (the report's).

    Args:
        fitter: the `fit.Fitter` (its ``params``, ``objective``, ``evaluate``, ``sewing_fallback``).
        ev, start: the iteration's accepted evaluation and its drape start.
    """
    with torch.no_grad():
        variables = fitter.params()
    entries: list[dict] = []
    record = {"iteration": fitter.iteration, "warm_loss": float(ev.loss.detach()), "fresh": entries}
    try:
        # at the fit's own stiffness: the fit goes on with it, whichever drape it takes
        starts = first_states(
            fitter.objective,
            variables,
            fitter.evaluate,
            entries,
            sewing_fallback=fitter.sewing_fallback,
            fit_bend_scales=(1.0,),
        )
    except SimulationError:  # every sewing failed: the warm drape goes on
        starts = []
    fresh = None  # one sewing, which `first_states` does not evaluate: its evaluation, kept if it is taken
    if len(starts) == 1 and math.isnan(starts[0][0]):
        fresh = fitter._checked_evaluate(starts[0][1])  # None when the drape is rejected (counted)
        loss = math.nan if fresh is None else float(fresh.loss.detach())
        starts[0][2].update({"loss": loss} if fresh is not None else {"error": "drape rejected"})
        starts = [(loss, starts[0][1], starts[0][2])] if fresh is not None else []
    new = None
    if starts and starts[0][0] < record["warm_loss"]:
        new = fresh if fresh is not None else fitter._checked_evaluate(starts[0][1])
    record["taken"] = new is not None
    fitter.resewings.append(record)
    return (new, starts[0][1]) if new is not None else (ev, start)
