#!/usr/bin/env python
"""A picture of each stage of a real-scan fit (README, "Real scans"), on a capture-simulated scan.

    python -m torch_diffavatar.cli make-scan tshirt --out /tmp/c_s11 --seed 11 --capture ring --yaw random \
        --scan-units cm --scan-up -y
    python -m torch_diffavatar.cli fit-body /tmp/c_s11/scan.ply --out /tmp/b_c_s11
    python -m torch_diffavatar.cli fit /tmp/c_s11/scan.ply --garment tshirt --out /tmp/F11
    PYTHONPATH=. python scripts/real_scan_stages.py /tmp/c_s11/scan.ply --body /tmp/b_c_s11 --fit /tmp/F11 \
        --out docs/real_scan_stages.png

Four panels, left to right: the file as it comes (its own units and axes, coloured points, floor and
clutter included), the person after the intake (metres, Y up, floor and clutter gone), the fitted body
under the scan's points, and the fitted garment under the scan's garment points. Points are drawn as
small camera-facing triangles, so the z-buffer decides what is in front.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from torch_diffavatar.mesh_io import read_obj
from torch_diffavatar.render import BODY_COLOR, RenderMesh, point_splats, render, save_png
from torch_diffavatar.scan import load_scan
from torch_diffavatar.scan_intake import intake_scan

GARMENT = (60, 100, 190)


def _grey(colors: np.ndarray | None):
    """A scan's (N, 3) colours, or grey for a scan without them."""
    return (150, 150, 150) if colors is None else colors


def stages(scan_path, body_dir, fit_dir, size: int, view: float) -> np.ndarray:
    """(size, 4·size, 3) uint8: the four panels (see the module docstring) seen from azimuth ``view``."""
    raw = load_scan(scan_path, check=False)
    person, _ = intake_scan(scan_path)
    kw = dict(view=view, width=size, height=size)
    splat = 0.006 * np.ptp(raw.points[:, 1])  # the file's own units
    panels = [
        render(point_splats(raw.points, _grey(raw.colors), splat, view), elevation_deg=20.0, **kw),
        render(point_splats(person.points, _grey(person.colors), 0.01, view), **kw),
    ]
    body = read_obj(Path(body_dir) / "body.obj")
    dots = (200, 40, 40)
    panels.append(
        render(
            [
                RenderMesh(body.verts.numpy(), body.faces.numpy(), BODY_COLOR),
                point_splats(person.points[::4], dots, 0.006, view),
            ],
            **kw,
        )
    )
    fitted_body, drape = read_obj(Path(fit_dir) / "body.obj"), read_obj(Path(fit_dir) / "draped.obj")
    garment = person.points if person.labels is None else person.points[person.labels == 1]
    dots = (240, 240, 240)
    panels.append(
        render(
            [
                RenderMesh(fitted_body.verts.numpy(), fitted_body.faces.numpy(), BODY_COLOR),
                RenderMesh(drape.verts.numpy(), drape.faces.numpy(), GARMENT),
                point_splats(garment[::3], dots, 0.006, view),
            ],
            **kw,
        )
    )
    return np.concatenate(panels, axis=1)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("scan")
    parser.add_argument("--body", required=True, help="a fit-body output folder (body.obj)")
    parser.add_argument("--fit", required=True, help="a fit output folder (body.obj, draped.obj)")
    parser.add_argument("--out", required=True)
    parser.add_argument("--size", type=int, default=360)
    parser.add_argument(
        "--view", type=float, default=None, help="azimuth [deg] (default: the person's front)"
    )
    args = parser.parse_args()
    view = args.view
    if view is None:  # face the person: the yaw the body fit found (a camera at azimuth 0 is on +Z)
        view = float(json.loads((Path(args.body) / "body.json").read_text()).get("yaw_deg", 0.0))
    save_png(stages(args.scan, args.body, args.fit, args.size, view), args.out)
    print(args.out)


if __name__ == "__main__":
    main()
