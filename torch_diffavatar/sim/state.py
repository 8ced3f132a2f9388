"""The cloth state: only what changes during a simulation."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class ClothState:
    """Positions and velocities of the simulated vertices.

    Attributes:
        x: (Vs, 3) positions [m].
        v: (Vs, 3) velocities [m/s].
        linearization: how the equilibrium at x moves with the drape's inputs, when x is the end of an
            equilibrium-adjoint drape whose backward ran (`sim.adjoint.linearization.Linearization`, from
            that drape's ``stats["linearization"]``): the next drape from this state starts at the
            predicted equilibrium. None otherwise.
    """

    x: torch.Tensor
    v: torch.Tensor
    linearization: object | None = None

    def __post_init__(self):
        if self.x.ndim != 2 or self.x.shape[-1] != 3 or self.v.shape != self.x.shape:
            raise ValueError(
                f"ClothState needs x and v of the same shape (Vs, 3), got {tuple(self.x.shape)} and "
                f"{tuple(self.v.shape)}"
            )

    def clone(self) -> ClothState:
        return ClothState(self.x.clone(), self.v.clone(), self.linearization)

    def to(self, device=None, dtype=None) -> ClothState:
        x, v = self.x.to(device=device, dtype=dtype), self.v.to(device=device, dtype=dtype)
        return ClothState(x, v, self.linearization)
