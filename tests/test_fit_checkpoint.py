"""A fit's own files load without running code: ``setup.pt`` and ``checkpoint.pt`` are read with
``weights_only=True`` and only the project's plain data classes allowed."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

from torch_diffavatar.errors import InputError
from torch_diffavatar.fit_checkpoint import atomic_save, safe_load
from torch_diffavatar.objective import ScanTarget
from torch_diffavatar.pattern import load_template, mesh_pattern, pattern_to_dict
from torch_diffavatar.sim.forward_drape import PoseRoute


class _Payload:
    """What a crafted file holds: unpickling it would create ``marker``."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.makedirs, (self.marker,))


def test_a_set_up_round_trips(tmp_path):
    pattern = load_template("skirt")
    garment = mesh_pattern(pattern, spacing=0.08)
    setup = {
        "garment": garment,
        "pattern": pattern,
        "target": ScanTarget(torch.rand(10, 3), {"hem": torch.rand(4, 3)}, torch.rand(5, 3)),
        "body_params": {"phenotypes": [[0.5] * 6]},
        "sewing_fallback": PoseRoute(garment.vert_pos.clone(), torch.rand(2, 7, 3)),
    }
    atomic_save(setup, tmp_path / "setup.pt")
    back = safe_load(tmp_path / "setup.pt")
    assert pattern_to_dict(back["pattern"]) == pattern_to_dict(pattern)
    torch.testing.assert_close(back["garment"].vert_uv, garment.vert_uv)
    torch.testing.assert_close(back["target"].boundaries["hem"], setup["target"].boundaries["hem"])
    torch.testing.assert_close(back["sewing_fallback"].body_path, setup["sewing_fallback"].body_path)


def test_a_crafted_file_is_refused_and_runs_nothing(tmp_path):
    marker = tmp_path / "ran"
    torch.save({"garment": _Payload(marker)}, tmp_path / "setup.pt")
    with pytest.raises(InputError, match="not a fit file this version reads safely"):
        safe_load(tmp_path / "setup.pt")
    assert not marker.exists()
    (tmp_path / "junk.pt").write_bytes(b"not a torch file")
    with pytest.raises(InputError, match="junk.pt"):
        safe_load(tmp_path / "junk.pt")


def test_no_file_of_the_project_loads_with_weights_only_false():
    """Every ``torch.load`` (package, scripts, tests) runs no code from the file: the scripts' caches too."""
    root = Path(__file__).resolve().parents[1]
    unsafe = "weights_only=" + "False"  # spelled apart so that this file does not match itself
    found = [
        str(path.relative_to(root))
        for folder in ("torch_diffavatar", "scripts", "tests")
        for path in (root / folder).rglob("*.py")
        if unsafe in path.read_text()
    ]
    assert found == []
