"""The conversion between Newton's cloth parameters and ours (`sim_newton`), and the clear error when
Newton is missing. Needs neither Newton nor Anny."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch

from torch_diffavatar import sim_newton as sn
from torch_diffavatar.cli import main
from torch_diffavatar.errors import InputError
from torch_diffavatar.geometry import triangle_green_strain
from torch_diffavatar.sim.constraints import membrane_stiffness
from torch_diffavatar.sim.material import ClothMaterial


def _newton_membrane_density(f: np.ndarray, mu: float, lam: float) -> float:
    """Newton's stable Neo-Hookean membrane energy per rest area [J/m²] of F (3, 2)
    (``evaluate_neo_hookean_membrane_force_hessian`` in newton's VBD kernels), less its value at rest
    (``μ²/(2λ')``: the stable Neo-Hookean energy is not 0 at F = I, its stress is)."""
    lam_nh = lam + mu
    alpha = 1.0 + mu / lam_nh
    j = np.linalg.norm(np.cross(f[:, 0], f[:, 1]))
    rest = 0.5 * lam_nh * (1.0 - alpha) ** 2
    return 0.5 * mu * (np.sum(f * f) - 2.0) + 0.5 * lam_nh * (j - alpha) ** 2 - rest


def test_membrane_round_trip():
    for mu, lam in ((1.0e3, 1.5e4), (4.0e3, 0.0), (250.0, 3.3e3)):
        ours = sn.membrane_from_newton(mu, lam)
        assert sn.membrane_to_newton(ours["k_uu"], ours["k_vv"], ours["k_uv"]) == pytest.approx((mu, lam))
    # ours -> Newton keeps the shear and the geometric mean of the axial stiffnesses
    mu, lam = sn.membrane_to_newton(2.0e4, 1.5e4, 1.0e3)
    assert mu == 1.0e3 and lam + 2 * mu == pytest.approx(np.sqrt(2.0e4 * 1.5e4))


def test_membrane_energies_agree_at_small_strain():
    """Our StVK energy with the converted material equals Newton's Neo-Hookean one to second order."""
    mu, lam = 2.0e3, 1.2e4
    material = ClothMaterial(**sn.membrane_from_newton(mu, lam))
    k = membrane_stiffness(material, torch.zeros((), dtype=torch.float64))
    rng = np.random.default_rng(0)
    for eps in (1e-2, 1e-3):
        for _ in range(5):
            f = np.eye(3, 2) + eps * rng.normal(size=(3, 2))  # F = D D̄⁻¹ of a rest triangle
            rest_inv = torch.eye(2, dtype=torch.float64)  # rest edges: the unit axes from corner 2
            x = torch.zeros(3, 3, dtype=torch.float64)
            x[0] = torch.from_numpy(f[:, 0])
            x[1] = torch.from_numpy(f[:, 1])
            c = triangle_green_strain(x[None], rest_inv[None])[0]  # [E00, E11, E01]
            ours = float(0.5 * c @ k @ c)
            newton = _newton_membrane_density(f, mu, lam)
            assert ours == pytest.approx(newton, rel=30 * eps)


def test_bending_and_material_round_trip():
    rng = np.random.default_rng(1)
    weight, length = rng.uniform(1.0, 4.0, 50), rng.uniform(0.01, 0.03, 50)
    edge_ke = sn.bend_to_newton(3.0e-5, weight, length)
    # equal energies per edge: ½ edge_ke |e| θ² = ½ k_b w θ²
    np.testing.assert_allclose(edge_ke * length, 3.0e-5 * weight)
    assert sn.bend_from_newton(edge_ke, weight, length) == pytest.approx(3.0e-5)
    mu, lam = 800.0, 9.0e3
    material = ClothMaterial(
        areal_density=0.2,
        **sn.membrane_from_newton(mu, lam),
        bend_stiffness=7e-6,
        friction=0.3,
        thickness=0.004,
    )
    newton = sn.material_to_newton(material, weight, length)
    assert (newton.tri_ke, newton.tri_ka) == pytest.approx((mu, lam))
    back = sn.material_from_newton(newton, weight, length)
    for name in (
        "areal_density",
        "k_uu",
        "k_vv",
        "k_uv",
        "poisson",
        "bend_stiffness",
        "friction",
        "thickness",
    ):
        assert float(getattr(back, name)) == pytest.approx(float(getattr(material, name)))


def test_drawn_material_is_in_our_units_and_ranges():
    base = ClothMaterial()
    factors = []
    for seed in range(40):
        material, draws = sn.draw_material(np.random.default_rng(seed), 2.0e-5)
        s = draws["stretch_factor"]
        lo, hi = sn.STRETCH_FACTOR_RANGE
        assert lo <= 1 / s <= hi  # softer than ours
        assert material.k_uv == pytest.approx(s * base.k_uv)
        assert material.k_uu == pytest.approx(s * np.sqrt(base.k_uu * base.k_vv))
        assert sn.BEND_FACTOR_RANGE[0] <= material.bend_stiffness / 2.0e-5 <= sn.BEND_FACTOR_RANGE[1]
        assert sn.FRICTION_RANGE[0] <= material.friction <= sn.FRICTION_RANGE[1]
        factors.append(s)
    assert max(factors) / min(factors) > 2  # spread over the range


def test_newton_scan_without_newton_says_how_to_install(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "newton", None)  # `import newton` now raises ImportError
    code = main(["make-scan", "skirt", "--out", str(tmp_path / "s"), "--simulator", "newton"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and len(err) == 1
    assert 'pip install -e ".[newton]"' in err[0]
    assert not (tmp_path / "s").exists()


def test_waist_drop_needs_newton(tmp_path, capsys):
    code = main(["make-scan", "skirt", "--out", str(tmp_path / "s"), "--waist-drop", "0.05"])
    assert code != 0 and "waist_drop" in capsys.readouterr().err


@pytest.mark.parametrize("extra", [[], ["--simulator", "newton"]])
def test_newton_iterations_need_newton_and_a_count(tmp_path, capsys, extra):
    args = ["make-scan", "skirt", "--out", str(tmp_path / "s"), "--newton-iterations", "0", *extra]
    code = main(args if extra else args[:-1] + ["40"])  # without newton: a valid count, still refused
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--newton-iterations needs --simulator newton" in err[0]
    assert not (tmp_path / "s").exists()


def test_newton_config_needs_newton():
    from torch_diffavatar.synthetic_scans import make_draped_scan

    with pytest.raises(InputError, match="newton_config needs simulator='newton'"):  # before any work
        make_draped_scan("skirt", anny_model=object(), newton_config=sn.NewtonDrapeConfig(iterations=40))


@pytest.mark.parametrize(
    "setting, message",
    [
        ({"iterations": 0}, "iterations must be an integer >= 1, got 0"),
        ({"substeps": 2.5}, "substeps must be an integer >= 1, got 2.5"),
        ({"min_frames": 500}, "min_frames 500 > max_frames 400"),
        ({"fps": 0.0}, "fps must be a finite number > 0, got 0.0"),
        ({"contact_gap": float("nan")}, "contact_gap must be a finite number >= 0, got nan"),
        ({"velocity_scale": 1.5}, r"velocity_scale must be in \(0, 1\], got 1.5"),
        ({"seam_ke": "1e4"}, "seam_ke must be a finite number >= 0, got '1e4'"),
    ],
)
def test_newton_config_refuses_settings_out_of_range(setting, message):
    # refused where it is made, not minutes into a drape
    with pytest.raises(ValueError, match=f"^NewtonDrapeConfig.{message}$"):
        sn.NewtonDrapeConfig(**setting)
    assert sn.NewtonDrapeConfig(iterations=1, min_frames=0, velocity_scale=1.0).iterations == 1


def test_lowered_cloth_stays_above_the_floor():
    """`lower_onto_body` moves the cloth down by the drop but never below the floor (the body's lowest point
    plus the thickness), cloth that starts under it included: Newton's floor met trouser legs 8 cm under
    it and blew up at the first frame."""
    from helpers_fit import TETRA_F, TETRA_V

    body = TETRA_V * 0.2 + torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)  # a small body, floor y = 1
    x = torch.tensor([[2.0, 1.5, 0.0], [2.0, 1.03, 0.0], [2.0, 0.9, 0.0]], dtype=torch.float64)
    out = sn.lower_onto_body(x, 0.05, body, TETRA_F, 0.002)
    assert out[:, [0, 2]].tolist() == x[:, [0, 2]].tolist()  # far from the body: only lowered
    assert out[:, 1].tolist() == pytest.approx([1.45, 1.002, 1.002])
