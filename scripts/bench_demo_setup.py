#!/usr/bin/env python
"""Where ``diffavatar demo``'s time goes, phase by phase (issue #32): wall and CPU seconds.

Runs the demo in this process (``torch_diffavatar.cli.main``) with timers wrapped around its phases and
prints a table, phase -> wall s, CPU s; a phase's sub-phases are indented under it (included in its time),
and ``other`` is what no listed phase covers. The CPU column is the one to compare on a shared machine.

    PYTHONPATH=. OMP_NUM_THREADS=1 python scripts/bench_demo_setup.py --out /tmp/demo_bench
    PYTHONPATH=. OMP_NUM_THREADS=1 python scripts/bench_demo_setup.py --out /tmp/demo_bench --iters 0

CPU seconds are the process's and its forked workers' (the body fit's second direction, the race's
candidates: counted once each worker has ended). ``--iters 0`` times the set-up and the writing alone (the
first drape and its report, no fit steps).
``--json FILE`` also writes the table and the demo's report figures as JSON.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
import time


def cpu_seconds() -> float:
    """User + system CPU seconds of this process and of its ended children (the forked workers)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


T0_WALL, T0_CPU = time.perf_counter(), cpu_seconds()

# (label, module, attribute [, class attribute]); in run order; a label with a leading space is a
# sub-phase of the one above it
PHASES = [
    ("scan fingerprint (SHA-256)", "torch_diffavatar.fit_scan", "fit_fingerprint"),
    ("scan intake", "torch_diffavatar.fit_setup", "load_fit_scan"),
    ("Anny load", "torch_diffavatar.body.anny_model", "load_anny"),
    ("prepare (set-up)", "torch_diffavatar.fit_setup", "prepare"),
    (" body fit", "torch_diffavatar.body.fit", "fit_body"),
    (" garment mask + openings", "torch_diffavatar.fit_setup", "scan_boundaries"),
    (" placement", "torch_diffavatar.sim.placement", "place_garment_turned"),
    (" A-pose route (sewing fallback)", "torch_diffavatar.sim.placement", "a_pose_route"),
    ("setup.pt + checkpoints saved", "torch_diffavatar.fit_checkpoint", "atomic_save"),
    ("Fitter built", "torch_diffavatar.fit", "Fitter", "__init__"),
    ("first sewing + drape", "torch_diffavatar.fit", "Fitter", "_first_states"),
    ("TensorBoard writer (import)", "torch_diffavatar.fit", "open_writer"),
    ("first evaluation", "torch_diffavatar.fit", "Fitter", "_first_evaluation"),
    ("fit iterations", "torch_diffavatar.fit", "Fitter", "_iterate"),
    (" TensorBoard logging (pictures)", "torch_diffavatar.fit", "log_evaluation"),
    ("best iterate restored", "torch_diffavatar.fit", "restore_best"),
    ("assets written", "torch_diffavatar.fit_scan", "write_fit_assets"),
    ("truth comparison", "torch_diffavatar.evaluation", "compare_with_truth"),
]


class Timers:
    def __init__(self):
        self.totals: dict[str, list[float]] = {}

    def wrap(self, label: str, fn):
        def timed(*args, **kwargs):
            w, c = time.perf_counter(), cpu_seconds()
            try:
                return fn(*args, **kwargs)
            finally:
                acc = self.totals.setdefault(label, [0.0, 0.0])
                acc[0] += time.perf_counter() - w
                acc[1] += cpu_seconds() - c

        return timed


def install(timers: Timers) -> None:
    for label, module, attr, *member in PHASES:
        owner = getattr(importlib.import_module(module), attr) if member else importlib.import_module(module)
        name = member[0] if member else attr
        setattr(owner, name, timers.wrap(label, getattr(owner, name)))
    # `commands.demo` imports `evaluation.compare_with_truth` at call time: the patched one is found


def table(timers: Timers, total: tuple[float, float], imports: tuple[float, float]) -> list[dict]:
    rows = [{"phase": "imports + argument parser", "wall_s": imports[0], "cpu_s": imports[1]}]
    for label, *_ in PHASES:
        wall, cpu = timers.totals.get(label, (0.0, 0.0))
        rows.append({"phase": label, "wall_s": wall, "cpu_s": cpu})
    top = [r for r in rows if not r["phase"].startswith(" ")]
    rows.append(
        {
            "phase": "other",
            "wall_s": total[0] - sum(r["wall_s"] for r in top),
            "cpu_s": total[1] - sum(r["cpu_s"] for r in top),
        }
    )
    rows.append({"phase": "total (process)", "wall_s": total[0], "cpu_s": total[1]})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="/tmp/demo_bench")
    ap.add_argument("--iters", type=int, default=None)
    ap.add_argument("--json", default=None, help="write the table and the report figures here")
    args = ap.parse_args()
    from torch_diffavatar import cli

    parser = cli.build_parser()
    imports = (time.perf_counter() - T0_WALL, cpu_seconds() - T0_CPU)
    timers = Timers()
    install(timers)
    argv = ["demo", "--out", args.out, "--force", "--no-progress", "--json"]
    argv += [] if args.iters is None else ["--iters", str(args.iters)]
    parsed = parser.parse_args(argv)
    summary = parsed.func(parsed)
    total = (time.perf_counter() - T0_WALL, cpu_seconds() - T0_CPU)
    rows = table(timers, total, imports)
    print(f"{'phase':<36} {'wall s':>8} {'CPU s':>8}", file=sys.stderr)
    for r in rows:
        print(f"{r['phase']:<36} {r['wall_s']:8.2f} {r['cpu_s']:8.2f}", file=sys.stderr)
    keys = ("chamfer_initial", "chamfer_final", "pattern_outline_error_m", "pattern_outline_hausdorff_m")
    figures = {k: summary.get(k) for k in keys}
    figures["bend_stiffness_final"] = summary["material"]["bend_stiffness_final"]
    figures["body_fit_chamfer_m"] = summary.get("body_fit_chamfer_m")
    figures["bending_stiffness_ratio"] = summary.get("bending_stiffness_ratio")
    print(json.dumps(figures), file=sys.stderr)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"phases": rows, "figures": figures}, f, indent=1)


if __name__ == "__main__":
    main()
