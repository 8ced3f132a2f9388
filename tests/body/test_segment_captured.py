"""The scan's openings on depth captures (`capture`: a ring of 4 cameras, noise growing with distance,
no returns at grazing angles), with the true body: this checks the openings, not the body fit."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

pytestmark = [pytest.mark.anny, pytest.mark.slow]


def _captured(template: str, seed: int, anny_model, **settings):
    """A ``template`` draped at 3 cm (seed ``seed``) and captured by a ring, and its openings found with
    the true body: (the captured `DrapedScan`, opening name -> (k, 3) points)."""
    from torch_diffavatar.body.parts import vertex_parts
    from torch_diffavatar.capture import CaptureSettings
    from torch_diffavatar.captured_scans import capture_draped_scan
    from torch_diffavatar.fit_setup import SEGMENT_TYPES, scan_boundaries
    from torch_diffavatar.synthetic_scans import make_draped_scan

    scan = make_draped_scan(template, anny_model=anny_model, seed=seed, spacing=0.03)
    cap, _ = capture_draped_scan(scan, CaptureSettings(layout="ring", **settings), seed)
    parts = vertex_parts(anny_model).numpy()
    kind = SEGMENT_TYPES.get(template, template)
    return cap, scan_boundaries(cap.points, cap.labels == 1, cap.body_vertices, cap.body_faces, parts, kind)


def _true_loop(cap, name: str) -> np.ndarray:
    (loop,) = [lp for lp in cap.garment.boundary_loops if lp.name == name]
    return cap.cloth_x[loop.vertices.numpy()]


def test_a_turned_persons_trouser_legs_are_each_its_own(anny_model):
    """Turned 90°, the legs lie front and back in x: each leg's hem took half of both legs (the left's
    points 6.8 cm from its true hem on average, traced 104.7 cm against 68.8). The body's own left-right
    axis splits them: 1.3 cm."""
    from torch_diffavatar.opening_lengths import scan_loop_length

    cap, loops = _captured("pants", 71, anny_model, yaw_deg=90.0)
    for name in ("hem_left", "hem_right"):
        truth = _true_loop(cap, name)
        assert float(np.mean(cKDTree(truth).query(loops[name])[0])) < 0.02, name
        true_length = float(np.linalg.norm(np.roll(truth, -1, 0) - truth, axis=1).sum())
        assert abs(scan_loop_length(loops[name])[0] - true_length) < 0.1 * true_length, name


def test_a_captured_cuff_whose_edge_the_noise_hides_is_the_sleeves_far_end(anny_model):
    """A ring capture's depth noise (σ 9 mm at 2.2 m) hides the edge of this T-shirt's left sleeve (too
    few rim points), and the fallback took the whole band near the body's loop, the sleeve's last 20 cm:
    its target lay 7.6 cm from the true cuff on average, and fits shrank the cuff 3-5 cm. Now the
    sleeve's far end: 1.9 cm (the right cuff, whose rim is found: 1.1 cm)."""
    cap, loops = _captured("tshirt", 62, anny_model)
    for name in ("cuff_left", "cuff_right"):
        assert float(np.mean(cKDTree(_true_loop(cap, name)).query(loops[name])[0])) < 0.025, name
