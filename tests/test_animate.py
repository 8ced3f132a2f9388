"""`diffavatar animate`: motions, the moving-body solver (no tunnelling) and a keyframe animation of a
small dress on the Anny body through the asset-folder path."""

from __future__ import annotations

import json
import math

import pytest
import torch
from helpers_fit import write_assets_on_default_body

from torch_diffavatar.animate import animate
from torch_diffavatar.assets import load_assets
from torch_diffavatar.body.model import POSE_BONES
from torch_diffavatar.errors import InputError
from torch_diffavatar.motion import Keyframe, KeyframeMotion, WalkCycle, keyframes_from_dict, load_motion
from torch_diffavatar.sim.forward_drape import DrapeConfig, drape_to_equilibrium, sew
from torch_diffavatar.sim.model import ClothModelBuilder
from torch_diffavatar.sim.solver import XPBDSolver
from torch_diffavatar.sim.testing import rectangle_garment

LEG = POSE_BONES.index("upperleg01.L")


def test_keyframes_hold_at_keys_and_ease_between():
    motion = KeyframeMotion(
        [Keyframe(0.0), Keyframe(1.0, {"upperleg01.L": (-0.6, 0.0, 0.0)}, (0.0, 0.0, 0.1)), Keyframe(2.0)]
    )
    pose, transl = motion.offsets(torch.tensor([-1.0, 0.0, 0.25, 0.5, 1.0, 1.5, 3.0]))
    angle = pose[:, LEG, 0]
    torch.testing.assert_close(angle[[0, 1, 4, 6]], torch.tensor([0.0, 0.0, -0.6, 0.0], dtype=torch.float64))
    assert float(angle[3]) == pytest.approx(-0.3)  # smoothstep(0.5) = 0.5
    assert float(angle[2]) == pytest.approx(-0.6 * 0.15625)  # smoothstep(0.25) = 0.15625: eased start
    assert float(transl[4, 2]) == pytest.approx(0.1) and float(transl[5, 2]) == pytest.approx(0.05)
    assert pose[:, [i for i in range(len(POSE_BONES)) if i != LEG]].abs().max() == 0


def test_keyframe_json_and_errors(tmp_path):
    path = tmp_path / "keys.json"
    data = {
        "ease": "linear",
        "keyframes": [{"time_s": 0, "pose": {}}, {"time_s": 2, "pose": {"head": [0, 0, 0.4]}}],
    }
    path.write_text(json.dumps(data))
    motion = load_motion(path)
    assert motion.duration == 2.0
    pose, _ = motion.offsets(torch.tensor([0.5]))
    assert float(pose[0, POSE_BONES.index("head"), 2]) == pytest.approx(0.1)  # linear
    with pytest.raises(InputError, match="unknown bones"):
        keyframes_from_dict({"keyframes": [{"time_s": 0, "pose": {"tail": [0, 0, 1]}}]})
    with pytest.raises(InputError, match="increasing"):
        keyframes_from_dict({"keyframes": [{"time_s": 1}, {"time_s": 1}]})
    with pytest.raises(InputError, match="walk"):
        load_motion(tmp_path / "missing.json")


def test_walk_starts_at_rest_and_alternates_legs():
    walk = WalkCycle(4.0, period=1.2)
    pose, transl = walk.offsets(torch.tensor([0.0, 0.9, 1.5]))
    assert pose[0].abs().max() == 0 and transl.abs().max() == 0  # amplitude ramps in from rest
    left, right = pose[1:, LEG, 0], pose[1:, POSE_BONES.index("upperleg01.R"), 0]
    torch.testing.assert_close(left, -right)
    assert float(left[0]) > 0.2 and float(left[1]) < -0.2  # back at 0.9 s (3/4 stride), forward at 1.5 s


def _plane(y: float, half: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Two triangles of a horizontal square at height y [m], normal +Y."""
    v = torch.tensor([[-half, y, -half], [half, y, -half], [half, y, half], [-half, y, half]])
    return v, torch.tensor([[0, 2, 1], [0, 3, 2]])


def test_moving_body_does_not_tunnel_where_a_static_step_does():
    """A floor rising 5 cm per frame (3 m/s) under a sheet lying 1 cm above it."""
    sheet = rectangle_garment(7, 7, 0.3, 0.3, origin=(-0.15, 0.01, 0.15))
    model = ClothModelBuilder().add_garment(sheet).finalize(dtype=torch.float32)
    rest = model.rest_data(sheet.vert_uv.float())
    faces = _plane(0.0)[1]
    dt, rise = 1 / 60, 0.05
    solver = XPBDSolver(model)
    s_mov = s_sta = model.initial_state()
    for k in range(4):
        start, end = _plane(k * rise)[0], _plane((k + 1) * rise)[0]
        s_mov = solver.step(s_mov, rest, dt, body_verts=start, body_faces=faces, body_verts_end=end)
        s_sta = solver.step(s_sta, rest, dt, body_verts=end, body_faces=faces)
        floor = (k + 1) * rise
        assert float(s_mov.x[:, 1].min()) > floor, k  # carried on top of the floor
    assert float(s_sta.x[:, 1].max()) < floor  # the per-frame static collider let it through
    assert float(s_mov.v[:, 1].mean()) == pytest.approx(rise / dt, rel=0.3)  # moves with the floor


@pytest.fixture(scope="module")
def small_dress_assets(anny_model, default_body, tmp_path_factory):
    """A coarse dress (6 cm spacing) sewn on the default body and briefly draped, as an asset folder."""
    from torch_diffavatar.pattern import load_template, mesh_pattern
    from torch_diffavatar.sim.placement import place_garment

    bv, bf = default_body
    pattern = load_template("dress")
    garment = place_garment(mesh_pattern(pattern, spacing=0.06), bv, bf)
    bv32 = bv.float()
    sew_model = ClothModelBuilder().add_garment(garment, merge_seams=False).finalize(dtype=torch.float32)
    sewn = sew(sew_model, garment.vert_uv.float(), body_verts=bv32, body_faces=bf)
    model = ClothModelBuilder().add_garment(garment).finalize(dtype=torch.float32)
    drape = drape_to_equilibrium(
        model,
        garment.vert_uv.float(),
        body_verts=bv32,
        body_faces=bf,
        state=model.initial_state(model.sim_positions(sewn.x)),
        config=DrapeConfig(max_steps=30),
    )
    return write_assets_on_default_body(
        tmp_path_factory.mktemp("dress_assets"), anny_model, default_body, pattern=pattern, garment=garment,
        rest_uv=garment.vert_uv, draped_x=drape.x, material=model.material,
    )  # fmt: skip


def test_keyframe_leg_kick_moves_the_skirt_without_penetration(small_dress_assets, anny_model, tmp_path):
    assets = load_assets(small_dress_assets)
    kick = KeyframeMotion([Keyframe(0.0), Keyframe(0.4, {"upperleg01.L": (-0.7, 0.0, 0.0)}), Keyframe(0.7)])
    summary = animate(assets, kick, tmp_path, fps=30, sim_fps=60, anny_model=anny_model, gif_size=64)
    assert summary["finite"] and summary["sim_frames"] == 42 and summary["output_frames"] == 22
    assert all(p < 0.01 for p in summary["per_frame"]["penetration_fraction"])
    # no blow-up (the solver raises at 50 m/s); single coarse-mesh vertices caught by the thigh spike
    # for a frame, the garment as a whole moves at the speed of the leg (≈ 1–3 m/s)
    speeds = sorted(summary["per_frame"]["max_speed_m_s"])
    assert speeds[-1] < 20.0 and speeds[len(speeds) // 2] < 5.0
    frames = sorted((tmp_path / "frames").glob("garment_*.obj"))
    assert len(frames) == 22 and len(list((tmp_path / "frames").glob("body_*.ply"))) == 22
    assert (tmp_path / "animation.gif").stat().st_size > 0
    # at the top of the kick (0.4 s = output frame 12) the skirt front is pushed forward (+Z) by the thigh
    from torch_diffavatar.mesh_io import read_obj

    z0 = read_obj(frames[0]).verts[:, 2].max()
    z_kick = read_obj(frames[12]).verts[:, 2].max()
    assert float(z_kick - z0) > 0.03
    uv = read_obj(frames[12]).uv
    torch.testing.assert_close(uv, assets.rest_uv, atol=1e-8, rtol=0)  # frames keep the pattern as UVs
    assert math.isclose(summary["duration_s"], 0.7)


def test_the_fit_report_walks_the_assets(small_dress_assets, anny_model, monkeypatch):
    """`fit_report.animation_warnings`: assets that walk say nothing; assets that blow up in the walk (the
    captured trousers 343's fits did within 0.5 s) get a warning in report.json; 0 s checks nothing."""
    from torch_diffavatar import animate as animate_module
    from torch_diffavatar.errors import SimulationError
    from torch_diffavatar.fit_report import animation_warnings
    from torch_diffavatar.sim import tangles

    assert animation_warnings(small_dress_assets, 0.25, anny_model) == []

    def blow_up(*args, **kwargs):
        raise SimulationError("simulation blew up: Green strain 3.48 > max_strain 3")

    monkeypatch.setattr(animate_module, "animate", blow_up)
    (said,) = animation_warnings(small_dress_assets, 0.5, anny_model)
    assert said.startswith("the assets blew up in a 0.5 s walk (simulation blew up: Green strain 3.48")
    assert said.endswith("the fit probably went wrong (look at before_after.png)")  # no edge through the body
    assert animation_warnings(small_dress_assets, 0.0, anny_model) == []

    # a drape with edges through the body (`sim.tangles`) is said to be the cause, with where they are
    assets = load_assets(small_dress_assets)
    lowest = torch.topk(-assets.draped_x[:, 1], 2).indices.sort().values  # the hem's two lowest vertices
    monkeypatch.setattr(tangles, "edges_through_body", lambda *args: lowest[None])
    (said,) = animation_warnings(small_dress_assets, 0.5, anny_model)
    hem = round(float(assets.draped_x[lowest, 1].mean() - assets.body_verts[:, 1].min()) * 100)
    assert f"simulation-ready as it is: 1 edge(s) of its drape pass through the body, {hem} cm above" in said
    assert "fit probably went wrong" not in said


def test_asset_strains_finds_the_drapes_most_strained_triangle(small_dress_assets, tmp_path, capsys):
    """`scripts/asset_strains.py`: the drape's largest Green strain against the rest pattern, the same the
    solver's blow-up test measures; the rest pattern halved shows there (E = 1.5), a missing folder
    is one line on stderr and exit code 2 while the others are still measured."""
    import shutil

    from helpers_scripts import load_script

    script = load_script("asset_strains")
    before = script.asset_strains(small_dress_assets)
    assert before["max_strain"] < 0.5 and before["over_max_strain"] == 0
    shrunk = tmp_path / "shrunk"
    shutil.copytree(small_dress_assets, shrunk)
    lines = (shrunk / "rest.obj").read_text().splitlines()
    vt = [i for i, line in enumerate(lines) if line.startswith("vt ")]
    for i in vt:  # every panel's rest coordinates halved: the drape is stretched ×2 (E = 1.5)
        u, v = (float(c) for c in lines[i].split()[1:3])
        lines[i] = f"vt {u / 2:.9g} {v / 2:.9g}"
    (shrunk / "rest.obj").write_text("\n".join(lines) + "\n")
    after = script.asset_strains(shrunk)
    assert after["max_strain"] > 1.2 and after["over_1"] > after["triangles"] // 2
    assert script.main([str(tmp_path / "missing"), str(small_dress_assets), "--json"]) == 2
    out, err = capsys.readouterr()
    assert "no such asset folder" in err
    assert json.loads(out.splitlines()[-1])["triangles"] == before["triangles"]
