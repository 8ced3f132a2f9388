"""Strict JSON out (issue #33): no ``Infinity`` or ``NaN`` in a file or on a ``--json`` line."""

from __future__ import annotations

import json
import math

import pytest

from torch_diffavatar import cli
from torch_diffavatar.json_io import dumps_json, write_json


def test_non_finite_numbers_are_refused_with_their_path():
    assert json.loads(dumps_json({"a": [1.0, {"b": 2}]})) == {"a": [1.0, {"b": 2}]}
    with pytest.raises(ValueError, match=r"\$\.material\.k_uu is not a finite number"):
        dumps_json({"material": {"k_uu": math.inf}})
    with pytest.raises(ValueError, match=r"\$\.losses\[1\]"):
        dumps_json({"losses": [0.5, math.nan]})


def test_a_refused_file_leaves_the_old_one_whole(tmp_path):
    path = tmp_path / "report.json"
    write_json(path, {"chamfer": 0.01})
    with pytest.raises(ValueError):
        write_json(path, {"chamfer": math.nan})
    assert json.loads(path.read_text()) == {"chamfer": 0.01}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.json"]  # no temporary left


def test_a_json_line_with_nan_is_an_error_not_output(monkeypatch, capsys):
    def command(args):
        return {"ratio": math.inf}

    parser = cli.build_parser
    monkeypatch.setattr(cli, "build_parser", lambda: _with_command(parser(), command))
    assert cli.main(["nan-test", "--json"]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err.strip() == "diffavatar nan-test: error: not JSON: $.ratio is not a finite number"


def _with_command(parser, func):
    sub = next(a for a in parser._actions if a.dest == "command")
    p = sub.add_parser("nan-test")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=func)
    return parser
