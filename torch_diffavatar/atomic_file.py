"""Files written whole or not at all: a temporary beside the target, flushed to the disk, then renamed over
it (`os.replace` is atomic on one file system). A crash, a refused value or a full disk leaves the old
file as it was and no temporary behind."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary file name beside ``path`` for a writer that wants a name (Pillow, a GIF writer); it keeps
    ``path``'s suffix (``picture.tmp.png``: writers that choose the format by the suffix still do). When the
    block ends without an error the file is flushed to the disk and becomes ``path``; when it raises, the
    temporary is removed (the error goes on) and ``path`` stays as it was."""
    path = Path(path)
    tmp = path.with_name(f"{path.stem}.tmp{path.suffix}")
    try:
        yield tmp
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


@contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb") -> Iterator[IO]:
    """A file (opened with ``mode``: "wb", or "w" for text) to write ``path``'s new content into; it becomes
    ``path`` when the block ends without an error, and is removed when it raises (`atomic_path`)."""
    if mode not in ("wb", "w"):
        raise ValueError(f"atomic_write: mode must be 'wb' or 'w', got {mode!r}")
    with atomic_path(path) as tmp, open(tmp, mode) as f:
        yield f


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` whole or not at all (`atomic_write`)."""
    with atomic_write(path, "w") as f:
        f.write(text)
