"""Strict JSON out: what this package writes is JSON that every parser reads.

Python's `json` writes ``Infinity`` and ``NaN`` for non-finite floats, which is not JSON (RFC 8259): a
browser, ``jq`` or another language's parser refuses the file, and a number that was meant to be a
measure silently is none. `dumps_json` refuses them instead and names where they are; `write_json`
writes a file whole or not at all (`atomic_file.atomic_write`).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

from torch_diffavatar.atomic_file import atomic_write
from torch_diffavatar.errors import NonFiniteError


def _non_finite_path(obj, path: str = "$") -> str | None:
    """The JSON path of the first non-finite float in ``obj`` (dicts, lists, tuples), or None."""
    if isinstance(obj, float):
        return None if math.isfinite(obj) else path
    if isinstance(obj, dict):
        items = ((f"{path}.{k}", v) for k, v in obj.items())
    elif isinstance(obj, list | tuple):
        items = ((f"{path}[{i}]", v) for i, v in enumerate(obj))
    else:
        return None
    for sub_path, value in items:
        found = _non_finite_path(value, sub_path)
        if found is not None:
            return found
    return None


def dumps_json(obj, **kwargs) -> str:
    """``json.dumps(obj, **kwargs)`` that refuses non-finite numbers.

    Raises:
        NonFiniteError: (a ValueError) ``obj`` holds NaN or ±inf; the message gives its path
            (``$.material.k_uu``).
    """
    try:
        return json.dumps(obj, allow_nan=False, **kwargs)
    except ValueError as exc:
        where = _non_finite_path(obj)
        if where is None:
            raise
        raise NonFiniteError(f"not JSON: {where} is not a finite number") from exc


def write_json(path: str | os.PathLike, obj, *, indent: int | None = 1) -> Path:
    """Write ``obj`` as strict JSON (`dumps_json`) to ``path`` atomically; returns the path.

    The text is made before the file is touched, so a refused value leaves any old file as it was.
    """
    text = dumps_json(obj, indent=indent).encode()  # ASCII: json escapes every other character
    with atomic_write(path) as f:
        f.write(text)
    return Path(path)
