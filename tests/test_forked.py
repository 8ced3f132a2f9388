"""Forked workers (`forked`): a worker's value, error or death reaches the driver; its progress counts
on the driver's bar; no worker outlives its driver."""

from __future__ import annotations

import multiprocessing
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from torch_diffavatar.errors import SimulationError
from torch_diffavatar.forked import ForkedCall, WorkerLost, WorkersBar, can_fork, usable_cores, wait_all

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif("fork" not in multiprocessing.get_all_start_methods(), reason="no fork")


@pytest.fixture(autouse=True)
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _count(bar):
    for _ in range(3):
        bar.update(1)
        bar.set_postfix(loss="1")
    return {"sum": torch.arange(4.0).sum(), "names": ["a", "b"], "none": None}


def test_a_worker_returns_its_value_and_counts_its_progress():
    call = ForkedCall(_count)
    try:
        value = call.result()
    finally:
        call.close()
    assert value["sum"].item() == 6.0 and value["names"] == ["a", "b"] and value["none"] is None
    assert call.progress.value == 3


class _Bar:
    def __init__(self):
        self.n, self.postfix = 0, None

    def update(self, n=1):
        self.n += n

    def set_postfix(self, **kw):
        self.postfix = kw


def test_the_drivers_bar_counts_the_workers_iterations():
    bar = _Bar()
    calls = [ForkedCall(_count), ForkedCall(_count)]
    try:
        wrapped = WorkersBar(bar, calls)
        wrapped.update(1)
        wrapped.set_postfix(loss="2")
        wait_all(calls, wrapped, poll_s=0.01)
        assert bar.n == 1 + 3 + 3 and bar.postfix == {"loss": "2"}
    finally:
        for c in calls:
            c.close()


def _fails(bar):
    raise SimulationError("the drape blew up")


def _breaks(bar):
    return {}["missing"]


def test_a_workers_error_is_raised_in_the_driver():
    call = ForkedCall(_fails)
    with pytest.raises(SimulationError, match="^the drape blew up$"):
        call.result()
    call.close()
    call = ForkedCall(_breaks)
    with pytest.raises(RuntimeError, match="KeyError: 'missing'"):
        call.result()
    call.close()


def _dies(bar):
    os.kill(os.getpid(), signal.SIGKILL)


def test_a_worker_that_dies_is_reported_lost():
    call = ForkedCall(_dies)
    with pytest.raises(WorkerLost, match="exit code -9"):
        call.result()
    call.close()


def test_a_worker_killed_while_it_sends_is_lost(monkeypatch):
    """A worker killed in the middle of sending its result leaves a partial message: the pipe raises
    OSError ("got end of file during message"), not EOFError, and the body fit's lost-worker test met it
    once in CI. It is a lost worker too."""
    call = ForkedCall(_count)
    try:
        call._process.join()

        def partial():
            raise OSError("got end of file during message")

        monkeypatch.setattr(call.connection, "recv_bytes", partial)
        with pytest.raises(WorkerLost, match="exit code 0 and no result"):
            call.result()
    finally:
        call.close()


def test_forking_needs_one_thread():
    assert can_fork()
    torch.set_num_threads(2)
    assert not can_fork()
    assert usable_cores() >= 1


ORPHAN = """
import sys, time
from torch_diffavatar.forked import ForkedCall

def sleep(bar):
    time.sleep(60)

call = ForkedCall(sleep)
print(call._process.pid, flush=True)
time.sleep(60)
"""


def test_no_worker_outlives_a_killed_driver():
    """A driver killed by SIGKILL (no clean-up of its own) takes its worker with it (Linux)."""
    if not sys.platform.startswith("linux"):
        pytest.skip("PR_SET_PDEATHSIG is Linux's")
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    driver = subprocess.Popen([sys.executable, "-c", ORPHAN], env=env, stdout=subprocess.PIPE, text=True)
    worker = int(driver.stdout.readline())
    driver.kill()
    driver.wait()
    for _ in range(100):
        try:
            os.kill(worker, 0)
        except ProcessLookupError:
            break
        if Path(f"/proc/{worker}/stat").read_text().split()[2] == "Z":  # a zombie: ended, not yet reaped
            break
        time.sleep(0.05)
    else:
        os.kill(worker, signal.SIGKILL)
        pytest.fail("the worker outlived its driver")


def _interrupted(bar):
    os.kill(os.getpid(), signal.SIGINT)  # as Ctrl-C in a terminal reaches every process of the fit
    time.sleep(0.1)
    return 7


def test_ctrl_c_is_left_to_the_driver():
    """A worker ignores SIGINT (no second traceback on the terminal; the driver stops its workers)."""
    call = ForkedCall(_interrupted)
    try:
        assert call.result() == 7
    finally:
        call.close()
