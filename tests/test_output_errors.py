"""Output paths that cannot be written end in one line and exit 2, not a traceback (issue #33)."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np
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
    assert f"{blocker} is a file, not a folder" in err


def test_an_output_in_a_read_only_folder(read_only_folder, capsys):
    code, err = _run(["mesh", "skirt", "--spacing", "0.05", "--svg", str(read_only_folder / "p.svg")], capsys)
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


def test_a_failed_picture_leaves_the_old_file_and_no_temporary(tmp_path, monkeypatch):
    from PIL import Image

    from torch_diffavatar.render import save_png

    path = save_png(np.zeros((4, 4, 3), np.uint8), tmp_path / "p.png")
    before = path.read_bytes()

    def full(self, fp, *args, **kwargs):
        Path(fp).write_bytes(b"partial")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(fp))

    monkeypatch.setattr(Image.Image, "save", full)
    with pytest.raises(OSError):
        save_png(np.full((4, 4, 3), 255, np.uint8), path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.png"]


def test_meshes_and_point_clouds_are_written_whole(tmp_path):
    from torch_diffavatar.mesh_io import read_obj, write_obj
    from torch_diffavatar.scan import load_scan, save_ply

    verts, faces = np.eye(3), np.array([[0, 1, 2]])
    write_obj(tmp_path / "m.obj", verts, faces)
    save_ply(tmp_path / "c.ply", verts, binary=True)
    assert read_obj(tmp_path / "m.obj").verts.shape == (3, 3)
    assert load_scan(tmp_path / "c.ply", check=False).point_count == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.ply", "m.obj"]
