"""The openings found on labelled scans of GarmentCode garments beyond our templates (`body.segment`).

A hood's face opening stands upright in front of the face, its sides several centimetres off it: the
neckline's rule (rim points near the bare skin, the top of each sector about the neck) kept only its top
and bottom (`_neck_opening` says what is kept now, and what was measured). A jumpsuit has a neck, two
cuffs and two trouser legs: typed as trousers, its neckline was named "waist" and matched to the
garment's neck by proximity, and its legs were unnamed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from torch_diffavatar.fit_setup import infer_garment_type, scan_boundaries
from torch_diffavatar.pattern import load_pattern

pytestmark = [pytest.mark.anny, pytest.mark.slow]

EXAMPLES = Path("/work/shared/garmentcode/repo_examples")


def _spec(name: str) -> Path:
    path = EXAMPLES / name / f"{name}_specification.json"
    if not path.is_file():
        pytest.skip(f"{path} not on this machine")
    return path


def _openings(name: str, anny_model, seed: int):
    """(scan, kind, found): a 3 cm drape of GarmentCode's ``name`` on a random body, its inferred garment
    type, and the openings found on its labelled scan with the true body, garment loop name -> (k, 3)
    target points [m]."""
    from torch_diffavatar.body.model import BodyModel
    from torch_diffavatar.synthetic_scans import make_draped_scan

    path = _spec(name)
    scan = make_draped_scan(str(path), anny_model=anny_model, seed=seed, spacing=0.03, garment_points=40000)
    parts = BodyModel(anny_model=anny_model).vertex_parts.numpy()
    kind = infer_garment_type(load_pattern(path))
    loops = scan_boundaries(scan.points, scan.labels == 1, scan.body_vertices, scan.body_faces, parts, kind)
    return scan, kind, loops


def _distances(scan, name: str, target: np.ndarray) -> tuple[float, float]:
    """Mean distance [m] of the target to the true opening ``name`` (each of its edges sampled at ten
    points), and of the opening's vertices to the target."""
    loops = {lp.name: lp.vertices.numpy() for lp in scan.garment.boundary_loops}
    v = scan.cloth_x[loops[name]]
    t = np.linspace(0.0, 1.0, 10, endpoint=False)[:, None, None]
    edge_points = (v[None] * (1 - t) + np.roll(v, -1, axis=0)[None] * t).reshape(-1, 3)
    return float(cKDTree(edge_points).query(target)[0].mean()), float(cKDTree(target).query(v)[0].mean())


def test_a_hoods_face_opening_is_found_whole(anny_model):
    scan, kind, found = _openings("hoody_mean", anny_model, seed=21)
    assert kind == "dress"  # a sleeveless top: armholes
    to_loop, to_target = _distances(scan, "neck", found["neck"])
    # measured: 22 and 20 mm (the neckline's rule: 34 and 59 mm; on 2 cm scans of three bodies 4-9 and
    # 10-12 mm, against 20-69 and 44-79 mm)
    assert to_loop < 0.03 and to_target < 0.03, (to_loop, to_target)


def test_a_jumpsuits_openings_are_its_neck_cuffs_and_legs(anny_model):
    scan, kind, found = _openings("js_mean_all", anny_model, seed=26)
    assert kind == "jumpsuit"
    names = {lp.name for lp in scan.garment.boundary_loops}
    assert names == {"neck", "cuff_left", "cuff_right", "hem_left", "hem_right"}
    assert set(found) == names
    for name, target in found.items():
        to_loop, to_target = _distances(scan, name, target)
        # measured: 5-12 mm and 7-17 mm
        assert to_loop < 0.02 and to_target < 0.03, (name, to_loop, to_target)
