"""The two adjoints of the differentiable drape, chosen by name (see `sim/differentiable.py`).

Each entry of `ADJOINTS` gives the adjoint's options dataclass, its forward (run under ``no_grad``; it
fills ``setup.saved``) and its backward (a vector–Jacobian product returning `Gradients`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from torch_diffavatar.sim.adjoint.common import DrapeSetup, Gradients
from torch_diffavatar.sim.adjoint.equilibrium import (
    EquilibriumOptions,
    equilibrium_backward,
    equilibrium_forward,
)
from torch_diffavatar.sim.adjoint.trajectory import TrajectoryOptions, trajectory_backward, trajectory_forward


@dataclass(frozen=True)
class Adjoint:
    """One adjoint: its options type, forward and backward."""

    options: type
    forward: Callable
    backward: Callable


ADJOINTS: dict[str, Adjoint] = {
    "trajectory": Adjoint(TrajectoryOptions, trajectory_forward, trajectory_backward),
    "equilibrium": Adjoint(EquilibriumOptions, equilibrium_forward, equilibrium_backward),
}

__all__ = ["ADJOINTS", "Adjoint", "DrapeSetup", "EquilibriumOptions", "Gradients", "TrajectoryOptions"]
