"""scripts/bench_demo_setup.py (issue #32): each phase it times names a function that exists (a renamed one
would leave its row at 0 s unnoticed), and its table's rows add up to the total."""

from __future__ import annotations

import importlib

import pytest
from helpers_scripts import load_script


@pytest.fixture(scope="module")
def bench():
    return load_script("bench_demo_setup")


def test_every_phase_names_a_function(bench):
    for label, module, attr, *member in bench.PHASES:
        owner = getattr(importlib.import_module(module), attr)
        assert callable(getattr(owner, member[0]) if member else owner), label


def test_the_table_adds_up(bench):
    timers = bench.Timers()
    timed = timers.wrap("scan intake", lambda x: 2 * x)
    assert timed(3) == 6 and timed(4) == 8
    assert set(timers.totals) == {"scan intake"} and timers.totals["scan intake"][0] >= 0.0
    timers.totals = {"scan intake": [2.0, 1.0], "prepare (set-up)": [6.0, 5.0], " body fit": [5.0, 4.0]}
    rows = {r["phase"]: (r["wall_s"], r["cpu_s"]) for r in bench.table(timers, (10.0, 8.0), (1.0, 0.5))}
    # sub-phases (indented) lie inside their phase: "other" leaves them out
    assert rows["other"] == (1.0, 1.5)
    assert rows[" body fit"] == (5.0, 4.0) and rows["Anny load"] == (0.0, 0.0)
    assert rows["total (process)"] == (10.0, 8.0)
