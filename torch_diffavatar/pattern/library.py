"""The bundled garment templates (GarmentCode specs, see templates/LICENSE-GarmentCode for provenance)."""

from __future__ import annotations

import os
from pathlib import Path

from torch_diffavatar.errors import PatternError
from torch_diffavatar.pattern.garmentcode import load_pattern
from torch_diffavatar.pattern.spec import Pattern

TEMPLATE_DIR = Path(__file__).resolve().parent / "templates"


def list_templates() -> list[str]:
    """Names of the bundled templates, sorted (``dress``, ``dress_pencil``, ``longsleeve`` …)."""
    return sorted(p.stem for p in TEMPLATE_DIR.glob("*.json"))


def template_path(name: str) -> Path:
    """Path of the template ``name``.

    Raises:
        PatternError: unknown name (the message lists the valid ones).
    """
    path = TEMPLATE_DIR / f"{name}.json"
    if not isinstance(name, str) or "/" in name or not path.is_file():
        raise PatternError(f"unknown garment template {name!r}; valid names: {', '.join(list_templates())}")
    return path


def load_template(name: str) -> Pattern:
    """Load a bundled template by name (metres; ``garment_type`` set)."""
    return load_pattern(template_path(name))


def resolve_pattern(name_or_path: str | os.PathLike) -> Pattern:
    """A template name (``"dress"``) or a path to a GarmentCode JSON file -> `Pattern`.

    A string that names an existing file, or that looks like a path (contains a path separator or ends
    in ``.json``), is read as a file; anything else must be a template name (a folder named like a
    template in the working directory, e.g. a fit's output ``skirt/``, does not hide the template).

    Raises:
        PatternError: unknown template name (listing the valid ones), or any loading error.
    """
    text = os.fspath(name_or_path)
    looks_like_path = os.sep in text or "/" in text or text.endswith(".json") or Path(text).is_file()
    if isinstance(name_or_path, os.PathLike) or looks_like_path:
        return load_pattern(text)
    return load_template(text)
