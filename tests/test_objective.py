"""`FitObjective` and `FitParameters` as modules: the loss `Fitter` drives, buffers that follow ``.to()`` and
``state_dict()``, and ``scripts/fit_loop.py``, the fit as a plain ``torch.optim`` loop, reaching `Fitter`'s
result (and ``diffavatar fit``'s on a scan with a body)."""

from __future__ import annotations

import importlib.util
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from helpers_fit import DT
from helpers_fit import fit_config as _config

from torch_diffavatar.fit import Fitter
from torch_diffavatar.fit_checkpoint import safe_load
from torch_diffavatar.fit_config import LossWeights
from torch_diffavatar.objective import TERM_NAMES, FitObjective, FitParameters, FitVariables

ROOT = Path(__file__).resolve().parents[1]


def _moved(params: FitParameters) -> FitParameters:
    """``params`` away from the template, where every term has a value and a gradient."""
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        params.cage.handles.add_(0.01 * torch.randn(params.cage.handles.shape, generator=gen, dtype=DT))
        params.log_bend_stiffness.add_(0.3)
    return params


def _fit_loop_module():
    spec = importlib.util.spec_from_file_location("fit_loop", ROOT / "scripts" / "fit_loop.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_objective_is_what_the_fitter_evaluates(skirt_problem):
    """A `FitObjective` built beside a `Fitter` gives its loss, terms, drape and gradients bit for bit, at
    parameters away from the template."""
    garment, state, target = skirt_problem
    config = _config()
    fitter = Fitter(garment, target, config, start_state=state, progress=False, tensorboard=False, dtype=DT)
    _moved(fitter.params)
    objective = FitObjective(garment, target, config, dtype=DT)
    params = _moved(FitParameters.from_config(garment, config, dtype=DT))
    expected = fitter.evaluate(state)
    variables = params()
    assert (
        isinstance(variables, FitVariables) and variables.body_verts is None and variables.phenotypes is None
    )
    out = objective(variables, state)
    assert list(out.terms) == ["interior", "boundary", "seam_length", "curvature", "rest_area", "rest_shape"]
    assert list(out.terms) == list(expected.terms)
    for name, value in expected.terms.items():
        assert torch.equal(out.terms[name], value), name
    assert torch.equal(out.loss, expected.loss) and torch.equal(out.x, expected.x)
    assert [lp.name for lp in out.openings] == ["hem"]
    assert float(out.terms["seam_length"].detach()) > 0 and float(out.terms["curvature"].detach()) > 0
    expected.loss.backward()
    out.loss.backward()
    assert torch.equal(params.cage.handles.grad, fitter.params.cage.handles.grad)
    assert torch.equal(params.log_bend_stiffness.grad, fitter.params.log_bend_stiffness.grad)
    # the rest terms alone, and the loss from plain tensors instead of `FitVariables`
    rest = {k: v for k, v in out.terms.items() if k not in ("interior", "boundary")}
    with torch.no_grad():  # the C++ kernels sum in another order (tests/test_rest_terms.py)
        want = objective.weighted_sum(rest)
        torch.testing.assert_close(objective.rest_loss(out.rest_uv), want, rtol=1e-12, atol=0)
        again = objective(out.rest_uv, state, bend_stiffness=out.bend_stiffness)
    assert torch.equal(again.loss, out.loss)
    with pytest.raises(ValueError, match="bend_stiffness"):
        objective(out.rest_uv, state)


def test_to_float64_moves_the_buffers(skirt_problem):
    """The scan target and the weights are buffers: ``.to(torch.float64)`` casts them, the cloth model
    follows, and the objective then drapes in float64."""
    garment, state, target = skirt_problem
    config = _config()
    objective = FitObjective(garment, target, config, dtype=torch.float32)
    assert objective.scan_points.dtype == torch.float32 and objective.cloth_model.dtype == torch.float32
    assert objective.boundary_names == ["hem"] and torch.equal(
        objective.scan_boundaries["hem"], objective.scan_boundary_0
    )
    names = set(objective.state_dict())
    assert {"scan_points", "scan_boundary_0", *(f"weight_{t}" for t in TERM_NAMES)} <= names
    assert objective.to(torch.float64) is objective
    buffers = dict(objective.named_buffers())
    assert {"scan_points", "scan_boundary_0", "template_uv", "weight_boundary"} <= set(buffers)
    assert all(b.dtype == torch.float64 for b in buffers.values() if b.is_floating_point())
    assert objective.cloth_model.dtype == torch.float64
    params = FitParameters.from_config(garment, config, dtype=DT)
    with torch.no_grad():
        out = objective(params(), state)
        direct = FitObjective(garment, target, config, dtype=DT)(params(), state)
    assert out.loss.dtype == torch.float64 and out.x.dtype == torch.float64
    # the same up to the float32 rounding of the scan points [~1e-8 m]
    torch.testing.assert_close(out.loss, direct.loss, rtol=1e-5, atol=0)


def test_the_weights_are_buffers_of_the_state_dict(skirt_problem):
    """Loading the state of an objective with doubled weights doubles the loss: the weights used are the
    buffers, not the config they came from."""
    garment, state, target = skirt_problem
    config = _config()
    doubled = LossWeights(**{name: 2 * getattr(config.weights, name) for name in TERM_NAMES})
    objective = FitObjective(garment, target, config, dtype=DT)
    other = FitObjective(garment, target, replace(config, weights=doubled), dtype=DT)
    variables = _moved(FitParameters.from_config(garment, config, dtype=DT))()
    with torch.no_grad():
        before = objective(variables, state).loss
        objective.load_state_dict(other.state_dict())
        after = objective(variables, state).loss
    assert objective.weights == doubled
    assert torch.equal(after, 2 * before)


def test_the_plain_loop_reaches_the_fitters_result(skirt_problem):
    """``scripts/fit_loop.py``'s loop (Adam, the cosine schedule, warm starts) ends where `Fitter` ends when
    its guards do not act: no proximal rest step, no loss-rise check, the last iteration kept."""
    garment, state, target = skirt_problem
    config = _config(iterations=3, rest_prox_iterations=0, max_loss_rise=float("inf"), keep_best=False)
    config = replace(config, lr_final=0.5)
    fitter = Fitter(garment, target, config, start_state=state, progress=False, tensorboard=False, dtype=DT)
    result = fitter.run()
    assert result.report["rejected_steps"] == 0 and result.report["result_iteration"] == 3
    params, out = _fit_loop_module().fit_loop(garment, target, config, start_state=state, dtype=DT)
    assert float(out.loss.detach()) == pytest.approx(result.report["loss_final"], rel=1e-12)
    torch.testing.assert_close(out.rest_uv.detach(), result.rest_uv, rtol=0, atol=1e-12)
    torch.testing.assert_close(out.x.detach(), result.x, rtol=0, atol=1e-12)
    torch.testing.assert_close(
        params.log_bend_stiffness, fitter.params.log_bend_stiffness, rtol=0, atol=1e-12
    )
    assert result.report["loss_final"] < 0.8 * result.report["loss_initial"]  # it did fit


@pytest.mark.anny
@pytest.mark.slow
def test_the_fit_loop_script_reaches_diffavatar_fits_result(skirt_scan, tmp_path):
    """On a scan with a body (fitted too: phenotypes, translation; skin term, phenotype prior), the script's
    set-up and loop end where ``diffavatar fit`` (`fit_scan`) ends with a config whose guards do not act."""
    from torch_diffavatar.body.anny_model import load_anny
    from torch_diffavatar.fit import CHECKPOINT, load_config
    from torch_diffavatar.fit_scan import fit_scan
    from torch_diffavatar.synthetic_scans import write_scan

    write_scan(skirt_scan, tmp_path / "scan")
    scan, truth = tmp_path / "scan" / "scan.ply", skirt_scan.body_params
    overrides = dict(spacing=0.05, iterations=2, rest_prox_iterations=0, max_loss_rise=float("inf"))
    config = load_config(garment="skirt", keep_best=False, **overrides)
    anny = load_anny(dtype=torch.float32)
    report = fit_scan(scan, config, tmp_path / "fit", progress=False, anny_model=anny, body_params=truth)
    assert report["rejected_steps"] == 0 and report["result_iteration"] == 2
    assert {"skin", "phenotype_prior"} <= set(report["loss_terms_final"])
    script = _fit_loop_module()
    setup, body = script.set_up(scan, config, anny, body_params=truth)
    params, out = script.fit_loop(
        setup["garment"], setup["target"], config, body, sewing_fallback=setup["sewing_fallback"]
    )
    assert float(out.loss.detach()) == pytest.approx(report["loss_final"], rel=1e-6)
    for name, value in report["loss_terms_final"].items():
        assert float(out.terms[name].detach()) == pytest.approx(value, rel=1e-5, abs=1e-12), name
    fitted = safe_load(tmp_path / "fit" / CHECKPOINT)["params"]
    for name, value in params.state_dict().items():  # the cage handles (the pattern), the body, k_b
        torch.testing.assert_close(value, fitted[name], rtol=1e-5, atol=1e-7)


def test_a_partial_scan_pulls_only_the_cloth_it_sees(skirt_problem):
    garment, state, target = skirt_problem
    config = _config()
    params = FitParameters.from_config(garment, config, dtype=DT)
    full = FitObjective(garment, target, config, dtype=DT)(params(), state)
    every_side = replace(target, seen_sides=torch.ones(8, dtype=torch.bool))
    assert torch.equal(FitObjective(garment, every_side, config, dtype=DT)(params(), state).loss, full.loss)
    front = torch.tensor([True, True, True, False, False, False, True, True])  # one camera in front
    partial = FitObjective(garment, replace(target, seen_sides=front), config, dtype=DT)(params(), state)
    assert not torch.equal(partial.terms["interior"], full.terms["interior"])
    assert not torch.equal(partial.terms["boundary"], full.terms["boundary"])  # the unseen hem half left out
