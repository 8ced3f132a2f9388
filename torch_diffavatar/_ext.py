"""Loads the optional C++ extension (`torch_diffavatar._C`), which registers `torch.ops.diffavatar.*`.

The package works without it (every op has a PyTorch reference twin); we say so once, on first use.
"""

from __future__ import annotations

import warnings

_STATE: dict[str, object] = {}


def has_extension() -> bool:
    """True when the compiled ops are importable; warns once when they are not."""
    if "ok" not in _STATE:
        try:
            import torch  # noqa: F401  (loads libc10/libtorch, which _C links against)

            from torch_diffavatar import _C  # noqa: F401  (importing registers the ops)

            _STATE["ok"] = True
        except ImportError as exc:
            _STATE["ok"] = False
            warnings.warn(
                "torch_diffavatar: C++ extension not built "
                f"({exc}); using the slower PyTorch reference kernels. "
                "Build it with `pip install --no-build-isolation -e .`.",
                RuntimeWarning,
                stacklevel=2,
            )
    return bool(_STATE["ok"])
