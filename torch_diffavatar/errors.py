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


def _refuse_constant(name: str):
    raise ValueError(f"{name} is not a JSON number")


def parse_json(text: str, where: str):
    """The parsed JSON ``text`` of a user's file, read strictly: `InputError` (naming ``where``) when it is
    not JSON, is nested too deeply (Python's parser recurses: 100,000 ``[`` end in a RecursionError), or
    holds ``NaN`` / ``Infinity``, which no JSON parser but Python's takes for numbers."""
    try:
        return json.loads(text, parse_constant=_refuse_constant)
    except RecursionError as exc:
        raise InputError(f"{where}: JSON nested too deeply to read") from exc
    except ValueError as exc:  # JSONDecodeError is one, and so is a refused constant
        raise InputError(f"{where}: not valid JSON ({exc})") from exc


def read_json_file(path: str | Path, missing: str, where: str | None = None):
    """The parsed JSON of the file ``path`` (`parse_json`, strict); `InputError` with the message ``missing``
    when there is no such file, and one naming ``where`` (default: the file) when it is not valid JSON."""
    path = Path(path)
    if not path.is_file():
        raise InputError(missing)
    where = str(path) if where is None else where
    try:
        text = path.read_text()
    except UnicodeDecodeError as exc:
        raise InputError(f"{where}: not a text JSON file ({exc})") from exc
    return parse_json(text, where)
