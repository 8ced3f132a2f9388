"""Output paths that cannot be written end in one line and exit 2, not a traceback (issue #33)."""

from __future__ import annotations

import errno
import os

import pytest
import torch

from torch_diffavatar import cli
from torch_diffavatar.fit_checkpoint import atomic_save


def _run(argv, capsys) -> tuple[int, str]:
    code = cli.main(argv)
    return code, capsys.readouterr().err


def test_an_output_under_a_file(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code, err = _run(["mesh", "skirt", "--spacing", "0.05", "--out", str(blocker / "g.obj")], capsys)
    assert code == 2
    assert err.count("\n") == 1 and "Traceback" not in err
    assert "a part of this path is a file, not a folder" in err


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_an_output_in_a_read_only_folder(tmp_path, capsys):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        code, err = _run(["mesh", "skirt", "--spacing", "0.05", "--svg", str(locked / "p.svg")], capsys)
    finally:
        locked.chmod(0o700)
    assert code == 2 and err.count("\n") == 1 and "not writable" in err


def test_a_full_disk_leaves_the_old_checkpoint_and_no_temporary(tmp_path, monkeypatch):
    path = tmp_path / "checkpoint.pt"
    atomic_save({"iteration": 1}, path)

    def full(obj, f, *args, **kwargs):
        f.write(b"partial")
        raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 0 vs 128")

    monkeypatch.setattr(torch, "save", full)
    with pytest.raises(OSError, match="could not write"):
        atomic_save({"iteration": 2}, path)
    monkeypatch.undo()
    assert torch.load(path, weights_only=True) == {"iteration": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt"]


def test_no_space_reads_as_one_line():
    exc = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "/out/draped.obj")
    assert cli._os_error_line(exc) == (
        "No space left on device: /out/draped.obj (free some space, or choose another --out)"
    )
