"""Exceptions raised for bad user input (files, patterns, scans). The CLI turns them into one line."""

from __future__ import annotations

import json
from pathlib import Path


class InputError(ValueError):
    """Bad input that the user can fix; the message names the problem and, where known, the file."""


class PatternError(InputError):
    """A sewing pattern that cannot be read, validated or meshed."""


class ScanError(InputError):
    """A scan that cannot be read or is unusable (empty, NaN, wrong units…)."""


class NonFiniteError(ValueError):
    """A number to write out is NaN or infinite (`json_io.dumps_json`): the result is broken, and no file
    is written with it."""


class SimulationError(RuntimeError):
    """The simulation blew up (NaN, runaway speed or stretch) and returned nothing usable."""


def read_json_file(path: str | Path, missing: str):
    """The parsed JSON of the file ``path``; `InputError` with the message ``missing`` when there is no such
    file, and one naming the file when it is not valid JSON."""
    path = Path(path)
    if not path.is_file():
        raise InputError(missing)
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: not valid JSON ({exc})") from exc
