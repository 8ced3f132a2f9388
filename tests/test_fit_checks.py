"""scripts/fit_checks.py: its ``--set`` overrides of a fit config (the checks need a suite scan)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from torch_diffavatar.errors import InputError

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def checks():
    spec = importlib.util.spec_from_file_location("fit_checks", ROOT / "scripts" / "fit_checks.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_overrides_set_fields_and_weights_over_the_config_file(checks):
    path = ROOT / "configs" / "tshirt.yaml"
    base = checks._config(path, [])
    config = checks._config(path, ["drape_substeps=10", "weights.boundary=2.5e3", "max_loss_rise=.inf"])
    assert config.drape_substeps == 10 and base.drape_substeps != 10
    assert config.weights.boundary == 2.5e3 and config.weights.interior == base.weights.interior
    assert config.max_loss_rise == float("inf")
    assert config.template == base.template == "tshirt"


def test_unknown_override_is_an_input_error(checks):
    with pytest.raises(InputError, match="drape_substep"):
        checks._config(ROOT / "configs" / "tshirt.yaml", ["drape_substep=10"])
