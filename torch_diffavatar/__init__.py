"""torch_diffavatar: simulation-ready avatar assets from one noisy scan, through differentiable XPBD cloth."""

__version__ = "0.1.0"

from torch_diffavatar.sim.differentiable import drape  # noqa: E402

__all__ = ["__version__", "drape"]
