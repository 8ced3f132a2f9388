"""Loading the Anny body model in the one configuration the project uses.

Every Anny configuration builds its own ~800 MB cache on first use (~80 s), so the whole project uses
exactly one: the single watertight component (no eyes, no tongue). The cache goes where
``ANNY_CACHE_DIR`` says (Anny reads that variable itself; default ``~/.cache/anny``; set but empty, the
default too, `_default_cache_for_an_empty_variable`).
"""

from __future__ import annotations

import os
import pathlib

import torch

from torch_diffavatar.body.frames import anny_to_world

ANNY_TOPOLOGY = "anny-noeyes-notongue"


def _quiet_warp() -> None:
    """Warp (Anny's skinning backend) prints its banner on stdout at init, which would break the
    one-line ``--json`` output of our commands; warnings still reach stderr."""
    try:
        import warp
    except ImportError:
        return
    warp.config.log_level = warp.LOG_WARNING


def _default_cache_for_an_empty_variable() -> None:
    """Anny reads ``ANNY_CACHE_DIR`` set but empty as the working directory, and writes its ~800 MB cache
    there (into a source checkout, where `git add` takes it): take its default instead."""
    from anny import paths

    if os.environ.get("ANNY_CACHE_DIR") == "" and paths.get_anny_cache_path() == pathlib.Path(""):
        paths.set_anny_cache_path(paths.DEFAULT_CACHE_PATH)


def load_anny(dtype: torch.dtype = torch.float64, device: torch.device | str | None = None):
    """Instantiate ``anny.Anny`` in the project's single configuration.

    Returns:
        an ``anny.Anny`` module (13,348 vertices, 26,692 triangles, 104 bones) on ``device``/``dtype``.
    """
    _quiet_warp()
    _default_cache_for_an_empty_variable()
    import anny

    model = anny.Anny(topology=ANNY_TOPOLOGY)
    return model.to(device=device, dtype=dtype)


def default_body_mesh(
    dtype: torch.dtype = torch.float64, device: torch.device | str | None = None, anny_model=None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The default body for draping: Anny at default phenotypes (all 0.5) in its A-pose.

    Args:
        anny_model: an already loaded model from `load_anny` (saves the load time).

    Returns:
        verts: (Vb, 3) [m] in the world frame (Y up, facing +Z, feet on y = 0).
        faces: (Fb, 3) int64, outward-facing, one closed watertight component.
    """
    model = load_anny(dtype=dtype, device=device) if anny_model is None else anny_model
    with torch.no_grad():
        verts = anny_to_world(model()["vertices"][0].to(dtype))
    verts = verts - verts.new_tensor([0.0, 1.0, 0.0]) * verts[:, 1].min()
    return verts, model.faces.to(device=verts.device)
