import torch

from torch_diffavatar.body.frames import anny_to_world, anny_to_world_rotation, world_to_anny


def test_rotation_is_proper_and_maps_axes():
    r = anny_to_world_rotation(torch.zeros(1, dtype=torch.float64))
    torch.testing.assert_close(r @ r.T, torch.eye(3, dtype=torch.float64))
    assert torch.det(r) > 0.999
    # Anny up (+Z) -> world up (+Y); Anny forward (−Y) -> world forward (+Z); left (+X) stays +X.
    up, fwd, left = anny_to_world(torch.tensor([[0.0, 0, 1], [0, -1, 0], [1, 0, 0]], dtype=torch.float64))
    torch.testing.assert_close(up, torch.tensor([0.0, 1, 0], dtype=torch.float64))
    torch.testing.assert_close(fwd, torch.tensor([0.0, 0, 1], dtype=torch.float64))
    torch.testing.assert_close(left, torch.tensor([1.0, 0, 0], dtype=torch.float64))


def test_round_trip():
    p = torch.randn(10, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(world_to_anny(anny_to_world(p)), p)


def test_default_body_in_world_frame(default_body):
    verts, faces = default_body
    assert verts[:, 1].min().abs() < 1e-9  # feet on the floor
    height = float(verts[:, 1].max())
    assert 1.55 < height < 1.70  # Anny at default phenotypes is 1.625 m tall
    # Facing +Z: the nose (highest-z point of the head) is in front of the back of the head.
    head = verts[verts[:, 1] > height - 0.25]
    assert head[:, 2].max() > 0.08 and head[:, 2].min() > -0.12
    # Outward orientation: positive signed volume.
    tri = verts[faces]
    vol = torch.einsum("fi,fi->f", tri[:, 0], torch.cross(tri[:, 1], tri[:, 2], dim=1)).sum() / 6
    assert vol > 0.03
