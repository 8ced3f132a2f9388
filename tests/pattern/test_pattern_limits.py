"""Patterns that cannot be meshed sensibly are refused at once, in one line (issue #33)."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import triangle

from torch_diffavatar import cli
from torch_diffavatar.errors import PatternError
from torch_diffavatar.pattern import load_template, mesh_pattern, save_pattern
from torch_diffavatar.pattern.garmentcode import load_pattern


def _scaled(factor: float):
    pattern = copy.deepcopy(load_template("skirt"))
    for panel in pattern.panels.values():
        panel.vertices = np.asarray(panel.vertices) * factor
    return pattern


def test_a_pattern_a_thousand_times_too_large_is_refused_before_meshing(monkeypatch):
    def no_triangle(*args, **kwargs):  # Triangle took 40 s to fail on a km-size panel
        raise AssertionError("Triangle was called")

    monkeypatch.setattr(triangle, "triangulate", no_triangle)
    with pytest.raises(PatternError, match=r"meshes to about [\d,]+ vertices .* check the pattern's units"):
        mesh_pattern(_scaled(1000.0), spacing=0.015)


def test_a_micrometre_pattern_is_refused():
    with pytest.raises(PatternError, match="m across, less than the mesh spacing 0.015 m"):
        mesh_pattern(_scaled(1e-6), spacing=0.015)


def test_deeply_nested_json_is_a_pattern_error(tmp_path):
    path = tmp_path / "deep.json"
    path.write_text("[" * 100000 + "]" * 100000)
    with pytest.raises(PatternError, match="nested too deeply"):
        load_pattern(path)


def test_the_mesh_command_says_so_in_one_line(tmp_path, capsys):
    path = tmp_path / "huge_specification.json"
    save_pattern(_scaled(1000.0), path)
    assert cli.main(["mesh", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "vertices at spacing" in err
