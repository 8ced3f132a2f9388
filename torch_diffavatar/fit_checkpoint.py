"""A fit's files that let a run continue: the set-up (``setup.pt``), the checkpoint after every iteration
(``checkpoint.pt``, written atomically), and the driver's bookkeeping that a checkpoint holds."""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np
import torch

from torch_diffavatar.atomic_file import atomic_write
from torch_diffavatar.errors import InputError
from torch_diffavatar.objective import ScanTarget
from torch_diffavatar.pattern.garment_mesh import BoundaryLoop, GarmentMesh
from torch_diffavatar.pattern.spec import Edge, EdgeRef, Panel, Pattern, Stitch
from torch_diffavatar.sim.adjoint.linearization import Linearization
from torch_diffavatar.sim.forward_drape import PoseRoute
from torch_diffavatar.sim.state import ClothState

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
    "resewings": (list, []),
    "prox_shift": (None, None),  # `fit.rest_prox`'s last correction, where the next one starts
    "seconds": (float, 0.0),
}


def atomic_save(obj, path: Path) -> None:
    """``torch.save`` to a temporary file, flushed to the disk, then renamed to ``path``: a crash or a full
    disk never leaves half a file, and the old file stays until the new one is whole.

    Raises:
        OSError: the file could not be written (no space, not writable); no temporary is left behind.
    """
    with atomic_write(path) as f:
        try:
            torch.save(obj, f)
        except RuntimeError as exc:  # torch reports a failed write (ENOSPC) as an enforce failure
            raise OSError(f"could not write {path}: {str(exc).splitlines()[0]}") from exc


def _data_classes() -> list:
    """The plain data a fit's files hold besides tensors and Python containers: the set-up's pattern,
    garment mesh, scan target and pose route, and the numpy arrays inside them. Nothing that runs code."""
    numpy_core = getattr(np, "_core", None) or np.core  # numpy 2 / 1
    dtypes = [type(np.dtype(t)) for t in (np.float64, np.float32, np.int64, np.int32, np.bool_, np.uint8)]
    ours = [ScanTarget, BoundaryLoop, GarmentMesh, Edge, EdgeRef, Panel, Pattern, Stitch, PoseRoute]
    return [*ours, np.ndarray, np.dtype, numpy_core.multiarray._reconstruct, *dtypes]


def safe_load(path: str | os.PathLike):
    """``torch.load`` of a fit's own file (``setup.pt``, ``checkpoint.pt``) with ``weights_only=True``: it
    unpickles tensors, containers and `_data_classes` only, so a crafted file cannot run code.

    Raises:
        InputError: the file holds anything else, or is not a torch file.
    """
    try:
        with torch.serialization.safe_globals(_data_classes()):
            return torch.load(path, weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, AttributeError, ModuleNotFoundError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(f"{path}: not a fit file this version reads safely ({first})") from exc


def start_state(start: ClothState) -> dict:
    """A drape start as plain data: ``start_x``, ``start_v`` and its linearization's inputs
    (``start_linearization``, or None), from which `start_from` rebuilds the same start."""
    lin = start.linearization
    return {
        "start_x": start.x.detach().clone(),
        "start_v": start.v.detach().clone(),
        "start_linearization": None if lin is None else lin.state_dict(),
    }


def start_from(state: dict, dtype: torch.dtype) -> ClothState:
    """The drape start of `start_state` ``state`` in ``dtype`` (a checkpoint of an older version has no
    linearization: its next drape is not predicted)."""
    lin = state.get("start_linearization")
    lin = None if lin is None else Linearization.from_state_dict(lin)
    return ClothState(state["start_x"].to(dtype), state["start_v"].to(dtype), lin)


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


def upgraded(state: dict) -> dict:
    """A checkpoint ``state`` of an older version in today's form: the parameters (and the best iteration's)
    of a checkpoint written before the membrane stretch or the waist height were fit variables get
    ``log_stretch`` = 0 and ``raw_waist_shift`` = 0, and its first evaluation's summary the factor 1 and
    no shift: the base membrane and the placed waist those fits used, so they resume exactly."""
    state = dict(state)
    for owner in (state, state.get("best")):
        for name in ("log_stretch", "raw_waist_shift"):
            if owner is not None and name not in owner["params"]:
                params = owner["params"]
                owner["params"] = {**params, name: params["log_bend_stiffness"].new_zeros(())}
    for name, value in (("stretch_scale", 1.0), ("waist_shift_m", 0.0)):
        if state.get("first") is not None and name not in state["first"]:
            state["first"] = {**state["first"], name: value}
    return state
