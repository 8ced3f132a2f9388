import pytest
import torch

from torch_diffavatar.body.model import POSE_BONES, BodyModel
from torch_diffavatar.body.priors import joint_limit_penalty, pose_prior, self_penetration_penalty

pytestmark = pytest.mark.anny


@pytest.fixture(scope="module")
def body(anny_model):
    return BodyModel(anny_model=anny_model, dtype=torch.float32)


def test_outputs_in_world_frame(body, anny_model):
    out = body()
    assert out.vertices.shape == (1, anny_model.template_vertices.shape[0], 3)
    assert out.faces.shape == (26692, 3) and out.faces.dtype == torch.int64
    assert out.joints.shape == (1, 104, 3)
    v = out.vertices[0].detach()
    assert abs(float(v[:, 1].max() - v[:, 1].min()) - 1.625) < 0.01  # default Anny is 1.625 m tall, Y up
    head = v[v[:, 1] > v[:, 1].max() - 0.25]
    assert head[:, 2].max() > 0.08  # the face points to +Z
    assert abs(float(body.standing_height()[0]) - 1.625) < 0.01
    # the shared float64 fixture was not cast in place
    assert anny_model.template_vertices.dtype == torch.float64


def test_placement_is_applied_in_world_frame(body):
    base = body().vertices
    t = torch.tensor([[0.1, -0.2, 0.3]])
    torch.testing.assert_close(body(translation=t).vertices, base + t[:, None])
    rot = torch.tensor([[0.0, torch.pi / 2, 0.0]])  # 90° about world +Y: +Z -> +X
    turned = body(global_orient=rot).vertices
    torch.testing.assert_close(turned[..., 0], base[..., 2], atol=1e-5, rtol=0)
    torch.testing.assert_close(turned[..., 1], base[..., 1], atol=1e-5, rtol=0)
    scaled = body(scale=torch.tensor([2.0])).vertices
    torch.testing.assert_close(scaled, 2 * base)


def test_batch_and_dtype(anny_model):
    b = BodyModel(anny_model=anny_model, batch_size=2)  # keeps the fixture's float64
    assert b.pose.dtype == torch.float64
    b.set_phenotypes(torch.tensor([[0.5] * 6, [0.5, 0.5, 0.5, 0.5, 0.9, 0.5]], dtype=torch.float64))
    h = b.standing_height()
    assert h.shape == (2,) and h[1] > h[0] + 0.2
    pose = torch.zeros(2, len(POSE_BONES), 3, dtype=torch.float64)
    pose[1, POSE_BONES.index("lowerleg01.L"), 0] = 1.0  # bend the left knee of the second body
    out = b(pose=pose)
    assert out.vertices.shape[0] == 2 and out.joints.shape[0] == 2
    foot = anny_model.bone_labels.index("foot.L")
    assert out.joints[1, foot, 2] < out.joints[0, foot, 2] - 0.2  # the foot swings backward (−Z)


def test_phenotypes_stay_in_range_and_round_trip(body):
    with torch.no_grad():
        body.phenotype_logits.fill_(50.0)
    assert float(body.phenotypes.max()) <= 1.0
    body.set_phenotypes({"height": 0.3, "weight": 0.7})
    params = body.parameters_dict()
    i = body.phenotype_labels.index("height")
    assert abs(params["phenotypes"][0][i] - 0.3) < 1e-5
    other = BodyModel(anny_model=body.anny)
    other.load_parameters_dict(params)
    torch.testing.assert_close(other().vertices, body().vertices)
    body.set_phenotypes(torch.full((1, 6), 0.5))
    with pytest.raises(ValueError, match="unknown phenotypes"):
        body.set_phenotypes({"hight": 0.5})


def test_gradients_reach_every_parameter(anny_model):
    b = BodyModel(anny_model=anny_model, dtype=torch.float32)
    with torch.no_grad():
        b.pose.normal_(0.0, 0.05)
    out = b()
    (out.vertices.square().sum() + out.joints.sum()).backward()
    for name in ("phenotype_logits", "pose", "global_orient", "translation", "log_scale"):
        g = getattr(b, name).grad
        assert g is not None and torch.isfinite(g).all() and g.abs().sum() > 0, name


def test_priors_values_and_gradcheck():
    lo = torch.tensor([[-0.5, -0.5, -0.5], [-0.1, -0.2, -0.2]], dtype=torch.float64)
    hi = -lo
    inside = torch.zeros(1, 2, 3, dtype=torch.float64)
    assert joint_limit_penalty(inside, lo, hi).item() == 0
    pose = torch.tensor([[[0.7, 0.0, 0.0], [0.0, -0.3, 0.1]]], dtype=torch.float64, requires_grad=True)
    torch.testing.assert_close(
        joint_limit_penalty(pose, lo, hi), torch.tensor([0.2**2 + 0.1**2], dtype=torch.float64)
    )
    assert torch.autograd.gradcheck(lambda p: joint_limit_penalty(p, lo, hi), (pose,))
    assert torch.autograd.gradcheck(lambda p: pose_prior(p, torch.tensor([1.0, 2.0], dtype=p.dtype)), (pose,))
    verts = torch.tensor([[[0, 0, 0], [0.004, 0, 0], [1, 0, 0], [0, 0.03, 0]]], dtype=torch.float64)
    verts.requires_grad_()
    pairs = [(torch.tensor([0]), torch.tensor([1, 2, 3]))]
    pen = self_penetration_penalty(verts, pairs, margin=0.01)
    torch.testing.assert_close(pen, torch.tensor([0.006**2], dtype=torch.float64))
    assert torch.autograd.gradcheck(lambda v: self_penetration_penalty(v, pairs, 0.01), (verts,))


def test_bad_constructor_arguments(anny_model):
    with pytest.raises(ValueError, match="pose_bones"):
        BodyModel(anny_model=anny_model, pose_bones=("spine05", "tail"))
    with pytest.raises(ValueError, match="local_changes"):
        BodyModel(anny_model=anny_model, local_changes=True)


def test_upper_arm_angles_read_the_arms_against_the_torso(anny_model):
    """The A-pose's upper arms stand 42° out; lowered 0.4 rad toward the torso, 19°; a turned and bent
    body reads the same as an upright one."""
    import math

    from torch_diffavatar.body.model import pose_from_bones

    body = BodyModel(anny_model=anny_model, dtype=torch.float64)
    a_pose = body.upper_arm_angles(body().joints[0])
    assert a_pose["left"] == pytest.approx(41.7, abs=1.0) and a_pose["right"] == pytest.approx(a_pose["left"])
    low = pose_from_bones({"upperarm01.L": [0, 0.4, 0], "upperarm01.R": [0, -0.4, 0]}, "test")[None]
    with torch.no_grad():
        body.pose.copy_(low)
    lowered = body.upper_arm_angles(body().joints[0])
    for side in ("left", "right"):
        assert lowered[side] == pytest.approx(a_pose[side] - math.degrees(0.4), abs=1.0)
    with torch.no_grad():  # the whole body turned 90° and leaning 0.3 rad forward
        turned = body(global_orient=torch.tensor([[0.0, math.pi / 2, 0.0]], dtype=torch.float64))
        leaning = body(global_orient=torch.tensor([[0.3, 0.0, 0.0]], dtype=torch.float64))
    for out in (turned, leaning):
        for side, angle in body.upper_arm_angles(out.joints[0]).items():
            assert angle == pytest.approx(lowered[side], abs=1e-6)


def test_waist_height_lies_between_hips_and_ribs(anny_model):
    """`waist_height` (the ``spine02`` joint) sits above the hips part and below the shoulders, and
    moves with the body."""
    from torch_diffavatar.body.parts import PART_NAMES, vertex_parts

    body = BodyModel(anny_model=anny_model, dtype=torch.float64)
    with torch.no_grad():
        out = body()
        raised = body(translation=torch.tensor([[0.0, 0.1, 0.0]], dtype=torch.float64))
    verts, labels = out.vertices[0], anny_model.bone_labels
    hips = verts[vertex_parts(anny_model) == PART_NAMES.index("hips"), 1]
    waist = body.waist_height(out.joints[0])
    assert float(hips.max()) + 0.1 < waist < float(out.joints[0, labels.index("upperarm01.L"), 1]) - 0.15
    assert body.waist_height(raised.joints[0]) == pytest.approx(waist + 0.1, abs=1e-9)


def test_stand_on_floor_puts_each_body_s_feet_on_y_0(anny_model):
    b = BodyModel(anny_model=anny_model, batch_size=2)
    b.set_phenotypes(torch.tensor([[0.5] * 6, [0.5, 0.5, 0.5, 0.5, 0.9, 0.5]], dtype=torch.float64))
    before = b().vertices.detach()
    assert float(before[..., 1].min()) < -0.8  # zero translation: the pelvis at the origin
    assert b.stand_on_floor() is b
    after = b().vertices.detach()
    torch.testing.assert_close(
        after[..., 1].amin(dim=1), torch.zeros(2, dtype=torch.float64), atol=1e-12, rtol=0
    )
    shift = (after - before)[..., 1]  # a vertical shift of each whole body, nothing else
    torch.testing.assert_close(shift, shift[:, :1].expand_as(shift), atol=1e-12, rtol=0)
    torch.testing.assert_close((after - before)[..., [0, 2]], torch.zeros_like(after[..., [0, 2]]))


def test_an_empty_anny_cache_variable_takes_the_default(monkeypatch):
    """``ANNY_CACHE_DIR`` set but empty: Anny would put its ~800 MB cache into the working directory (a
    source checkout, where `git add` takes it); `load_anny` takes Anny's default instead, and leaves a set
    directory alone."""
    from anny import paths

    from torch_diffavatar.body.anny_model import _default_cache_for_an_empty_variable

    before = paths.get_anny_cache_path()
    try:
        monkeypatch.setenv("ANNY_CACHE_DIR", "")
        paths.set_anny_cache_path("")  # what Anny makes of the empty variable at import
        _default_cache_for_an_empty_variable()
        assert paths.get_anny_cache_path() == paths.DEFAULT_CACHE_PATH
        monkeypatch.setenv("ANNY_CACHE_DIR", "/tmp/anny-cache-elsewhere")
        paths.set_anny_cache_path("/tmp/anny-cache-elsewhere")
        _default_cache_for_an_empty_variable()
        assert str(paths.get_anny_cache_path()) == "/tmp/anny-cache-elsewhere"
    finally:
        paths.set_anny_cache_path(before)
