#!/usr/bin/env python
"""Batch fitting on Ray (issue #34): ``fit-batch --workers N`` against the same fits one after another.

Makes ``--scans`` small synthetic skirt scans (``make-scan``, kept in ``--work`` for later runs), then times,
in wall seconds, (1) a shell-style loop of ``diffavatar fit`` over them, one process per scan (what a user
without fit-batch runs), (2) ``fit-batch --workers 1`` and (3) ``fit-batch --workers N``, each into a fresh
folder, and checks that every scan's Chamfer is the same in all three. The load average (1 min) is printed
beside each figure: on a shared machine other jobs' load shows there.

    PYTHONPATH=. OMP_NUM_THREADS=1 python scripts/bench_fit_batch.py --work /tmp/batch_bench
    # on a cluster started with `ray start --head --num-cpus 2`: the batch alone, joined with --address
    PYTHONPATH=. OMP_NUM_THREADS=1 python scripts/bench_fit_batch.py --work /tmp/batch_bench --address auto
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

CLI = [sys.executable, "-m", "torch_diffavatar.cli"]


def make_scans(work: Path, count: int) -> Path:
    """``count`` skirt scans ``work/scans/sK/scan.ply`` (seeds 1..count; made once) and their manifest."""
    rows = ["scan,garment"]
    for seed in range(1, count + 1):
        folder = work / "scans" / f"s{seed}"
        if not (folder / "scan.ply").is_file():
            argv = ["make-scan", "skirt", "--out", str(folder), "--seed", str(seed), "--spacing", "0.05"]
            argv += ["--garment-points", "3000", "--body-points", "3000"]
            subprocess.run([*CLI, *argv], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        rows.append(f"scans/s{seed}/scan.ply,skirt")
    manifest = work / "manifest.csv"
    manifest.write_text("\n".join(rows) + "\n")
    return manifest


def timed(label: str, argvs: list[list[str]]) -> dict:
    """Run the commands ``argvs`` one after another; wall seconds and the load average before/after."""
    load0, t0 = os.getloadavg()[0], time.perf_counter()
    for argv in argvs:
        subprocess.run(argv, check=False, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    seconds = time.perf_counter() - t0
    row = {"run": label, "wall_s": round(seconds, 1), "load_before": load0, "load_after": os.getloadavg()[0]}
    print(
        f"{label:28s} {seconds:7.1f} s wall   load average {load0:.2f} -> {row['load_after']:.2f}", flush=True
    )
    return row


def chamfers(folder: Path) -> dict:
    """scan folder name -> final Chamfer [m] of the fits under ``folder``."""
    return {
        p.parent.name.removesuffix("-scan"): json.loads(p.read_text())["chamfer_final"]
        for p in sorted(folder.glob("*/report.json"))
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--work", required=True, help="folder for the scans and the runs' outputs")
    p.add_argument("--scans", type=int, default=8)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--iters", type=int, default=2)
    p.add_argument("--spacing", type=float, default=0.08)
    p.add_argument("--address", default=None, help="time only fit-batch on this running Ray cluster")
    args = p.parse_args(argv)
    work = Path(args.work)
    manifest = make_scans(work, args.scans)
    opts = ["--iters", str(args.iters), "--spacing", str(args.spacing), "--no-progress"]
    runs = {}
    if args.address is None:
        runs["loop"] = work / "loop"
        shutil.rmtree(runs["loop"], ignore_errors=True)
        fits = [
            [*CLI, "fit", str(s), "--garment", "skirt", "--out", str(runs["loop"] / s.parent.name), *opts]
            for s in sorted((work / "scans").glob("s*/scan.ply"))[: args.scans]
        ]
        rows = [timed(f"loop of {len(fits)} `fit`", fits)]
        widths = (1, args.workers)
    else:  # compared with an earlier run's loop when it is there
        rows, widths = [], (args.workers,)
        if (work / "loop").is_dir():
            runs["loop"] = work / "loop"
    for n in widths:
        out = runs.setdefault(f"w{n}", work / f"batch_w{n}")
        shutil.rmtree(out, ignore_errors=True)
        where = ["--address", args.address] if args.address else []
        batch = [*CLI, "fit-batch", str(manifest), "--out", str(out), "--workers", str(n), *where, *opts]
        rows.append(timed(f"fit-batch --workers {n}" + (" (cluster)" if where else ""), [batch]))
    results = {k: chamfers(v) for k, v in runs.items()}
    first = next(iter(results.values()))
    same = all(r == first for r in results.values())
    print(f"per-scan final Chamfer identical across the runs: {same} ({len(first)} scans)")
    if len(rows) > 1:
        print(f"fit-batch --workers {args.workers} / loop: {rows[-1]['wall_s'] / rows[0]['wall_s']:.2f}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
