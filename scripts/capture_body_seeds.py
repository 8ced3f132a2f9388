#!/usr/bin/env python
"""Issue #29's body-fit criterion on capture-simulated scans: `diffavatar fit-body` with no flags on a ring
of 4 depth cameras, the floor in view, a random yaw, centimetres, Y down and colour; the fitted body's height
and mean surface distance against the truth.

    PYTHONPATH=. python scripts/capture_body_seeds.py --work /tmp/cbs --garments tshirt pants \
        --seeds 350 351 352 353 354 355 356 357 358 359

Per garment and seed: `diffavatar make-scan G --out WORK/G_S/scan --seed S --capture ring --yaw random
--scan-units cm --scan-up -y`, then `diffavatar fit-body WORK/G_S/scan/scan.ply --out WORK/G_S/body --json`
(the intake infers the units and the up axis). Height error: the fit's ``height_m`` against truth.json's;
surface: the symmetric mean surface distance between the fitted and the true ``body.obj``
(`evaluation.mesh_distance_m`); vertex: their mean vertex distance (the same Anny topology and frame).
Targets (#29): height within 1.5 cm and surface distance ≤ 1 cm; with ``--capture front`` (one camera, the
same flags otherwise) the front-only target, the height within 2 cm. Prints a Markdown table and writes
``WORK/summary.json``; a scan whose folders exist is not made or fitted again.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

HEIGHT_TARGET_M = 0.015
SURFACE_TARGET_M = 0.01
FRONT_HEIGHT_TARGET_M = 0.02  # #29's front-only captures: the height alone, within 2 cm


def _run(args: list[str], log: Path, check: bool = True) -> str | None:
    """Run ``python -m torch_diffavatar.cli ARGS``; its stdout (stderr appended to ``log``). A failed
    command ends the script, or with ``check`` False returns None."""
    with open(log, "a") as err:
        command = [sys.executable, "-m", "torch_diffavatar.cli", *args]
        done = subprocess.run(command, stdout=subprocess.PIPE, stderr=err, text=True)
    if done.returncode != 0 and not check:
        return None
    if done.returncode != 0:
        name = " ".join(args[:2])
        raise SystemExit(f"{Path(sys.argv[0]).stem}: {name} failed (exit {done.returncode}); see {log}")
    return done.stdout


def make_capture(
    folder: Path, garment: str, seed: int, capture: str = "ring", rig: tuple[str, ...] = ()
) -> Path:
    """``folder/scan``: the capture of ``garment`` and ``seed`` (``capture``: ``ring`` or ``front``, the
    `make-scan --capture` choices; random yaw, cm, Y down; ``rig``: more of make-scan's capture options,
    e.g. ``("--flying-pixels", "0.3")``), made unless it is there."""
    scan = folder / "scan"
    folder.mkdir(parents=True, exist_ok=True)
    if not (scan / "scan.ply").is_file():
        capture = ["--capture", capture, "--yaw", "random", "--scan-units", "cm", "--scan-up", "-y", *rig]
        _run(["make-scan", garment, "--out", str(scan), "--seed", str(seed), *capture], folder / "log.txt")
    return scan


def one_scan(work: Path, garment: str, seed: int, capture: str = "ring") -> dict:
    """Make (unless made) and fit (unless fitted) one capture (``capture``: ``ring`` or ``front``, the
    `make-scan --capture` choices); its row of figures."""
    from torch_diffavatar.evaluation import mesh_distance_m
    from torch_diffavatar.mesh_io import read_obj

    folder = work / f"{garment}_{seed}"
    scan = make_capture(folder, garment, seed, capture)
    body, log = folder / "body", folder / "log.txt"
    if not (body / "fit.json").is_file():
        line = _run(["fit-body", str(scan / "scan.ply"), "--out", str(body), "--json"], log).strip()
        (body / "fit.json").write_text(line.splitlines()[-1] + "\n")
    fit = json.loads((body / "fit.json").read_text())
    truth = json.loads((scan / "truth" / "truth.json").read_text())
    fitted, true = read_obj(body / "body.obj"), read_obj(scan / "truth" / "body.obj")
    surface = mesh_distance_m(fitted.verts, fitted.faces, true.verts, true.faces)
    same = fitted.verts.shape == true.verts.shape  # the same Anny topology: vertex to vertex
    vertex = float((fitted.verts - true.verts).norm(dim=1).mean()) if same else None
    return {
        "garment": garment,
        "seed": seed,
        "true_height_m": truth["height_m"],
        "height_error_m": fit["height_m"] - truth["height_m"],
        "surface_m": surface,
        "vertex_m": vertex,
        "sole_m": float(fitted.verts[:, 1].min() - true.verts[:, 1].min()),
        "yaw_true_deg": truth.get("capture", {}).get("yaw_deg", 0.0),  # 0: a scan with no capture
        "yaw_deg": fit.get("yaw_deg"),
        "chamfer_m": fit["chamfer_m"],
        "seconds": fit["seconds"],
        "warnings": fit.get("warnings", []),
    }


def table(rows: list[dict], front: bool = False) -> str:
    """The Markdown table of ``rows``, **bold** where a target is missed (``front``: the front-only
    criterion, the height within `FRONT_HEIGHT_TARGET_M` and no surface target)."""
    height_target = FRONT_HEIGHT_TARGET_M if front else HEIGHT_TARGET_M
    surface_target = math.inf if front else SURFACE_TARGET_M
    out = [
        "| scan | true height [m] | height error [cm] | surface / vertex [cm] | soles [cm] "
        "| yaw true / found [°] | body fit Chamfer [mm] | s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        h, s = r["height_error_m"], r["surface_m"]
        hs = f"{100 * h:+.2f}" if abs(h) <= height_target else f"**{100 * h:+.2f}**"
        ss = f"{100 * s:.2f}" if s <= surface_target else f"**{100 * s:.2f}**"
        vs = "–" if r["vertex_m"] is None else f"{100 * r['vertex_m']:.2f}"
        yaw = "–" if r["yaw_deg"] is None else f"{r['yaw_deg'] % 360:.1f}"
        out.append(
            f"| {r['garment']} {r['seed']} | {r['true_height_m']:.3f} | {hs} | {ss} / {vs} | "
            f"{100 * r['sole_m']:+.1f} | {r['yaw_true_deg'] % 360:.1f} / {yaw} | "
            f"{1e3 * r['chamfer_m']:.1f} | {r['seconds']:.0f} |"
        )
    met = sum(abs(r["height_error_m"]) <= height_target and r["surface_m"] <= surface_target for r in rows)
    out.append(f"\n{'The height target' if front else 'Both targets'} met on {met} of {len(rows)}.")
    return "\n".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, required=True, help="folder for the scans and the fits")
    parser.add_argument("--garments", nargs="+", default=["tshirt"])
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(350, 360)))
    parser.add_argument(
        "--capture",
        choices=("ring", "front"),
        default="ring",
        help="a ring of 4 cameras (#29's first criterion) or one in front (its front-only criterion)",
    )
    args = parser.parse_args()
    rows = [one_scan(args.work, g, s, args.capture) for g in args.garments for s in args.seeds]
    (args.work / "summary.json").write_text(json.dumps(rows, indent=1) + "\n")
    print(table(rows, front=args.capture == "front"))


if __name__ == "__main__":
    main()
