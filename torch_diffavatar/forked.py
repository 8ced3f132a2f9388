"""Calls run in forked worker processes, for work that splits into independent runs (the body fit's
starting directions, `body.fit`, and the first sewings, `fit_start`, through `side_by_side`; the race of
first drapes, `fit_race`): each worker is a copy of the driver
at the fork, its models included, so nothing is rebuilt or sent to it; only its result comes back, through
a pipe, as a ``torch.save`` of plain data read with ``weights_only``.

A fork is safe only while torch's intra-op pool has one thread (an OpenMP pool does not survive a fork: the
worker would hang in its first parallel loop), so `can_fork` says no otherwise and the caller runs its
calls one after another. A worker dies with its driver (Linux: ``PR_SET_PDEATHSIG``), so a killed fit
leaves none running.
"""

from __future__ import annotations

import ctypes
import functools
import io
import multiprocessing as mp
import multiprocessing.connection
import os
import signal
import sys
import traceback

import torch

from torch_diffavatar.errors import InputError, SimulationError

_PR_SET_PDEATHSIG = 1  # linux/prctl.h
_ERRORS = {"SimulationError": SimulationError, "InputError": InputError}


class WorkerLost(RuntimeError):
    """A worker process ended without sending its result (killed, out of memory)."""


def _load_plain(stream: io.BytesIO):
    return torch.load(stream, weights_only=True)


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def can_fork() -> bool:
    """Whether `ForkedCall` may fork here: a ``fork`` start method exists and torch runs one intra-op
    thread."""
    return "fork" in mp.get_all_start_methods() and torch.get_num_threads() == 1


class ForkedCall:
    """``fn(counter)`` run in a forked worker process.

    ``counter``: a `ProgressCounter` that ``fn`` may update as a progress bar; it counts in ``progress`` (a
    shared integer). ``fn``'s return value must be data that ``torch.save`` writes and ``load`` reads back
    from a stream: by default a ``weights_only`` ``torch.load`` (tensors, containers, numbers, strings).
    """

    def __init__(self, fn, load=_load_plain):
        ctx = mp.get_context("fork")
        self._load = load
        self.progress = ctx.Value("i", 0)
        self.connection, send = ctx.Pipe(duplex=False)
        for stream in (sys.stdout, sys.stderr):  # a worker flushes its copy of the buffers when it ends
            stream.flush()
        self._process = ctx.Process(target=_work, args=(fn, send, self.progress), daemon=True)
        self._process.start()
        send.close()

    def result(self):
        """``fn``'s return value, once the worker has sent it (waits for it).

        Raises:
            SimulationError, InputError: ``fn`` raised one (its message).
            RuntimeError: ``fn`` raised another exception (its type, message and the worker's traceback).
            WorkerLost: the worker ended without a result, or while it sent it (a partial message).
        """
        try:
            data = self.connection.recv_bytes()
        except (EOFError, OSError):  # OSError: "got end of file during message", killed while it sent
            self._process.join()
            code = self._process.exitcode
            raise WorkerLost(f"a worker process ended with exit code {code} and no result") from None
        self._process.join()
        payload = self._load(io.BytesIO(data))
        if "error" in payload:
            kind, message = payload["error"]
            raise _ERRORS.get(kind, RuntimeError)(message if kind in _ERRORS else f"{kind}: {message}")
        return payload["value"]

    def close(self) -> None:
        """Stop the worker if it still runs; release the pipe."""
        if self._process.is_alive():
            self._process.kill()
        self._process.join()
        self.connection.close()


class ProgressCounter:
    """A progress bar's stand-in in a worker (``update`` / ``set_postfix``, as `fit_logging.update_bar`
    calls them): it counts the updates in the shared ``value``."""

    def __init__(self, value):
        self.value = value

    def update(self, n: int = 1) -> None:
        with self.value.get_lock():
            self.value.value += n

    def set_postfix(self, **_) -> None:
        pass


class WorkersBar:
    """The driver's progress bar that also counts its workers' updates (their `ProgressCounter`\\ s), as
    they are seen at each of its own updates or `catch_up`."""

    def __init__(self, bar, calls: list[ForkedCall]):
        self.bar, self.calls, self.seen = bar, calls, 0

    def catch_up(self) -> None:
        done = sum(c.progress.value for c in self.calls)
        if done > self.seen:
            self.bar.update(done - self.seen)
            self.seen = done

    def update(self, n: int = 1) -> None:
        self.bar.update(n)
        self.catch_up()

    def set_postfix(self, **kw) -> None:
        self.bar.set_postfix(**kw)


def wait_all(calls: list[ForkedCall], bar: WorkersBar | None, poll_s: float = 0.5) -> None:
    """Wait until every call's worker has sent its result or ended, updating ``bar`` meanwhile."""
    pending = [c.connection for c in calls]
    while pending:
        ready = multiprocessing.connection.wait(pending, timeout=poll_s)
        pending = [c for c in pending if c not in ready]
        if bar is not None:
            bar.catch_up()


def side_by_side(fn, items: list, workers: int) -> list:
    """``fn(item)`` for each of ``items``, in order, up to ``workers`` at a time: the driver computes the
    first of each round while forked copies of it (`ForkedCall`, where `can_fork`) compute the others;
    returns the results in ``items``' order. ``fn`` must be deterministic and return data a worker can send
    (`ForkedCall`), so that any number of workers gives the same results; a worker lost (killed, out of
    memory) has its item computed by the driver. An exception of ``fn`` is raised (`ForkedCall.result`)."""
    results = []
    step = max(workers, 1)
    for first in range(0, len(items), step):
        chunk = items[first : first + step]
        calls = [ForkedCall(functools.partial(_item, fn, item)) for item in chunk[1:]] if can_fork() else []
        try:
            results.append(fn(chunk[0]))
            for k, item in enumerate(chunk[1:]):
                results.append(_result_or_here(calls[k], fn, item) if calls else fn(item))
        finally:
            for call in calls:
                call.close()
    return results


def _item(fn, item, _counter):
    """In a worker: ``fn(item)`` (``_counter``: the worker's progress counter, unused)."""
    return fn(item)


def _result_or_here(call: ForkedCall, fn, item):
    """``call``'s result, or ``fn(item)`` computed here when its worker was lost."""
    try:
        return call.result()
    except WorkerLost:
        return fn(item)


def _work(fn, send, progress) -> None:
    """The worker's body: ``fn(ProgressCounter)``'s value or its error, ``torch.save``\\ d into ``send``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the driver's to handle (it stops the workers)
    try:  # die with the driver: a killed fit leaves no worker behind
        ctypes.CDLL(None).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    except (AttributeError, OSError):
        pass
    try:
        payload = {"value": fn(ProgressCounter(progress))}
    except Exception as exc:  # sent to the driver, which raises it
        message = str(exc) if type(exc).__name__ in _ERRORS else f"{exc}\n{traceback.format_exc()}"
        payload = {"error": (type(exc).__name__, message)}
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    send.send_bytes(buffer.getvalue())
    send.close()
