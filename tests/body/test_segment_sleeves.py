"""Segmentation of an unlabelled long-sleeve scan: the cuffs over the wrists (`body.segment`).

A long sleeve ends over the wrist, where the nearest body vertices belong to the hand. With the hands
outside the shirt's region its last centimetres came out skin and the cuff's target moved up the sleeve
(measured on this scan: 56 % of the garment points within 5 cm of the true left cuff labelled, target
27 mm from the cuff; with the hands 99 % and 16 mm).
"""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from torch_diffavatar.body.segment import segment_garment

pytestmark = [pytest.mark.anny, pytest.mark.slow]


@pytest.fixture(scope="module")
def longsleeve_scan(anny_model):
    """A long sleeve draped on a random body (seed 0) at 3 cm, 10k cloth points, 3 mm noise, holes."""
    from torch_diffavatar.synthetic_scans import make_draped_scan

    return make_draped_scan("longsleeve", anny_model=anny_model, seed=0, spacing=0.03, garment_points=10000)


def test_a_long_sleeves_cuff_over_the_wrist_is_garment(longsleeve_scan, anny_model):
    from torch_diffavatar.body.model import BodyModel

    scan = longsleeve_scan
    parts = BodyModel(anny_model=anny_model).vertex_parts.numpy()
    # the true body: this checks the segmentation, not the body fit
    seg = segment_garment(scan.points, "shirt", scan.body_vertices, scan.body_faces, parts)
    truth = scan.labels == 1
    precision = (seg.labels & truth).sum() / seg.labels.sum()
    assert precision >= 0.98, precision
    loops = {lp.name: lp for lp in scan.garment.boundary_loops}
    # the left cuff is whole in this scan (a hole took the right one's end)
    rim = scan.cloth_x[loops["cuff_left"].vertices.numpy()]
    near_cuff = truth & (cKDTree(rim).query(scan.points)[0] < 0.05)
    assert near_cuff.sum() > 100
    recall = (seg.labels & near_cuff).sum() / near_cuff.sum()
    assert recall >= 0.95, recall
    (cuff,) = [lp for lp in seg.loops if lp.name == "cuff_left"]
    target = scan.points[seg.garment_indices[cuff.point_indices]]
    assert float(np.mean(cKDTree(rim).query(target)[0])) < 0.02
