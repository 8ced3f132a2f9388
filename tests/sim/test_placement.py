"""Garment placement around bodies: every template starts outside the body, seams start outside too."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from helpers_placement import green_strain_max

from torch_diffavatar.body.frames import anny_to_world
from torch_diffavatar.pattern.library import load_template
from torch_diffavatar.pattern.mesher import mesh_pattern
from torch_diffavatar.sim.placement import body_landmarks, body_signed_distance, place_garment

TEMPLATES = ("dress", "dress_pencil", "tshirt", "longsleeve", "polo", "skirt", "pants", "shorts")
SPACING = 0.02  # coarser than the default to keep the test fast


def _check_clear(garment, placed, verts, faces):
    pos = placed.vert_pos.numpy()
    sd = body_signed_distance(pos, verts, faces)
    assert sd.min() >= 0.01 - 1e-6, f"a panel vertex starts {sd.min() * 100:.2f} cm from the body"
    pairs = placed.stitch_pairs.numpy()
    mid = body_signed_distance(0.5 * (pos[pairs[:, 0]] + pos[pairs[:, 1]]), verts, faces)
    assert mid.min() >= 0.015 - 1e-6, f"a stitch midpoint starts {mid.min() * 100:.2f} cm from the body"
    return pos


@pytest.fixture(scope="module")
def body(default_body):
    verts, faces = default_body
    return verts, faces, body_landmarks(verts, faces)


@pytest.fixture(scope="module")
def meshes():
    return {name: mesh_pattern(load_template(name), spacing=SPACING) for name in TEMPLATES}


def test_signed_distance_matches_a_sphere():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.3)
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(500, 3))
    pts *= rng.uniform(0.05, 0.6, size=(500, 1)) / np.linalg.norm(pts, axis=1, keepdims=True)
    sd = body_signed_distance(pts + [0, 1.0, 0], sphere.vertices + [0, 1.0, 0], sphere.faces)
    # the icosphere's faces lie up to ~1.2 mm inside the true sphere
    np.testing.assert_allclose(sd, np.linalg.norm(pts, axis=1) - 0.3, atol=2e-3)


@pytest.mark.anny
def test_landmarks_of_the_default_body(body):
    _, _, lm = body
    assert lm.floor_y == pytest.approx(0.0, abs=1e-6)
    assert lm.height == pytest.approx(1.625, abs=0.01)
    assert 0.6 < lm.crotch_y < lm.hip_y < lm.waist_y < lm.armpit_y < lm.shoulder_y < lm.neck_y < lm.top_y
    assert 0.95 < lm.waist_y < 1.10 and 1.15 < lm.armpit_y < 1.30 and 1.30 < lm.shoulder_y < 1.40
    for arm, sign in ((lm.arm_left, 1.0), (lm.arm_right, -1.0)):
        assert arm is not None and len(arm) > 10
        assert 0.10 < sign * arm[0, 0] < 0.22  # the shoulder joint
        assert sign * arm[-1, 0] > 0.35 and arm[-1, 1] < arm[0, 1] - 0.2  # the wrist: out and down
        upper = arm[min(8, len(arm) - 1)] - arm[0]
        angle = np.degrees(np.arctan2(-upper[1], abs(upper[0])))
        assert 35 < angle < 60  # Anny's A-pose: upper arms ~48° below horizontal


@pytest.mark.anny
@pytest.mark.parametrize("name", TEMPLATES)
def test_every_template_starts_outside_the_default_body(name, body, meshes):
    verts, faces, lm = body
    garment = meshes[name]
    placed = place_garment(garment, verts, faces, body_landmarks=lm)
    pos = _check_clear(garment, placed, verts, faces)
    assert body_signed_distance(pos, verts, faces).max() < 0.2  # wrapped close, not flung out
    # only the 3D placement changed
    assert placed.vert_uv is garment.vert_uv and placed.tri_vertices is garment.tri_vertices
    assert placed.vert_pos.shape == garment.vert_pos.shape and placed.vert_pos.dtype == garment.vert_pos.dtype
    # wrapped, not crumpled: nearly all triangles keep their rest shape within a moderate strain
    strain = green_strain_max(garment, pos)
    assert np.percentile(strain, 95) < 0.35
    assert (strain > 1.0).mean() < 0.005
    # panels sit where the garment belongs on this body
    y = pos[:, 1]
    if name in ("skirt", "pants", "shorts"):
        assert y.max() < lm.armpit_y and y.max() > lm.waist_y - 0.05
    else:
        assert y.max() > lm.shoulder_y


@pytest.mark.anny
@pytest.mark.parametrize("spacing", [0.014, 0.0145])
def test_torso_wrap_between_the_arms_stays_shallow(spacing, body):
    # at these spacings the T-shirt's widest lateral outline under the armpits came within 0.1 mm of the
    # room between the arms, and the ellipse narrowed to that room had to be 2.3 m deep to enclose the
    # body: panel vertices started 2.3 m (0.014: 0.45 m) from it and the sewing phase exploded
    verts, faces, lm = body
    garment = mesh_pattern(load_template("tshirt"), spacing=spacing)
    placed = place_garment(garment, verts, faces, body_landmarks=lm)
    sd = body_signed_distance(placed.vert_pos.numpy(), verts, faces)
    assert sd.min() >= 0.01 - 1e-6 and sd.max() < 0.2


@pytest.mark.anny
@pytest.mark.parametrize("name", [n for n in TEMPLATES if n in ("tshirt", "longsleeve", "polo")])
def test_sleeve_panels_do_not_cross_under_the_arm(name, body, meshes):
    """A sleeve's front panel starts in front of its back panel along their shared seams.

    On the long tapered sleeve the old single centre line put the cap off-centre: its underarm corner
    wrapped past the bottom of the arm, the front and back panels crossed there, and sewing pulled cloth
    through the arm (the longsleeve's sewing phase never closed).
    """
    verts, faces, lm = body
    garment = meshes[name]
    pos = place_garment(garment, verts, faces, body_landmarks=lm).vert_pos.numpy()
    names, vp = garment.panel_names, garment.vert_panel.numpy()
    for a, b in garment.stitch_pairs.numpy():
        pa, pb = names[vp[a]], names[vp[b]]
        if "sleeve" not in pa or "sleeve" not in pb:
            continue
        front, back = (a, b) if pa.endswith("_f") else (b, a)
        assert pos[front, 2] > pos[back, 2] - 0.005, (
            f"{name}: sleeve seam crossed at {pos[front].round(3)}: front z {pos[front, 2]:.3f} behind "
            f"back z {pos[back, 2]:.3f}"
        )


@pytest.mark.anny
@pytest.mark.parametrize("phenotypes", [{"height": 0.15}, {"height": 0.9}, {"gender": 0.0, "weight": 0.9}])
def test_other_bodies(phenotypes, anny_model, meshes):
    kwargs = {k: torch.tensor([v], dtype=torch.float64) for k, v in phenotypes.items()}
    with torch.no_grad():
        verts = anny_to_world(anny_model(phenotype_kwargs=kwargs)["vertices"][0])
    verts = verts - verts.new_tensor([0.0, 1.0, 0.0]) * verts[:, 1].min()
    faces = anny_model.faces
    lm = body_landmarks(verts, faces)
    for name in ("tshirt", "pants"):
        placed = place_garment(meshes[name], verts, faces, body_landmarks=lm)
        pos = _check_clear(meshes[name], placed, verts, faces)
        if name == "tshirt":
            assert pos[:, 1].max() > lm.shoulder_y
        else:
            assert lm.waist_y - 0.05 < pos[:, 1].max() < lm.armpit_y


def test_bad_bodies_are_rejected(meshes):
    box = trimesh.creation.box(extents=(0.4, 1.7, 0.3))
    with pytest.raises(ValueError, match=r"\(Vb, 3\)"):
        place_garment(meshes["skirt"], box.vertices[:, :2], box.faces)
    with pytest.raises(ValueError, match="metres"):
        place_garment(meshes["skirt"], box.vertices * 100.0, box.faces)
    with pytest.raises(ValueError, match="out of range"):
        body_landmarks(box.vertices, box.faces + 100)
