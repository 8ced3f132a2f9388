"""A fit's files that let a run continue: the set-up (``setup.pt``), the checkpoint after every iteration
(``checkpoint.pt``, written atomically), and the driver's bookkeeping that a checkpoint holds."""

from __future__ import annotations

import os
from pathlib import Path

import torch

CHECKPOINT = "checkpoint.pt"
SETUP = "setup.pt"

# the driver's bookkeeping in a checkpoint: attribute -> (type a loaded value is cast to, or None to keep it
# as it is; value when an older checkpoint lacks it)
PROGRESS = {
    "iteration": (int, 0),
    "history": (list, []),
    "rejected_steps": (int, 0),
    "rejection_reasons": (dict, {}),
    "nan_gradients": (int, 0),
    "adjoint_failures": (int, 0),
    "lr_scale": (float, 1.0),
    "trial_from_start": (bool, False),
    "first": (None, None),
    "best": (None, None),
    "first_candidates": (list, []),
    "seconds": (float, 0.0),
}


def atomic_save(obj, path: Path) -> None:
    """``torch.save`` to a temporary file, then rename it to ``path``: a crash never leaves half a file."""
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def progress_state(driver) -> dict:
    """The `PROGRESS` attributes of ``driver`` (lists and dicts shallow-copied)."""
    return {
        name: kind(getattr(driver, name)) if kind in (list, dict) else getattr(driver, name)
        for name, (kind, _) in PROGRESS.items()
    }


def load_progress(driver, state: dict) -> None:
    """Set the `PROGRESS` attributes of ``driver`` from a checkpoint's ``state``."""
    for name, (kind, default) in PROGRESS.items():
        value = state.get(name, default)
        setattr(driver, name, value if kind is None else kind(value))
