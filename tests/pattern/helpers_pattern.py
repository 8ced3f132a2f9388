"""Small hand-made patterns for the pattern tests (cm, GarmentCode JSON dicts)."""

from __future__ import annotations

import copy
import json
from pathlib import Path

SPECS = sorted(Path("/work/shared/garmentcode").glob("**/*_specification.json"))
VALID_SPECS = [p for p in SPECS if "hoody_mean" not in p.name]


def two_squares(right_wrong: bool = False) -> dict:
    """A front square (CCW, z = +10 cm) and a back square (CW, z = -10 cm) sewn at one side.

    Front: (0,0) (20,0) (20,30) (0,30); edge 1 is its right side, running up.
    Back (mirrored, CW): (0,0) (0,30) (20,30) (20,0) placed so x matches; edge 2 is its right side (down).
    The default seam (end of A to start of B) joins them; with ``right_wrong`` the back edge is
    reversed so the same geometric seam needs start-to-start.
    """
    front = {
        "translation": [0, 100, 10],
        "rotation": [0, 0, 0],
        "vertices": [[0, 0], [20, 0], [20, 30], [0, 30]],
        "edges": [{"endpoints": [0, 1]}, {"endpoints": [1, 2]}, {"endpoints": [2, 3]}, {"endpoints": [3, 0]}],
    }
    if right_wrong:  # back loop CCW-ordered the other way: edge 2 runs up along x = 20
        back_v = [[0, 30], [0, 0], [20, 0], [20, 30]]
    else:  # CW: edge 2 runs down along x = 20
        back_v = [[0, 0], [0, 30], [20, 30], [20, 0]]
    back = {
        "translation": [0, 100, -10],
        "rotation": [0, 0, 0],
        "vertices": back_v,
        "edges": [{"endpoints": [0, 1]}, {"endpoints": [1, 2]}, {"endpoints": [2, 3]}, {"endpoints": [3, 0]}],
    }
    stitch = [{"panel": "front", "edge": 1}, {"panel": "back", "edge": 2}]
    if right_wrong:
        stitch.append("right_wrong")
    return {
        "pattern": {"panels": {"front": front, "back": back}, "stitches": [stitch]},
        "properties": {"units_in_meter": 100, "curvature_coords": "relative"},
    }


def dart_panel() -> dict:
    """A 30 x 30 cm panel with a V dart cut into its bottom edge, the dart legs stitched together."""
    panel = {
        "translation": [0, 100, 10],
        "rotation": [0, 0, 0],
        "vertices": [[0, 0], [13, 0], [15, 10], [17, 0], [30, 0], [30, 30], [0, 30]],
        "edges": [{"endpoints": [i, (i + 1) % 7]} for i in range(7)],
    }
    return {
        "pattern": {
            "panels": {"front": panel},
            "stitches": [[{"panel": "front", "edge": 1}, {"panel": "front", "edge": 2}]],
        },
        "properties": {"units_in_meter": 100},
    }


def write_json(path: Path, data) -> Path:
    path.write_text(json.dumps(data) if not isinstance(data, str) else data)
    return path


def deep(d: dict) -> dict:
    return copy.deepcopy(d)
