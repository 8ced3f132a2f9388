"""The differentiable drape: float64 gradchecks of both adjoints on small problems, the trajectory adjoint
against unrolled autograd, the two adjoints against each other, the C++ sparse solve against SciPy, and
input validation."""

from __future__ import annotations

import dataclasses
import math
import warnings

import pytest
import torch

from torch_diffavatar.objective import bounded_stretch, stretch_material
from torch_diffavatar.sim import collision
from torch_diffavatar.sim.adjoint import EquilibriumOptions, TrajectoryOptions
from torch_diffavatar.sim.adjoint.linsolve import residual, solve_op, solve_reference, solve_symmetric
from torch_diffavatar.sim.adjoint.trajectory import replay_frame
from torch_diffavatar.sim.differentiable import drape
from torch_diffavatar.sim.forward_drape import DrapeConfig
from torch_diffavatar.sim.material import ClothMaterial
from torch_diffavatar.sim.model import ClothModelBuilder
from torch_diffavatar.sim.solver import XPBDConfig, XPBDSolver
from torch_diffavatar.sim.testing import rectangle_garment, tube_garment

DT = torch.float64
KB, KUU = 1e-5, 60.0


def icosphere(radius: float, subdivisions: int = 1, center=(0.0, 0.0, 0.0)):
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    verts = torch.as_tensor(s.vertices, dtype=DT) + torch.tensor(center, dtype=DT)
    return verts, torch.as_tensor(s.faces, dtype=torch.int64)


def material(kb=KB, kuu=KUU, friction=0.0) -> ClothMaterial:
    return ClothMaterial(
        k_uu=kuu, k_vv=60.0, k_uv=20.0, bend_stiffness=kb, thickness=0.005, friction=friction, damping=2.0
    )


def sheet_on_sphere(n: int = 5, radius: float = 0.2, friction: float = 0.0):
    """A 0.6 m sheet pinned at its four corners at y = 0, sagging onto a sphere whose top is at −1 cm."""
    g = rectangle_garment(n, n, 0.6, 0.6, origin=(-0.3, 0.0, 0.3))
    pins = torch.tensor([0, n - 1, n * (n - 1), n * n - 1])
    model = ClothModelBuilder(material(friction=friction)).add_garment(g, pinned=pins).finalize(dtype=DT)
    # off-centre so no sheet vertex sits exactly above a sphere vertex (closest-triangle ties)
    verts, faces = icosphere(radius, 1, (0.013, -radius - 0.01, -0.007))
    return g, model, verts, faces


def pinned_tube(n: int = 5):
    """A two-panel tube (seams merged) hanging from its pinned waist row."""
    g = tube_garment(n, n, 0.3, 0.3, gap=0.06, y0=0.0)
    top = (n - 1) * n + torch.arange(n)
    pins = torch.cat((top, top + n * n))
    model = ClothModelBuilder(material()).add_garment(g, pinned=pins).finalize(dtype=DT)
    return g, model


def attached_tube(n: int = 5):
    """A two-panel tube held by its waist attachments (soft height constraints), with one waist vertex
    per panel pinned so that nothing slides or turns freely (the equilibrium adjoint needs a minimiser)."""
    g = tube_garment(n, n, 0.3, 0.3, gap=0.06, y0=0.0)
    mid = (n - 1) * n + n // 2
    pins = torch.tensor([mid, mid + n * n])
    model = ClothModelBuilder(material()).add_garment(g, pinned=pins).finalize(dtype=DT)
    return g, model


def short_config(frames: int = 3, substeps: int = 2, iterations: int = 2) -> DrapeConfig:
    """A fixed-length drape (for the trajectory adjoint's gradchecks)."""
    return DrapeConfig(
        xpbd=XPBDConfig(substeps=substeps, iterations=iterations),
        dt=1 / 30,
        max_steps=frames,
        min_steps=frames,
    )


def settle_config(max_steps: int = 120) -> DrapeConfig:
    return DrapeConfig(
        xpbd=XPBDConfig(substeps=4, iterations=2),
        dt=1 / 30,
        max_steps=max_steps,
        min_steps=20,
        speed_tol=1e-3,
    )


def log(x: float) -> float:
    return math.log(x)


# ----------------------------------------------------------------------------------------- helpers

TIGHT = EquilibriumOptions(newton_tol=1e-12, solve_tol=1e-12)
# "membrane": the fit's log stretch scale s (`objective.bounded_stretch`, `stretch_material`: k_uu, k_vv, k_uv
# times the bounded exp(s)), all three membrane stiffnesses at once
GROUPS = ("rest_uv", "bend", "stretch", "membrane", "body")
LOG_STRETCH = 0.4  # away from 0, where the bound's tanh is curved


@pytest.fixture(scope="module")
def sheet():
    return sheet_on_sphere()


@pytest.fixture(scope="module")
def tube():
    g, model = pinned_tube()
    return g, model, None, None


def _fn(scene, group, adjoint, config, options=None, stats=None):
    """(f, t0): f(t) drapes with input group ``group`` replaced by t; t0 its nominal value."""
    g, model, body, faces = scene
    nominal = {
        "rest_uv": g.vert_uv.to(DT),
        "bend": torch.tensor(math.log(KB), dtype=DT),
        "stretch": torch.tensor(KUU, dtype=DT),
        "membrane": torch.tensor(LOG_STRETCH, dtype=DT),
        "body": body,
        # the waist attachments' target heights, 2 cm below their placement (the fit's waist drop)
        "attach": model.attach_height - 0.02,
    }

    def f(t):
        v = dict(nominal, **{group: t})
        mat = material(kb=v["bend"].exp(), kuu=v["stretch"])
        if group == "membrane":
            mat = stretch_material(mat, mat.bend_stiffness, bounded_stretch(v["membrane"], 30.0))
        return drape(
            v["rest_uv"], model, v["body"], mat, body_faces=faces, config=config, adjoint=adjoint,
            options=options, stats=stats, attach_height=v["attach"] if group == "attach" else None,
        )  # fmt: skip

    return f, nominal[group].clone().requires_grad_(True)


def _gradcheck(f, t):
    # fast mode: checks vᵀ J u against central differences along random u, v (each input's full Jacobian
    # would need one backward per output entry)
    assert torch.autograd.gradcheck(f, (t,), eps=1e-6, atol=1e-7, rtol=1e-4, fast_mode=True)


# ------------------------------------------------------------------------------------- trajectory


@pytest.mark.parametrize("group", GROUPS)
def test_trajectory_gradcheck_sheet_on_sphere(sheet, group):
    stats = {}
    f, t = _fn(sheet, group, "trajectory", short_config(2), TrajectoryOptions(checkpoint_every=1), stats)
    _gradcheck(f, t)
    assert stats["max_contacts"] > 0  # the contacts take part
    x = f(t.detach()).detach()
    r = (x - sheet[2].mean(0)).norm(dim=-1)
    assert float(r.min()) < 0.2 + 0.006  # some vertex was pushed by the body (radius + thickness)


@pytest.mark.parametrize("group", ("rest_uv", "body"))
def test_trajectory_gradcheck_jacobi(sheet, group):
    """The Jacobi scheme replays through the reference kernels; their multipliers were updated in place
    after autograd had saved them, and every Jacobi backward failed."""
    cfg = DrapeConfig(
        xpbd=XPBDConfig(substeps=2, iterations=2, scheme="jacobi"), dt=1 / 30, max_steps=2, min_steps=2
    )
    stats = {}
    f, t = _fn(sheet, group, "trajectory", cfg, TrajectoryOptions(checkpoint_every=1), stats)
    _gradcheck(f, t)
    assert stats["max_contacts"] > 0


@pytest.mark.parametrize("group", ("rest_uv", "body"))
def test_trajectory_gradcheck_contacts_that_do_not_bounce(sheet, group):
    """`XPBDConfig.contact_bounce` < 1: the replay cuts the pushed contacts' outward speed as the op did."""
    cfg = DrapeConfig(
        xpbd=XPBDConfig(substeps=2, iterations=2, contact_bounce=0.0), dt=1 / 30, max_steps=2, min_steps=2
    )
    g, model, verts, faces = sheet
    # the sphere raised through the sheet's middle: the contacts are pushed out, upwards, from the start
    scene = (g, model, verts + verts.new_tensor([0.0, 0.02, 0.0]), faces)
    stats = {}
    f, t = _fn(scene, group, "trajectory", cfg, TrajectoryOptions(checkpoint_every=1), stats)
    _gradcheck(f, t)
    assert stats["max_contacts"] > 0
    bouncing = _fn(scene, group, "trajectory", short_config(2), TrajectoryOptions(checkpoint_every=1))[0]
    assert float((f(t.detach()) - bouncing(t.detach())).abs().max()) > 1e-6  # the cut acted


def test_trajectory_gradcheck_tube(tube):
    f, t = _fn(tube, "rest_uv", "trajectory", short_config(2), TrajectoryOptions(checkpoint_every=1))
    _gradcheck(f, t)


@pytest.fixture(scope="module")
def waist_tube():
    g, model = attached_tube()
    assert model.attach_vertices.numel() >= 4  # the waist rows minus the stitched corners and the pins
    return g, model, None, None


@pytest.mark.parametrize("group", ("attach", "rest_uv"))
def test_trajectory_gradcheck_attached_waist(waist_tube, group):
    f, t = _fn(waist_tube, group, "trajectory", short_config(3), TrajectoryOptions(checkpoint_every=2))
    _gradcheck(f, t)
    _assert_nonzero_gradient(f, t)


def _assert_nonzero_gradient(f, t):
    """The heights move the drape (a gradcheck of a zero Jacobian would pass too)."""
    (grad,) = torch.autograd.grad(f(t)[:, 1].sum(), t)
    assert float(grad.abs().max()) > 0.1


@pytest.mark.parametrize("group", ("attach", "rest_uv"))
def test_equilibrium_gradcheck_attached_waist(waist_tube, group):
    stats = {}
    f, t = _fn(waist_tube, group, "equilibrium", settle_config(40), TIGHT, stats)
    _gradcheck(f, t)
    _assert_nonzero_gradient(f, t)
    assert stats["newton_force_residual"] < 1e-10


def test_lowered_waist_hangs_lower(waist_tube):
    """The drape holds the attached waist at the given heights (the fit's waist-drop variable moves the
    garment, not only its gradient)."""
    g, model, _, _ = waist_tube
    uv = g.vert_uv.to(DT)
    cfg = settle_config(60)
    x0 = drape(uv, model, None, material(), config=cfg)
    x1 = drape(uv, model, None, material(), config=cfg, attach_height=model.attach_height - 0.03)
    free = ~model.vert_pinned[model.attach_vertices]
    dy = x1[model.attach_vertices[free], 1] - x0[model.attach_vertices[free], 1]
    assert float(dy.mean()) < -0.02  # the waist follows its targets (the pins hold it back near them)
    with pytest.raises(ValueError, match="attach_height must be a tensor of shape"):
        drape(uv, model, None, material(), config=cfg, attach_height=model.attach_height[:-1])


def test_trajectory_adjoint_matches_unrolled_autograd(sheet):
    g, model, body, faces = sheet
    cfg = short_config(4)
    weights = torch.sin(torch.arange(model.vert_count * 3, dtype=DT)).reshape(-1, 3)

    def leaves():
        return (
            g.vert_uv.to(DT).requires_grad_(True),
            body.clone().requires_grad_(True),
            torch.tensor(math.log(KB), dtype=DT, requires_grad=True),
        )

    uv, bv, lkb = leaves()
    x = drape(uv, model, bv, material(kb=lkb.exp()), body_faces=faces, config=cfg, adjoint="trajectory",
              options=TrajectoryOptions(checkpoint_every=3))  # fmt: skip
    (x * weights).sum().backward()
    uv2, bv2, lkb2 = leaves()
    mat = material(kb=lkb2.exp())
    rest = model.rest_data(uv2, mat)
    xs, vs = model.vert_init_pos.clone(), torch.zeros_like(model.vert_init_pos)
    band = 0.005 + cfg.xpbd.collision_band
    for _ in range(cfg.max_steps):
        c = collision.detect_contacts(xs, bv2, faces, band)
        xs, vs = replay_frame(
            model, cfg.xpbd, xs, vs, rest, cfg.dt, contacts=c if c.count else None,
            body_verts=bv2, body_faces=faces, velocity_scale=cfg.drape_velocity_scale,
        )  # fmt: skip
    torch.testing.assert_close(x.detach(), xs.detach(), rtol=0, atol=1e-12)
    (xs * weights).sum().backward()
    for a, b in ((uv, uv2), (bv, bv2), (lkb, lkb2)):
        assert float(b.grad.abs().max()) > 0
        torch.testing.assert_close(a.grad, b.grad, rtol=1e-9, atol=1e-12)


def test_replay_frame_matches_solver_step(sheet):
    """The differentiable replay is the same maths as `XPBDSolver.step` (guards against drift)."""
    g, model, body, faces = sheet
    rest = model.rest_data(g.vert_uv.to(DT))
    for scheme in ("gauss_seidel", "jacobi"):
        cfg = XPBDConfig(substeps=3, iterations=2, scheme=scheme)  # C++ kernels vs the reference replay
        state = model.initial_state()
        for _ in range(4):
            c = collision.detect_contacts(state.x, body, faces, 0.005 + cfg.collision_band)
            new = XPBDSolver(model, cfg).step(state, rest, 1 / 30, body_verts=body, body_faces=faces)
            x, v = replay_frame(model, cfg, state.x, state.v, rest, 1 / 30, contacts=c if c.count else None,
                                body_verts=body, body_faces=faces)  # fmt: skip
            torch.testing.assert_close(x, new.x, rtol=0, atol=1e-12)
            torch.testing.assert_close(v, new.v, rtol=0, atol=1e-10)
            state = new


def test_return_trajectory_frames_are_differentiable(sheet):
    g, model, body, faces = sheet
    uv = g.vert_uv.to(DT).requires_grad_(True)
    x, frames = drape(
        uv, model, body, material(), body_faces=faces, config=short_config(3), adjoint="trajectory",
        options=TrajectoryOptions(return_trajectory=True),
    )  # fmt: skip
    assert frames.shape == (4, model.vert_count, 3)
    torch.testing.assert_close(frames[-1], x)
    (grad,) = torch.autograd.grad(frames[1:].sum(), uv)
    assert float(grad.abs().max()) > 0


# ------------------------------------------------------------------------------------ equilibrium


@pytest.mark.parametrize("group", GROUPS)
def test_equilibrium_gradcheck_sheet_on_sphere(sheet, group):
    stats = {}
    f, t = _fn(sheet, group, "equilibrium", settle_config(15), TIGHT, stats)
    _gradcheck(f, t)
    assert stats["active_contacts"] > 0
    assert stats["newton_force_residual"] < 1e-12
    assert stats["adjoint_solve_residual"] < 1e-10


@pytest.mark.parametrize("group", ("rest_uv", "bend", "membrane"))
def test_equilibrium_gradcheck_tube(tube, group):
    f, t = _fn(tube, group, "equilibrium", settle_config(15), TIGHT)
    _gradcheck(f, t)


# ---------------------------------------------------------------------------------- sparse solves


def _laplacian_system(n=60, shift=0.5, seed=0):
    gen = torch.Generator().manual_seed(seed)
    a = torch.zeros(n, n, dtype=DT)
    i = torch.arange(n - 1)
    a[i, i + 1] = a[i + 1, i] = -1.0
    a += torch.diag(2.0 + shift + torch.rand(n, generator=gen, dtype=DT))
    crow = torch.zeros(n + 1, dtype=torch.int64)
    nz = a != 0
    crow[1:] = torch.cumsum(nz.sum(1), 0)
    col = nz.nonzero()[:, 1]
    return a, crow, col, a[nz], torch.randn(n, generator=gen, dtype=DT)


@pytest.mark.parametrize("shift", [0.5, -1.7])  # SPD, then symmetric indefinite
def test_sparse_solve_matches_dense(shift):
    a, crow, col, val, b = _laplacian_system(shift=shift)
    exact = torch.linalg.solve(a, b)
    for method in ("auto", "minres", "direct") + (("cg",) if shift > 0 else ()):
        x, info = solve_symmetric(crow, col, val, b, method=method, tol=1e-12)
        assert info.residual < 1e-9, (method, info)
        torch.testing.assert_close(x, exact, rtol=1e-7, atol=1e-9)
    if shift < 0:
        _, info = solve_symmetric(crow, col, val, b, method="auto", tol=1e-12)
        assert info.indefinite and info.method != "cg"


@pytest.mark.skipif(solve_op() is None, reason="C++ extension not built")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cpp_sparse_solve_matches_scipy(dtype):
    a, crow, col, val, b = _laplacian_system(shift=0.5)
    op = solve_op()
    for method, name in ((0, "cg"), (1, "minres")):
        x, info = op(crow, col, val.to(dtype), b.to(dtype), method, 1e-10, 500)
        ref, _, _ = solve_reference(crow, col, val, b, name, 1e-12, 500)
        assert x.dtype == dtype and int(info[2]) == 0
        tol = 1e-9 if dtype == torch.float64 else 1e-4
        torch.testing.assert_close(x.double(), ref, rtol=tol, atol=tol)
        assert abs(float(info[1]) - residual(crow, col, val.to(dtype), x, b.to(dtype))) < 1e-6
    a2, crow2, col2, val2, b2 = _laplacian_system(shift=-1.7)
    _, info = op(crow2, col2, val2, b2, 0, 1e-10, 500)
    assert int(info[2]) == 2 and float(info[3]) < 0  # CG reports the negative curvature
    torch.library.opcheck(op.default, (crow, col, val, b, 1, 1e-10, 500))


def _spring_chain(n=300, spread=6.0, seed=0):
    """A stiff 1D spring chain (springs 1 to 10^spread N/m, light masses) like a cloth Hessian: condition
    number ~1e8 at spread 6, and ‖H‖ ‖x‖ ≫ ‖b‖."""
    gen = torch.Generator().manual_seed(seed)
    k = 10 ** (spread * torch.rand(n + 1, generator=gen, dtype=DT))
    i = torch.arange(n)
    a = torch.zeros(n, n, dtype=DT)
    a[i, i] = k[:-1] + k[1:] + 1e-2
    a[i[:-1], i[:-1] + 1] = a[i[:-1] + 1, i[:-1]] = -k[1:-1]
    nz = a != 0
    crow = torch.zeros(n + 1, dtype=torch.int64)
    crow[1:] = torch.cumsum(nz.sum(1), 0)
    return a, crow, nz.nonzero()[:, 1], a[nz], torch.randn(n, generator=gen, dtype=DT)


@pytest.mark.parametrize("method", ["auto", "minres"])
def test_converged_solve_of_a_stiff_system_does_not_warn(method):
    """Every equilibrium backward warned "inexact sparse solve … 1.15e-08 > 1e-08": converged solves end
    with a true relative residual around their target (CG's recursive residual drifts; MINRES measures
    it in its preconditioner's norm), and the check compared it with that very target."""
    from torch_diffavatar.sim.adjoint.linsolve import check_solve

    a, crow, col, val, b = _spring_chain()
    x, info = solve_symmetric(crow, col, val, b, method=method, tol=1e-8)
    exact = torch.linalg.solve(a, b)
    # around its target: above it in some runs (what used to warn), below in others (the solve's dot
    # products are OpenMP reductions, summed in an unspecified order across threads)
    assert info.converged and info.residual > 3e-9
    assert float((x - exact).norm() / exact.norm()) < 1e-7  # the answer is good
    assert info.backward_error < 1e-10
    for dtype in (torch.float64, torch.float32):
        for rel in (info.residual, 1.15e-8):  # this run's, and the one that used to warn
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                check_solve(dataclasses.replace(info, residual=rel), 1e-8, "test", dtype)


@pytest.mark.parametrize(
    "method, spread, max_iter", [("cg", 3.0, 650), ("minres", 3.0, 600), ("minres", 4.0, 1200)]
)
def test_unconverged_solve_warns(method, spread, max_iter):
    """Solves cut short by the iteration cap (forward errors 3e-5 to 2e-4) still warn. Their relative
    residuals are no worse than the converged MINRES solve's above, and the last one's backward error is
    7e-10: the convergence flag tells them apart."""
    from torch_diffavatar.sim.adjoint.linsolve import check_solve

    a, crow, col, val, b = _spring_chain(spread=spread)
    x, info = solve_symmetric(crow, col, val, b, method=method, tol=1e-8, max_iter=max_iter)
    exact = torch.linalg.solve(a, b)
    assert not info.converged and info.residual < 1e-3
    assert float((x - exact).norm() / exact.norm()) > 1e-5
    with pytest.warns(RuntimeWarning, match="did not converge"):
        check_solve(info, 1e-8, "test")


@pytest.mark.parametrize(
    "noise, warns64, warns32", [(1e-13, False, False), (1e-7, True, False), (1e-6, True, True)]
)
def test_backward_error_guards_a_converged_but_inaccurate_answer(noise, warns64, warns32):
    """An answer off by a relative ``noise`` (backward errors 2e-14, 2e-8, 2e-7): beyond ``tol`` it warns,
    unless the answer is used in float32, whose rounding (1.2e-7) would hide the error anyway."""
    from torch_diffavatar.sim.adjoint.linsolve import SolveInfo, backward_error, check_solve, residual

    a, crow, col, val, b = _spring_chain(spread=2.0)
    x = torch.linalg.solve(a, b) * (1 + noise * torch.sin(torch.arange(b.shape[0], dtype=DT)))
    res, omega = residual(crow, col, val, x, b), backward_error(crow, col, val, x, b)
    info = SolveInfo("direct", 0, res, False, ("direct",), True, omega)
    for dtype, warns in ((torch.float64, warns64), (torch.float32, warns32)):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            check_solve(info, 1e-8, "test", dtype)
        assert [str(w.message).count("backward error") for w in caught] == ([1] if warns else []), (
            dtype,
            omega,
        )


def test_singular_adjoint_solve_raises():
    from torch_diffavatar.errors import SimulationError
    from torch_diffavatar.sim.adjoint.linsolve import check_solve

    a, crow, col, val, b = _laplacian_system()
    val = torch.where(col == 3, torch.zeros_like(val), val)  # column 3 zero: singular
    row3 = torch.arange(crow.shape[0] - 1).repeat_interleave(crow[1:] - crow[:-1]) == 3
    val = torch.where(row3, torch.zeros_like(val), val)
    b[3] = 1.0  # inconsistent right-hand side
    _, info = solve_symmetric(crow, col, val, b, method="auto", tol=1e-12)
    with pytest.raises(SimulationError, match="residual"):
        check_solve(info, 1e-10, "test")


# ------------------------------------------------------------------------------------- validation


def test_drape_validates_inputs(sheet):
    g, model, body, faces = sheet
    uv = g.vert_uv.to(DT)
    with pytest.raises(ValueError, match="trajectory"):
        drape(uv, model, body, body_faces=faces, adjoint="newton")
    with pytest.raises(ValueError, match="rest_uv must have shape"):
        drape(uv[:-1], model, body, body_faces=faces)
    with pytest.raises(ValueError, match="both body_verts and body_faces"):
        drape(uv, model, body)
    with pytest.raises(ValueError, match="float64"):
        drape(uv.float(), model, body, body_faces=faces)
    with pytest.raises(ValueError, match="damping"):
        drape(uv, model, body, ClothMaterial(damping=torch.tensor(1.0, requires_grad=True)), body_faces=faces)
    with pytest.raises(ValueError, match="TrajectoryOptions"):
        drape(uv, model, body, body_faces=faces, adjoint="trajectory", options=EquilibriumOptions())
