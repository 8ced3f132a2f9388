"""The race of first drapes, resumable at any point: ``first_race_iterations`` fit iterations from each first
sewing (`fit_start.first_states`), from the same parameters and optimizer, and the fit continues with the
whole state of the one whose lowest loss is the lowest.

While it runs, the race's own state rides in every checkpoint under ``"race"`` (`race_state`): the state
every candidate starts from, each candidate's drape start, which candidate runs (the checkpoint's fit state
is that candidate's), the candidates' entries with the race losses so far, and the best finished
candidate's whole state. A run stopped anywhere in the race resumes to the result of an uninterrupted run,
bit for bit (`opening`).
"""

from __future__ import annotations

import copy
import functools
import math

import torch

from torch_diffavatar.errors import InputError, SimulationError
from torch_diffavatar.fit_checkpoint import CHECKPOINT, safe_load
from torch_diffavatar.fit_start import Start
from torch_diffavatar.forked import ForkedCall, WorkerLost, WorkersBar, can_fork, wait_all
from torch_diffavatar.objective import unbounded_stretch
from torch_diffavatar.sim.state import ClothState

RACE_KEYS = ("laps", "index", "started", "initial", "starts", "candidates", "best")


def race_state(fitter, starts: list[Start], laps: int) -> dict:
    """The race's state at its beginning: ``laps`` iterations from each of ``starts``, every candidate from
    ``fitter``'s present state (``initial``). ``starts``' candidate entries are items of
    ``fitter.first_candidates``; ``"candidate"`` is the position of each."""
    candidates = fitter.first_candidates
    initial = copy.deepcopy(fitter.state_dict(starts[0][1]))
    entries = [
        {
            "x": s.x.detach().clone(),
            "v": s.v.detach().clone(),
            "candidate": next(i for i, c in enumerate(candidates) if c is candidate),
        }
        for _, s, candidate in starts
    ]
    return {
        "laps": laps,
        "index": 0,  # the candidate that runs (or runs next)
        "started": False,  # whether the fitter's state is that candidate's (always so in a checkpoint)
        "initial": initial,
        "starts": entries,
        "candidates": candidates,  # with the race loss of each finished candidate
        "best": None,  # {"loss", "state"} of the finished candidate with the lowest race loss
        "seconds": 0.0,  # the finished candidates' iterations [s], of every run (the report's time)
    }


def check_old_race(checkpoint: dict, config) -> None:
    """Refuse a checkpoint that an older version wrote during the race (no ``"race"`` entry, while some
    sewn candidate has no race loss yet): it holds one candidate's state only, and resuming it would finish
    that candidate alone.

    Raises:
        InputError: ``checkpoint`` is such a one.
    """
    if "race" in checkpoint or config.first_race_iterations <= 0:
        return
    sewn = [c for c in checkpoint.get("first_candidates", []) if "loss" in c]
    if len(sewn) >= 2 and any("race_loss" not in c for c in sewn):
        raise InputError(
            f"{CHECKPOINT} was written during the race of first drapes by an older version, which cannot "
            "resume it exactly; start the fit again (--force instead of --resume)"
        )


def opening(fitter, total: int, resume: bool, workers: int = 1) -> ClothState:
    """Where ``fitter``'s run of ``total`` iterations starts: its checkpoint's state with ``resume`` (and
    the race's, if it stopped during one), else the first states (``workers`` sewings at a time), raced
    when there are several and ``first_race_iterations`` is positive. Sets ``fitter.race`` (None without a
    race); returns the start.

    Raises:
        InputError: the checkpoint cannot be read, or cannot be resumed exactly (`check_old_race`).
    """
    path = None if fitter.out_dir is None else fitter.out_dir / CHECKPOINT
    if resume and path is not None and path.is_file():
        checkpoint = safe_load(path)
        check_old_race(checkpoint, fitter.config)
        race = checkpoint.get("race")
        if race is not None and not (isinstance(race, dict) and set(RACE_KEYS) <= set(race)):
            raise InputError(f"{path}: its race of first drapes is incomplete; start the fit again")
        start = fitter.load_state_dict(checkpoint)
        if race is not None:  # the race's time in the stopped runs, up to their last checkpoint
            race["seconds_before"] = race.get("seconds", 0.0) + fitter.seconds
        fitter.race = race
        return start
    starts = fitter._first_states(workers)
    laps = min(fitter.config.first_race_iterations, total) if len(starts) > 1 else 0
    fitter.race = race_state(fitter, starts, laps) if laps > 0 else None
    if fitter.race is None:  # one start: the fit goes on at its material
        candidate_material(fitter, starts[0][2])
    return starts[0][1]


def candidate_material(fitter, candidate: dict) -> None:
    """Give ``fitter``'s parameters the material of a first sewing made with a scaled one (its entry's
    ``stretch_scale`` and ``fit_bend_scale``, `fit_start.first_states`): the present membrane factor and
    bending stiffness times those scales."""
    params = fitter.params
    scale = candidate.get("stretch_scale", 1.0)
    with torch.no_grad():
        if scale != 1.0:
            factor = float(params.stretch().detach()) * scale
            params.log_stretch.fill_(unbounded_stretch(factor, params.stretch_bound))
        stiffer = candidate.get("fit_bend_scale", 1.0)
        if stiffer != 1.0:
            params.log_bend_stiffness.add_(math.log(stiffer))


def bar_span(fitter, total: int) -> tuple[int, int]:
    """(iterations in all, iterations done) of ``fitter``'s run to ``total``, the race's counted."""
    race = fitter.race
    if race is None:
        return total, min(fitter.iteration, total)
    laps = race["laps"]
    done = race["index"] * laps + (min(fitter.iteration, laps) if race["started"] else 0)
    return total + (len(race["starts"]) - 1) * laps, done


def race(fitter, start: ClothState, bar=None, workers: int = 1) -> ClothState:
    """Run the race ``fitter.race`` (`race_state`, or a checkpoint's) to its end, then take on the whole
    state of the candidate whose lowest loss is the lowest; returns its drape start. ``start``: the drape
    start of the candidate that runs, when the fitter holds its state (a resumed race). Each start's lowest
    loss goes to its candidate entry (``race_loss``; None when its first drape failed).

    ``workers`` > 1 runs up to that many candidates at a time: the driver runs one while forked copies of
    it run the next ones (`forked`; where `forked.can_fork`), with the same results as one after
    another, since each candidate starts from the same state and the fit is deterministic.

    ``fitter``: the `torch_diffavatar.fit.Fitter` that runs the iterations (its ``state_dict`` /
    ``load_state_dict`` snapshot and restore everything a candidate changes).

    Raises:
        SimulationError: the first drape of every candidate failed.
    """
    state = fitter.race
    try:
        while state["index"] < len(state["starts"]):
            calls = _forked_candidates(fitter, state, workers)
            try:
                own_bar = bar if bar is None or not calls else WorkersBar(bar, calls)
                end = _run_candidate(fitter, state, start, own_bar)
                state["index"] += 1
                state["started"] = False
                if calls:
                    _gather(fitter, state, calls, own_bar, end)
            finally:
                for call in calls:
                    call.close()
        if state["best"] is None:
            raise SimulationError("the first drape of every candidate failed (blow-up or non-finite values)")
        start = fitter.load_state_dict(state["best"]["state"])
        fitter.first_candidates = state["candidates"]  # with every race loss, not the winner's copy
    finally:
        fitter.race = None
    fitter.seconds = state.get("seconds_before", 0.0)  # `run` adds its own time, the race's included
    fitter.save_checkpoint(start)
    return start


def _forked_candidates(fitter, state: dict, workers: int) -> list[ForkedCall]:
    """Workers (`forked.ForkedCall`) for the ``workers`` - 1 candidates after the one that runs next,
    where forking is safe (none otherwise)."""
    following = range(state["index"] + 1, min(state["index"] + workers, len(state["starts"])))
    if not following or not can_fork():
        return []
    # a candidate's state holds the fit's own data classes: `safe_load` reads them
    return [
        ForkedCall(functools.partial(_candidate_alone, fitter, state, i), load=safe_load) for i in following
    ]


def _candidate_alone(fitter, state: dict, index: int, bar) -> dict:
    """In a worker: candidate ``index`` of the race ``state`` fitted on ``fitter`` (the worker's copy) as
    `_run_candidate` fits it, no checkpoint written; returns its race loss, its whole state where it
    finished (None when its first drape failed) and its iterations' time."""
    fitter.out_dir = None  # the driver alone writes the fit's files
    own = dict(state, index=index, started=False, best=None, seconds=0.0)
    own["candidates"] = copy.deepcopy(state["candidates"])
    _run_candidate(fitter, own, None, bar)
    candidate = own["candidates"][own["starts"][index]["candidate"]]
    return {"race_loss": candidate["race_loss"], "best": own["best"], "seconds": own["seconds"]}


def _gather(fitter, state: dict, calls: list[ForkedCall], bar, start: ClothState | None) -> None:
    """Record the results of ``calls`` (the workers' candidates, which follow ``state["index"]`` in
    order) as `_run_candidate` records its own, then checkpoint. A worker lost (killed, out of memory)
    leaves its candidate and those after it to run again."""
    wait_all(calls, bar if isinstance(bar, WorkersBar) else None)
    for call in calls:
        try:
            result = call.result()
        except WorkerLost:
            break
        entry = state["starts"][state["index"]]
        state["candidates"][entry["candidate"]]["race_loss"] = result["race_loss"]
        best = result["best"]
        if best is not None and _beats_best(state, best["loss"]):
            state["best"] = best
        state["index"] += 1
    if start is not None:  # the driver's candidate ran: its state is the fitter's
        fitter.seconds = 0.0  # already in state["seconds"]: a resumed run must not count it twice
        fitter.save_checkpoint(start)


def _run_candidate(fitter, state: dict, start: ClothState | None, bar) -> ClothState | None:
    """Fit the candidate ``state["index"]`` of the race ``state`` to ``state["laps"]`` iterations: from
    ``initial`` and its own drape start, or on from ``start`` when the fitter already holds its state; then
    record its race loss and, when the lowest so far, its whole state. Returns its last drape start (None
    when its first drape failed)."""
    entry, laps = state["starts"][state["index"]], state["laps"]
    candidate = state["candidates"][entry["candidate"]]
    if state["started"]:
        ev = None
        if fitter.iteration < laps:
            ev = fitter._checked_evaluate(start)
            if ev is None:  # cannot happen for a deterministic drape: it was accepted before
                raise SimulationError("the resumed candidate's drape failed (blow-up or non-finite values)")
    else:
        fitter.load_state_dict(copy.deepcopy(state["initial"]))
        candidate_material(fitter, candidate)
        start = ClothState(entry["x"].to(fitter.dtype), entry["v"].to(fitter.dtype))
        ev = fitter._checked_evaluate(start)
        if ev is None:
            candidate["race_loss"] = None
            return None
        state["started"] = True
        fitter.first = fitter._summary(ev)
        fitter._note_best(ev, start)
    _, start = fitter._iterate(ev, start, laps, bar=bar)
    loss = fitter.best["loss"]
    candidate["race_loss"] = loss
    state["seconds"] = state.get("seconds", 0.0) + fitter.seconds  # its iterations' time, all runs'
    if _beats_best(state, loss):
        state["best"] = {"loss": loss, "state": copy.deepcopy(fitter.state_dict(start))}
    return start


def _beats_best(state: dict, loss: float) -> bool:
    """Whether a finished candidate's race ``loss`` replaces the race's best: strictly lower, so that of
    equal losses the earlier candidate wins, whichever process fitted it (the workers' results are
    recorded in the race's order)."""
    return state["best"] is None or loss < state["best"]["loss"]
