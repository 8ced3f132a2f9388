import warnings

import numpy as np
import pytest

from torch_diffavatar.errors import ScanError
from torch_diffavatar.scan import (
    ScanWarning,
    check_scan_frame,
    load_scan,
    remove_floor,
    remove_outliers,
    save_ply,
)


def _person(n=4000, seed=0):
    """A crude standing 'person' point cloud in metres, Y up: two legs, a torso, a head."""
    rng = np.random.default_rng(seed)
    parts = []
    for cx, lo, hi, r in (
        (-0.1, 0.0, 0.8, 0.07),
        (0.1, 0.0, 0.8, 0.07),
        (0.0, 0.8, 1.45, 0.16),
        (0.0, 1.5, 1.72, 0.09),
    ):
        m = n // 4
        t = rng.random(m) * 2 * np.pi
        parts.append(np.stack([cx + r * np.cos(t), lo + (hi - lo) * rng.random(m), r * np.sin(t)], 1))
    return np.concatenate(parts)


def test_ply_with_labels_colours_units_and_up(tmp_path):
    pts = _person()
    colors = np.tile(np.array([[10, 20, 30]], dtype=np.uint8), (len(pts), 1))
    labels = (pts[:, 1] > 0.8).astype(np.int64)
    # Stored in cm with Z up (Anny-like: facing −Y).
    stored = np.stack([pts[:, 0], -pts[:, 2], pts[:, 1]], 1) * 100.0
    path = tmp_path / "scan.ply"
    save_ply(path, stored, colors=colors, int_properties={"label": labels})
    scan = load_scan(path, units="cm", up="z")
    np.testing.assert_allclose(scan.points, pts, atol=1e-5)
    np.testing.assert_array_equal(scan.labels, labels)
    np.testing.assert_array_equal(scan.colors, colors)
    assert scan.faces is None and scan.warnings == []
    side = tmp_path / "labels.txt"
    np.savetxt(side, 1 - labels, fmt="%d")
    np.testing.assert_array_equal(load_scan(path, units="cm", up="z", labels=side).labels, 1 - labels)


def test_obj_mesh_and_faces(tmp_path):
    path = tmp_path / "tri.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 3 4\n")
    scan = load_scan(path, check=False)
    assert scan.faces.shape == (2, 3)
    kept = scan.subset(np.array([True, True, True, False]))
    assert kept.faces.shape == (1, 3)


def _textured_cylinder(top_rgb, bottom_rgb, shift=0.0):
    """A cylinder (r = 0.3 m, 1.6 m tall, Y up) textured with ``top_rgb`` above y = 0.8 + ``shift`` and
    ``bottom_rgb`` below: its UVs' v is the height, its image two bands."""
    import trimesh
    from PIL import Image

    mesh = trimesh.creation.cylinder(radius=0.3, height=1.6, sections=48)
    mesh.vertices = mesh.vertices[:, [0, 2, 1]] + [shift, 0.8, 0.0]  # Y up, standing on y = 0
    y = mesh.vertices[:, 1]
    uv = np.stack([np.arctan2(mesh.vertices[:, 2], mesh.vertices[:, 0]) / (2 * np.pi) % 1.0, y / 1.6], 1)
    image = np.zeros((32, 32, 3), np.uint8)
    image[:16], image[16:] = top_rgb, bottom_rgb  # row 0 is v = 1, the top
    mesh.visual = trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(image))
    return mesh


@pytest.mark.parametrize("suffix", [".obj", ".glb"])
def test_a_textured_mesh_gives_its_colours_at_the_vertices(tmp_path, suffix):
    """Photogrammetry meshes carry their colour as a texture (OBJ + MTL + image, GLB): the scan's colours
    are the image at each vertex's UV (they were None, and the fit segmented without colour); a GLB of
    two textured parts keeps each part's colours."""
    import trimesh

    parts = [_textured_cylinder((200, 30, 30), (20, 20, 220))]
    if suffix == ".glb":
        parts.append(_textured_cylinder((240, 240, 240), (10, 10, 10), shift=1.0))
    path = tmp_path / f"scan{suffix}"
    (trimesh.Scene(parts) if len(parts) > 1 else parts[0]).export(path)
    scan = load_scan(path, check=False)
    assert scan.colors is not None and scan.colors.shape == (scan.point_count, 3)
    y, near = scan.points[:, 1], scan.points[:, 0] < 0.5
    for part, (top, bottom) in zip((near, ~near), (((200, 30, 30), (20, 20, 220)), ((240,) * 3, (10,) * 3))):
        if part.any():
            np.testing.assert_array_equal(np.unique(scan.colors[part & (y > 1.2)], axis=0), [top])
            np.testing.assert_array_equal(np.unique(scan.colors[part & (y < 0.4)], axis=0), [bottom])
    assert (~near).any() == (suffix == ".glb")


@pytest.mark.anny
def test_frame_warnings(default_body):
    from torch_diffavatar.body.synthetic import sample_surface

    verts, faces = default_body
    pts, _, _ = sample_surface(verts.numpy(), faces.numpy(), 20000, np.random.default_rng(0))
    assert check_scan_frame(pts) == []
    assert any("mm" in w for w in check_scan_frame(pts * 1000))
    assert any("--up" in w for w in check_scan_frame(pts[:, [1, 0, 2]]))  # lying along X
    assert any("upside down" in w for w in check_scan_frame(pts * np.array([1, -1, 1])))


def test_loader_warns_on_millimetres(tmp_path):
    path = tmp_path / "mm.ply"
    save_ply(path, _person() * 1000)
    with pytest.warns(ScanWarning, match="mm"):
        load_scan(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_scan(path, units="mm")


def test_floor_and_outlier_removal():
    rng = np.random.default_rng(1)
    pts = _person()
    floor = np.stack([rng.uniform(-1, 1, 3000), rng.normal(0, 0.002, 3000), rng.uniform(-1, 1, 3000)], 1)
    outliers = rng.uniform(-1, 1, (20, 3)) + np.array([0, 3.0, 0])
    from torch_diffavatar.scan import Scan

    scan = Scan(points=np.concatenate([pts + [0, 0.02, 0], floor, outliers]))
    cleaned, removed = remove_floor(scan)
    assert removed >= 2900 and cleaned.point_count >= len(pts) * 0.95
    assert remove_floor(Scan(points=pts))[1] == 0  # no floor: nothing removed
    cleaned, removed = remove_outliers(cleaned)
    assert cleaned.points[:, 1].max() < 1.8 and removed >= 20


@pytest.mark.parametrize(
    "content, message",
    [
        ("", "empty"),
        ("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n", "NaN"),
        ("not a mesh", "no geometry|no points"),
    ],
)
def test_bad_files_raise_scan_error(tmp_path, content, message):
    path = tmp_path / "bad.obj"
    path.write_text(content)
    with pytest.raises(ScanError, match=message):
        load_scan(path)


def test_missing_faces_and_bad_options(tmp_path):
    path = tmp_path / "cloud.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(ScanError, match="no faces"):
        load_scan(path, require_faces=True, check=False)
    with pytest.raises(ScanError, match="units"):
        load_scan(path, units="inch")
    with pytest.raises(ScanError, match="up axis"):
        load_scan(path, up="x")
    with pytest.raises(ScanError, match="not found"):
        load_scan(tmp_path / "missing.ply")
    with pytest.raises(ScanError, match="labels for a scan"):
        side = tmp_path / "l.txt"
        side.write_text("1\n0\n")
        load_scan(path, labels=side, check=False)


@pytest.mark.parametrize("binary", [True, False])
def test_a_big_ply_is_sampled_as_it_streams(tmp_path, monkeypatch, binary):
    """More points than asked: a seeded random subset read block by block, never the whole file (trimesh
    is not called), each point with its own colour and labels (the label here is the row number)."""
    import trimesh

    from torch_diffavatar import scan as scan_module

    pts = _person(n=20000)
    rows = np.arange(len(pts))
    colors = np.stack([rows % 251, rows % 241, rows % 239], 1).astype(np.uint8)
    path = tmp_path / "big.ply"
    save_ply(path, pts, colors=colors, int_properties={"label": rows}, binary=binary)
    (tmp_path / "rows.txt").write_text("\n".join(str(r) for r in rows))
    monkeypatch.setattr(scan_module, "READ_BLOCK", 7000)  # three blocks
    monkeypatch.setattr(trimesh, "load", lambda *a, **k: pytest.fail("read whole"))
    scan = load_scan(path, max_points=3000, labels=tmp_path / "rows.txt", check=False)
    assert scan.point_count == 3000 and scan.file_point_count == len(pts) and scan.faces is None
    assert np.all(np.diff(scan.labels) > 0)  # distinct rows, in file order
    np.testing.assert_allclose(scan.points, pts[scan.labels], atol=1e-6)
    np.testing.assert_array_equal(scan.colors, colors[scan.labels])
    again = load_scan(path, max_points=3000, check=False)
    np.testing.assert_array_equal(again.points, scan.points)  # seeded: the same subset every time


def test_a_ply_that_ends_before_its_points_is_refused(tmp_path):
    path = tmp_path / "short.ply"
    save_ply(path, _person(n=400), binary=True)
    data = path.read_bytes().replace(b"element vertex 400", b"element vertex 4000000000")
    path.write_bytes(data)
    with pytest.raises(ScanError, match="promises 4,000,000,000 points; the file ends before them"):
        load_scan(path, max_points=200)
