"""`place_garment_turned`: a garment placed on a body facing any way (a captured person, issue #29) is the
+Z placement turned with the body."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torch_diffavatar.geometry import yaw_rotation
from torch_diffavatar.pattern.library import load_template
from torch_diffavatar.pattern.mesher import mesh_pattern
from torch_diffavatar.sim.placement import TURNED_BODY_DEG, place_garment, place_garment_turned

pytestmark = pytest.mark.anny


def test_turned_body_gets_the_turned_placement(default_body):
    verts, faces = default_body
    mesh = mesh_pattern(load_template("tshirt"), spacing=0.04)
    upright = place_garment(mesh, verts, faces).vert_pos.numpy()
    turn = yaw_rotation(120.0)
    turned_body = torch.as_tensor(verts.numpy() @ turn.T)
    placed = place_garment_turned(mesh, turned_body, faces, 120.0).vert_pos.numpy()
    np.testing.assert_allclose(placed, upright @ turn.T, atol=1e-6)
    near = place_garment_turned(mesh, verts, faces, 0.5 * TURNED_BODY_DEG).vert_pos.numpy()
    np.testing.assert_array_equal(near, upright)  # near +Z: the placement itself, bit for bit
