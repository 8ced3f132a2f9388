"""`diffavatar fit-batch MANIFEST --out DIR [--workers N] [--address ADDR]`: many scans, one fit each, on Ray.

Each manifest row (`torch_diffavatar.batch.read_manifest`) is one Ray task that runs `diffavatar fit`'s own
code (`commands.fit.fit_command`) into ``DIR/NAME`` with one thread. Ray starts in this process with
``--workers`` CPUs (default: one per core), or ``--address`` joins a running cluster (``ray start --head``).

A rerun picks up where a batch stopped: a scan whose folder holds a finished fit is skipped, a half-done one
resumes from its checkpoint (``fit --resume``), a failed one is tried again. A failing scan is an ``error``
row of ``DIR/summary.csv`` / ``summary.json``, and the others go on; ``DIR/summary.png`` shows them all.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
from pathlib import Path

from torch_diffavatar.batch import (
    BatchJob,
    batch_settings,
    changed_settings,
    fit_state,
    read_manifest,
    record_settings,
    result_row,
    summary_picture,
    write_summary,
)
from torch_diffavatar.commands.out_paths import check_out_folder
from torch_diffavatar.errors import InputError

LOCKS = ".locks"  # under --out: one lock file per scan (`scan_lock`)
INSTALL_RAY = 'fit-batch runs on Ray, which is not installed: pip install "torch_diffavatar[ray]"'


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "fit-batch",
        help="fit every scan of a manifest (CSV or JSON lines) on Ray; resumable; gathers a summary",
        description="Fit each scan of MANIFEST (CSV with a header, or JSON lines: scan, garment, optional "
        "config, units, up, body; paths relative to the manifest) as `diffavatar fit` does, one asset "
        "folder per scan under --out, in parallel on Ray. A rerun skips finished scans and resumes "
        "half-done ones. Writes summary.csv, summary.json and summary.png into --out.",
    )
    p.add_argument("manifest", help="CSV (with a header) or .jsonl file listing the scans")
    p.add_argument("--out", required=True, help="output folder (one sub-folder per scan)")
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        help="fits at once (default: one per core locally; on a cluster, as many as it schedules)",
    )
    p.add_argument(
        "--address",
        default=None,
        help="a running Ray cluster (e.g. 'auto' or HOST:6379) instead of a local one",
    )
    p.add_argument("--iters", type=int, default=None, help="iterations of every fit (overrides the configs)")
    p.add_argument("--spacing", type=float, default=None, help="mesh spacing [m] of every fit")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print the batch's counts as one JSON line")
    p.set_defaults(func=fit_batch_command)


def import_ray():
    """The `ray` module; InputError saying how to install it when it is not there."""
    try:
        import ray
    except ImportError as exc:
        raise InputError(INSTALL_RAY) from exc
    return ray


def _one_line(text: str) -> str:
    return " ".join(part.strip() for part in str(text).splitlines() if part.strip())


def fit_one(job: dict, out: str, iters: int | None, spacing: float | None) -> dict:
    """Fit one manifest row (a `BatchJob` as a dict) into ``out/NAME`` as `diffavatar fit` does (resuming a
    half-done fit there; a finished one is skipped); the Ray task. Returns its summary row
    (`batch.result_row`): a failure is an ``error`` row, never an exception."""
    job = BatchJob(**job)
    with scan_lock(Path(out), job.name):
        folder = Path(out) / job.name
        state = fit_state(folder)
        if state == "done":  # finished by a task of a killed batch while this one waited
            return finished_row(job, folder, iters, spacing)
        row = _fit_in_folder(job, folder, state == "partial", iters, spacing)
        if row["status"] == "ok":
            record_settings(folder, batch_settings(job, iters, spacing))
        return row


def finished_row(job: BatchJob, folder: Path, iters, spacing) -> dict:
    """The row of a scan whose ``folder`` holds a finished fit: ``skipped`` when a batch fitted it with the
    same row, files and ``--iters`` / ``--spacing`` (`batch.changed_settings`), else an error naming what
    changed (never a silent result of other settings)."""
    changed = changed_settings(folder, batch_settings(job, iters, spacing))
    if changed:
        message = (
            f"{folder} holds a fit made with other settings ({', '.join(changed)}); remove that folder "
            "(or choose another --out) to fit it again"
        )
        return result_row(job, "skipped", 0.0, None, message)
    report = _read_report(folder)
    return result_row(job, "skipped", report.get("total_seconds", 0.0), report, None)


@contextlib.contextmanager
def scan_lock(out: Path, name: str):
    """Hold ``out/.locks/NAME.lock`` (an exclusive `fcntl.flock`, waiting for it) while the block runs: a
    task of a killed batch lives on for a moment after its driver and must not write the folder a rerun
    resumes; the lock goes with the process that holds it, however it ends."""
    import fcntl

    locks = out / LOCKS
    locks.mkdir(parents=True, exist_ok=True)
    with open(locks / f"{name}.lock", "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _fit_in_folder(job: BatchJob, folder: Path, resume: bool, iters, spacing) -> dict:
    """`fit_command` of ``job`` into ``folder`` with one thread; its summary row (see `fit_one`)."""
    import torch

    from torch_diffavatar.commands.fit import fit_command

    torch.set_num_threads(1)  # one core per task: Ray gives each task one CPU
    args = argparse.Namespace(
        scan=job.scan,
        garment=job.garment,
        garment_type=None,
        config=job.config,
        out=str(folder),
        body=job.body,
        iters=iters,
        spacing=spacing,
        no_colour=False,
        resume=resume,
        workers=1,  # the task's one core: no fits inside it side by side
        force=False,
        units=job.units,
        up=job.up,
        no_progress=True,
        json=True,  # nothing on stdout
    )
    t0 = time.perf_counter()
    run = "resumed" if resume else "fitted"
    try:
        report = fit_command(args)
    except Exception as exc:  # any scan's failure is its row's, and the batch goes on
        message = _one_line(exc) or type(exc).__name__
        if not isinstance(exc, (InputError, OSError)):
            message = f"{type(exc).__name__}: {message}"
        return result_row(job, run, time.perf_counter() - t0, None, message)
    return result_row(job, run, time.perf_counter() - t0, report, None)


def _start_ray(ray, workers: int | None, address: str | None) -> None:
    """Join the cluster at ``address``, or start a local Ray with ``workers`` CPUs (None: all cores)."""
    import logging

    quiet = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
    if address is not None:
        quiet.pop("include_dashboard")
        ray.init(address=address, **quiet)
    else:
        ray.init(address="local", num_cpus=workers or os.cpu_count() or 1, **quiet)  # never a running cluster


def run_jobs(ray, todo: list[BatchJob], out: Path, args, on_row) -> None:
    """Run ``todo`` (`fit_one` of each job) as Ray tasks, at most ``args.workers`` at once (None: as many as
    Ray schedules); ``on_row(row)`` for each finished one, in the order they finish."""
    task = ray.remote(num_cpus=1, max_retries=0)(fit_one)
    cap = args.workers or len(todo)
    queue, pending = list(todo), {}
    while queue or pending:
        while queue and len(pending) < cap:
            job = queue.pop(0)
            pending[task.remote(job.to_dict(), str(out), args.iters, args.spacing)] = job
        done, _ = ray.wait(list(pending), num_returns=1)
        for ref in done:
            job = pending.pop(ref)
            try:
                row = ray.get(ref)
            except Exception as exc:  # the worker died (killed, out of memory): that scan's error
                row = result_row(job, "fitted", 0.0, None, _one_line(exc)[:500])
            on_row(row)


def fit_batch_command(args) -> int:
    ray = import_ray()
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers must be >= 1, got {args.workers}")
    if args.iters is not None and args.iters < 0:
        raise InputError(f"--iters must be >= 0, got {args.iters}")
    jobs = read_manifest(args.manifest)
    out = Path(args.out)
    check_out_folder(out)
    out.mkdir(parents=True, exist_ok=True)
    rows, todo = {}, []
    for job in jobs:
        if fit_state(out / job.name) == "done":
            rows[job.name] = finished_row(job, out / job.name, args.iters, args.spacing)
        else:
            todo.append(job)
    rows = _run_and_gather(ray, jobs, todo, rows, out, args)
    summary_picture(out, rows)
    failed = sum(r["status"] == "error" for r in rows)
    counts = {"scans": len(rows), "ok": len(rows) - failed, "error": failed, "out": str(out)}
    counts["skipped"] = sum(r["run"] == "skipped" for r in rows)
    if args.json:
        from torch_diffavatar.json_io import dumps_json

        print(dumps_json(counts, sort_keys=False))
    else:
        print(
            f"{counts['ok']} ok, {failed} error ({counts['skipped']} skipped as done); {out / 'summary.csv'}"
        )
    return 1 if failed else 0


def _read_report(folder: Path) -> dict:
    import json

    return json.loads((folder / "report.json").read_text())


def _run_and_gather(ray, jobs, todo, rows: dict, out: Path, args) -> list[dict]:
    """Run ``todo`` on Ray (`run_jobs`) under a progress bar over all scans, writing the summary after each
    one (a killed batch keeps what finished); returns the rows in the manifest's order."""
    from tqdm import tqdm

    def ordered() -> list[dict]:
        return [rows[j.name] for j in jobs if j.name in rows]

    initial = len(jobs) - len(todo)
    bar = tqdm(total=len(jobs), initial=initial, unit="scan", file=sys.stderr, disable=args.no_progress)

    def on_row(row: dict) -> None:
        rows[row["name"]] = row
        write_summary(out, ordered())
        bar.set_postfix_str(f"{row['name']}: {row['status']}")
        bar.update(1)

    if todo:
        _start_ray(ray, args.workers, args.address)
        try:
            run_jobs(ray, todo, out, args, on_row)
        finally:
            ray.shutdown()
    bar.close()
    write_summary(out, ordered())
    return ordered()
