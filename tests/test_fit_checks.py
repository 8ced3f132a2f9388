"""scripts/fit_checks.py: its ``--set`` overrides of a fit config (the checks need a suite scan)."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers_scripts import load_script

from torch_diffavatar.errors import InputError

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def checks():
    return load_script("fit_checks")


def test_overrides_set_fields_and_weights_over_the_config_file(checks):
    path = ROOT / "torch_diffavatar" / "configs" / "tshirt.yaml"
    base = checks._config(path, [])
    config = checks._config(path, ["drape_substeps=10", "weights.boundary=2.5e3", "max_loss_rise=.inf"])
    assert config.drape_substeps == 10 and base.drape_substeps != 10
    assert config.weights.boundary == 2.5e3 and config.weights.interior == base.weights.interior
    assert config.max_loss_rise == float("inf")
    assert config.template == base.template == "tshirt"


def test_unknown_override_is_an_input_error(checks):
    with pytest.raises(InputError, match="drape_substep"):
        checks._config(ROOT / "torch_diffavatar" / "configs" / "tshirt.yaml", ["drape_substep=10"])


@pytest.mark.anny
@pytest.mark.slow
def test_spacing_check_reproduces_the_true_drape_at_the_scans_own_spacing(checks, skirt_scan, tmp_path):
    """At the scan's spacing the check's drape is the scan's (same mesh, same path; the float64 fixture's
    body is rounded to 9 digits in body.obj), and a drape started from the true drape stays there; at
    another spacing both are measured."""
    import argparse

    from torch_diffavatar.synthetic_scans import write_scan

    write_scan(skirt_scan, tmp_path / "skirt" / "scan")
    args = argparse.Namespace(garment_dir=str(tmp_path / "skirt"), spacings=[0.05, 0.07])
    out = checks.spacing(args)
    same, coarse = out["rows"]
    assert out["scan_spacing_m"] == 0.05 and same["spacing_m"] == 0.05 and coarse["spacing_m"] == 0.07
    assert same["sewn_mm"] < 0.5 and same["from_truth_mm"] < 0.5
    assert coarse["vertices"] < same["vertices"] and coarse["sewn_mm"] > 0.0 and coarse["from_truth_mm"] > 0.0
    assert same["converged"] and coarse["converged"]


def test_grown_moves_a_sphere_along_its_normals(checks):
    import torch
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    verts = torch.tensor(sphere.vertices, dtype=torch.float32)
    faces = torch.tensor(sphere.faces, dtype=torch.int64)
    assert torch.equal(checks.grown(verts, faces, 0.0), verts)
    for offset in (0.002, -0.003):
        radius = checks.grown(verts, faces, offset).double().norm(dim=1)
        assert torch.allclose(radius, torch.full_like(radius, 0.1 + offset), atol=1e-6)


@pytest.mark.anny
@pytest.mark.slow
def test_body_check_reproduces_the_true_drape_on_the_true_body(checks, skirt_scan, tmp_path):
    """Offset 0 sews the scan's drape again (below the float64 fixture's 9-digit rounding in body.obj);
    a body grown by 5 mm pushes the cloth out."""
    import argparse

    from torch_diffavatar.synthetic_scans import write_scan

    write_scan(skirt_scan, tmp_path / "skirt" / "scan")
    out = checks.body(argparse.Namespace(garment_dir=str(tmp_path / "skirt"), offsets=[0.0, 0.005]))
    same, thick = out["rows"]
    assert out["check"] == "body" and same["offset_mm"] == 0.0 and thick["offset_mm"] == 5.0
    assert same["sewn_mm"] < 0.5 and thick["sewn_mm"] > 1.0
    assert (
        abs(same["sewn_scan_mm"] - out["truth_scan_mm"]) < 0.5
        and thick["sewn_scan_mm"] > out["truth_scan_mm"]
    )
    assert same["converged"] and thick["converged"]
