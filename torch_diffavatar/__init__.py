"""torch_diffavatar: simulation-ready avatar assets from one noisy scan, through differentiable XPBD cloth."""

__version__ = "0.1.0"
