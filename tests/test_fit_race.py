"""The race of first drapes, stopped anywhere, resumes to the result of an uninterrupted run, bit for bit; a
checkpoint an older version wrote during a race is refused."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from helpers_fit import DT
from helpers_fit import fit_config as _config

from torch_diffavatar.errors import InputError
from torch_diffavatar.fit import Fitter
from torch_diffavatar.fit_checkpoint import CHECKPOINT, atomic_save, safe_load

ROOT = Path(__file__).resolve().parents[1]

# two candidates of two race iterations each, then one more: checkpoints after candidate 0's iterations 1
# and 2 (saves 1, 2), candidate 1's (3, 4), the race's end (5) and the fit's last iteration (6)
RACE = dict(
    iterations=3,
    first_max_steps=80,
    max_loss_rise=float("inf"),
    first_bend_scales=[1, 30],
    first_race_iterations=2,
)


class Killed(Exception):
    """Stands for a kill right after a checkpoint was written (any kill before the next one is the same)."""


def _fitter(problem, out, settings: dict = RACE) -> Fitter:
    garment, _, target = problem
    config = _config(**settings)
    return Fitter(garment, target, config, progress=False, dtype=DT, out_dir=out, tensorboard=False)


def _killed_after(fitter: Fitter, saves: int) -> Fitter:
    """``fitter``, whose run stops (`Killed`) right after its ``saves``-th checkpoint."""
    original, done = fitter.save_checkpoint, []

    def save(start):
        original(start)
        done.append(start)
        if len(done) == saves:
            raise Killed

    fitter.save_checkpoint = save
    return fitter


def _timeless(history: list[dict]) -> list[dict]:
    """``history`` without its clock readings (``drape/forward_seconds`` …)."""
    return [{k: v for k, v in row.items() if not k.endswith("_seconds")} for row in history]


@pytest.fixture(scope="module")
def straight(skirt_problem, tmp_path_factory):
    fitter = _fitter(skirt_problem, tmp_path_factory.mktemp("straight"))
    return fitter, fitter.run()


def test_the_race_is_a_race(straight):
    """Both candidates ran, and the one raced first (the lower first loss) won, so a resume during the
    second must bring the first's whole state back from the checkpoint."""
    _, result = straight
    ones, thirties = result.report["first_drape_candidates"]  # in the sewing's order
    assert math.isfinite(ones["race_loss"]) and math.isfinite(thirties["race_loss"])
    assert thirties["loss"] < ones["loss"] and thirties["race_loss"] < ones["race_loss"]
    assert result.report["iterations"] == 3 and len(result.history) == 3


# (saves before each kill, the race's candidate running at the last kill or None after the race)
KILLS = [((1,), 0), ((2,), 0), ((3,), 1), ((4,), 1), ((5,), None), ((1, 2), 1)]


@pytest.mark.parametrize("kills, running", KILLS, ids=lambda k: str(k))
def test_a_race_stopped_anywhere_resumes_to_the_uninterrupted_result(
    skirt_problem, straight, tmp_path, kills, running
):
    straight_fitter, expected = straight
    for i, saves in enumerate(kills):
        with pytest.raises(Killed):
            _killed_after(_fitter(skirt_problem, tmp_path), saves).run(resume=i > 0)
    race = safe_load(tmp_path / CHECKPOINT).get("race")
    assert (None if race is None else race["index"]) == running
    fitter = _fitter(skirt_problem, tmp_path)
    result = fitter.run(resume=True)
    assert torch.equal(result.rest_uv, expected.rest_uv) and torch.equal(result.x, expected.x)
    for name, value in fitter.params.state_dict().items():
        assert torch.equal(value, straight_fitter.params.state_dict()[name]), name
    assert _timeless(result.history) == _timeless(expected.history)
    report, want = dict(result.report), dict(expected.report)
    # the clock differs, nothing else; the stopped runs' race time is counted
    assert report.pop("seconds") >= (0.0 if race is None else race["seconds"]) and want.pop("seconds") > 0
    assert report == want
    assert "race" not in safe_load(tmp_path / CHECKPOINT) and fitter.race is None


MEMBRANES = dict(RACE, first_bend_scales=[1], first_stretch_scales=[1, 0.2], lr_log_stretch=0.05)


def test_a_race_of_membranes_gives_each_candidate_its_own_and_resumes_exactly(skirt_problem, tmp_path):
    """``first_stretch_scales``: the second sewing is made with a 5× softer membrane and its race fits from
    that membrane; stopped inside that candidate, the run resumes to the uninterrupted result."""

    def fitter(out):
        return _fitter(skirt_problem, out, MEMBRANES)

    straight_fitter = fitter(tmp_path / "a")
    expected = straight_fitter.run()
    plain, soft = expected.report["first_drape_candidates"]
    assert "stretch_scale" not in plain and soft["stretch_scale"] == 0.2
    assert math.isfinite(plain["race_loss"]) and math.isfinite(soft["race_loss"])
    with pytest.raises(Killed):
        _killed_after(fitter(tmp_path / "b"), 3).run()
    race = safe_load(tmp_path / "b" / CHECKPOINT)["race"]
    assert race["index"] == 1 and race["started"]
    assert float(safe_load(tmp_path / "b" / CHECKPOINT)["params"]["log_stretch"]) < -1.0  # ~log 0.2
    resumed_fitter = fitter(tmp_path / "b")
    result = resumed_fitter.run(resume=True)
    assert torch.equal(result.x, expected.x) and torch.equal(result.rest_uv, expected.rest_uv)
    for name, value in resumed_fitter.params.state_dict().items():
        assert torch.equal(value, straight_fitter.params.state_dict()[name]), name
    with pytest.raises(ValueError, match="need a race"):
        _config(**dict(MEMBRANES, first_race_iterations=0))


STIFFNESSES = dict(RACE, first_bend_scales=[1], first_fit_bend_scales=[1, 4])


def test_a_race_of_bending_stiffnesses_fits_each_from_its_own_and_resumes_exactly(skirt_problem, tmp_path):
    """``first_fit_bend_scales``: the second sewing is made and settled at 4× the fit's bending stiffness
    and its race fits from that stiffness; stopped inside that candidate, the run resumes to the
    uninterrupted result. A fresh sewing during the fit (``resew_at``) keeps the fit's own stiffness."""
    start_log = math.log(_config().initial_bend_stiffness)

    def fitter(out, **kw):
        return _fitter(skirt_problem, out, dict(STIFFNESSES, **kw))

    straight_fitter = fitter(tmp_path / "a")
    expected = straight_fitter.run()
    plain, stiff = expected.report["first_drape_candidates"]
    assert "fit_bend_scale" not in plain and stiff["fit_bend_scale"] == 4
    assert math.isfinite(plain["race_loss"]) and math.isfinite(stiff["race_loss"])
    scales = []
    for saves, index in ((1, 0), (3, 1)):  # each candidate's first iteration
        with pytest.raises(Killed):
            _killed_after(fitter(tmp_path / "b"), saves).run()
        checkpoint = safe_load(tmp_path / "b" / CHECKPOINT)
        race = checkpoint["race"]
        assert race["index"] == index and race["started"]
        scale = race["candidates"][race["starts"][index]["candidate"]].get("fit_bend_scale", 1.0)
        own = start_log + math.log(scale)
        # the candidate's own stiffness, moved by its one iteration
        assert abs(float(checkpoint["params"]["log_bend_stiffness"]) - own) < 0.3, (scale, own)
        scales.append(scale)
    assert sorted(scales) == [1.0, 4.0]
    resumed_fitter = fitter(tmp_path / "b")
    result = resumed_fitter.run(resume=True)
    assert torch.equal(result.x, expected.x) and torch.equal(result.rest_uv, expected.rest_uv)
    for name, value in resumed_fitter.params.state_dict().items():
        assert torch.equal(value, straight_fitter.params.state_dict()[name]), name
    resewn = fitter(tmp_path / "c", resew_at=[1], first_race_iterations=1, iterations=1).run()
    assert [set(e) & {"fit_bend_scale"} for e in resewn.report["resewings"][0]["fresh"]] == [set()]
    with pytest.raises(ValueError, match="need a race"):
        _config(**dict(STIFFNESSES, first_race_iterations=0))
    with pytest.raises(ValueError, match="outside"):
        _config(**dict(STIFFNESSES, first_fit_bend_scales=[1, 1e5]))


PAIRS = dict(
    RACE,
    first_bend_scales=[1],
    first_stretch_scales=[1, 0.2],
    first_fit_bend_scales=[4, 1],
    first_race_pairs=True,
)


def test_a_race_of_pairs_sews_one_candidate_per_pair(skirt_problem, tmp_path):
    """``first_race_pairs``: the membranes and bending stiffnesses paired entry by entry, two candidates (the
    nominal membrane at 4× k_b, the soft one at 1×) where every combination makes four; the one kept starts
    the fit from its own pair. Lists of different lengths are refused."""
    result = _fitter(skirt_problem, tmp_path, PAIRS).run()
    candidates = result.report["first_drape_candidates"]
    pairs = [(c.get("stretch_scale", 1.0), c.get("fit_bend_scale", 1.0)) for c in candidates]
    assert pairs == [(1.0, 4.0), (0.2, 1.0)]
    assert all(math.isfinite(c["race_loss"]) for c in candidates)
    kept = min(candidates, key=lambda c: c["race_loss"])
    material = result.report["material"]
    assert material["stretch_scale_initial"] == pytest.approx(kept.get("stretch_scale", 1.0), rel=1e-6)
    start = _config().initial_bend_stiffness * kept.get("fit_bend_scale", 1.0)
    assert material["bend_stiffness_initial"] == pytest.approx(start, rel=1e-6)
    with pytest.raises(ValueError, match="same length"):
        _config(**dict(PAIRS, first_fit_bend_scales=[4, 1, 2]))


def test_an_older_checkpoint_from_inside_the_race_is_refused(skirt_problem, tmp_path):
    """Without its race's state a checkpoint written during the race holds one candidate only: resuming it
    would finish that candidate alone, so it is refused. One written after the race (saves 5, above) has no
    race state either and resumes as it always did."""
    with pytest.raises(Killed):
        _killed_after(_fitter(skirt_problem, tmp_path), 3).run()
    checkpoint = safe_load(tmp_path / CHECKPOINT)
    race = checkpoint.pop("race")
    atomic_save(checkpoint, tmp_path / CHECKPOINT)
    with pytest.raises(InputError, match="during the race of first drapes by an older version") as info:
        _fitter(skirt_problem, tmp_path).run(resume=True)
    assert "\n" not in str(info.value)
    del race["best"]  # a damaged one is refused too, not half-resumed
    atomic_save({**checkpoint, "race": race}, tmp_path / CHECKPOINT)
    with pytest.raises(InputError, match="race of first drapes is incomplete"):
        _fitter(skirt_problem, tmp_path).run(resume=True)


KILLER = """
import os, signal, sys
from pathlib import Path
import torch
from helpers_fit import DT, skirt_problem
from test_fit_race import _fitter

torch.set_num_threads(1)
fitter = _fitter(skirt_problem(), Path(sys.argv[1]))
original, saves = fitter.save_checkpoint, []


def save(start):
    original(start)
    saves.append(start)
    if len(saves) == int(sys.argv[2]):
        os.kill(os.getpid(), signal.SIGKILL)


fitter.save_checkpoint = save
fitter.run()
"""


def test_a_race_killed_for_real_resumes_to_the_uninterrupted_result(skirt_problem, straight, tmp_path):
    """A process killed by SIGKILL during the second candidate (no ``finally``, no clean-up) resumes too."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(ROOT / "tests")]), OMP_NUM_THREADS="1")
    run = subprocess.run([sys.executable, "-c", KILLER, str(tmp_path), "3"], env=env, capture_output=True)
    assert run.returncode == -signal.SIGKILL, run.stderr.decode()[-2000:]
    assert safe_load(tmp_path / CHECKPOINT)["race"]["index"] == 1
    assert not list(tmp_path.glob("*.tmp*"))
    result = _fitter(skirt_problem, tmp_path).run(resume=True)
    _, expected = straight
    assert torch.equal(result.rest_uv, expected.rest_uv) and torch.equal(result.x, expected.x)
    assert _timeless(result.history) == _timeless(expected.history)


@pytest.fixture
def one_thread():
    """torch on one intra-op thread, as `diffavatar fit` runs it: a fork is refused with more
    (`forked.can_fork`)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_the_race_on_two_workers_gives_the_uninterrupted_result(
    skirt_problem, straight, tmp_path, one_thread
):
    """``race_workers=2``: the second candidate runs in a forked worker while the driver runs the first
    (its progress bar on, the workers' iterations counted on it); the fit ends exactly where one after
    another ends."""
    straight_fitter, expected = straight
    fitter = _fitter(skirt_problem, tmp_path)
    fitter.progress = True
    result = fitter.run(race_workers=2)
    assert torch.equal(result.rest_uv, expected.rest_uv) and torch.equal(result.x, expected.x)
    for name, value in fitter.params.state_dict().items():
        assert torch.equal(value, straight_fitter.params.state_dict()[name]), name
    assert _timeless(result.history) == _timeless(expected.history)
    report, want = dict(result.report), dict(expected.report)
    report.pop("seconds"), want.pop("seconds")
    assert report == want
    assert "race" not in safe_load(tmp_path / CHECKPOINT)


def test_a_lost_race_worker_leaves_its_candidate_to_the_driver(
    skirt_problem, straight, tmp_path, monkeypatch, one_thread
):
    """A worker that ends without its result (killed, out of memory): the driver fits that candidate
    itself, and the fit still ends where one after another ends."""
    from torch_diffavatar import fit_race
    from torch_diffavatar.forked import ForkedCall, WorkerLost

    lost = []

    class LostCall(ForkedCall):
        def result(self):
            self._process.kill()
            lost.append(self)
            raise WorkerLost("killed")

    monkeypatch.setattr(fit_race, "ForkedCall", LostCall)
    _, expected = straight
    result = _fitter(skirt_problem, tmp_path).run(race_workers=2)
    assert len(lost) == 1  # the second candidate's worker; the driver then fitted it alone (no later one)
    assert torch.equal(result.rest_uv, expected.rest_uv) and torch.equal(result.x, expected.x)


def test_a_race_on_workers_stopped_after_its_round_resumes_to_the_uninterrupted_result(
    skirt_problem, straight, tmp_path, one_thread
):
    """With two workers the round's checkpoint (the third save: after the driver's two iterations) holds
    both candidates' results; a run stopped there resumes to the same fit."""
    with pytest.raises(Killed):
        _killed_after(_fitter(skirt_problem, tmp_path), 3).run(race_workers=2)
    race = safe_load(tmp_path / CHECKPOINT)["race"]
    assert race["index"] == 2 and not race["started"]
    assert all(math.isfinite(c["race_loss"]) for c in race["candidates"])
    result = _fitter(skirt_problem, tmp_path).run(resume=True, race_workers=2)
    _, expected = straight
    assert torch.equal(result.rest_uv, expected.rest_uv) and torch.equal(result.x, expected.x)
    assert _timeless(result.history) == _timeless(expected.history)


SEWINGS = dict(iterations=0, first_max_steps=80, first_bend_scales=[1, 30, 3000, 10])


@pytest.mark.parametrize("lose", [False, True], ids=["forked", "workers lost"])
def test_first_sewings_on_two_workers_are_those_made_one_after_another(
    skirt_problem, monkeypatch, one_thread, lose
):
    """``workers=2``: every other first sewing is made (and evaluated) in a forked worker while the driver
    makes the one before it: the same states, losses, order and recorded failure (scale 3000: the seams do
    not close) as one after another. A worker lost (killed) leaves its sewing to the driver."""
    from helpers_forked import counted_forks

    expected = _fitter(skirt_problem, None, SEWINGS)
    want = expected._first_states()
    forks, lost = counted_forks(monkeypatch, lose)
    fitter = _fitter(skirt_problem, None, SEWINGS)
    got = fitter._first_states(workers=2)
    assert len(forks) == 2 and len(lost) == (2 if lose else 0)  # the sewings at 30 and 10
    assert fitter.first_candidates == expected.first_candidates
    assert "seams did not close" in fitter.first_candidates[2]["error"]
    assert [(loss, entry) for loss, _, entry in got] == [(loss, entry) for loss, _, entry in want]
    for (_, state, _), (_, other, _) in zip(got, want):
        assert torch.equal(state.x, other.x) and torch.equal(state.v, other.v)
