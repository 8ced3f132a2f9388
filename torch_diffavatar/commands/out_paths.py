"""Output paths checked before any work: a folder under a file, or in a folder not writable, is refused in
one line at once, not after minutes of fitting (issue #33)."""

from __future__ import annotations

import os
from pathlib import Path

from torch_diffavatar.errors import InputError


def check_out_folder(path: str | os.PathLike, option: str = "--out") -> None:
    """InputError when the folder ``path`` (given as ``option``) cannot be made or written into: it is a
    file, a part of it is a file, or the nearest existing folder above it is not writable."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{option} {path} exists and is not a folder; choose another {option}")
    probe = path
    while not probe.exists():  # the nearest existing part ("." or "/" at the latest)
        probe = probe.parent
    if not probe.is_dir():
        raise InputError(f"{option} {path}: {probe} is a file, not a folder; choose another {option}")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise InputError(f"{option} {path}: {probe} is not writable; choose another {option}")


def check_out_files(args, *options: str) -> None:
    """`check_out_folder` for the folder of each file option of ``args`` that is given (``"out"``,
    ``"png"``, …): a picture or mesh under a file, or in a read-only folder, refused before any work."""
    for option in options:
        value = getattr(args, option, None)
        if value is None:
            continue
        folder = Path(value).resolve().parent
        if folder.exists() and not folder.is_dir():
            raise InputError(
                f"--{option} {value}: {folder} is a file, not a folder; choose another --{option}"
            )
        check_out_folder(folder, f"--{option}")
