"""The rest pattern's regularizers as one fused autograd node: value and gradient from the C++ kernels.

A fit's proximal step (`fit.rest_prox`) minimises the weighted rest terms (`FitObjective.rest_loss`) around
Adam's step with L-BFGS, ~40 evaluations per iteration. Built as autograd graphs of the loss functions of
`torch_diffavatar.losses` (seam length, curvature, rest area with the darts, rest shape) and of
`torch_diffavatar.opening_lengths` (the openings' length and split), an evaluation with its backward cost
~4 ms on the demo's dress (2,158 panel vertices), almost all of it the overhead of ~200 small tensor ops:
~6 s of the demo's fit. The kernels ``torch.ops.diffavatar.rest_seam_length``, ``rest_curvature``,
``rest_triangle_hinges`` and ``rest_openings`` (``csrc/rest_terms.cpp``) each return the weighted sum and
its gradient in one pass; `fused_rest_terms` adds them up under one `torch.autograd.Function`, whose
backward scales the stored gradient. The loss functions are their PyTorch twins (tests compare values and
gradients; ``gradcheck`` checks the fused node against finite differences).

`fused_rest_terms` is first-order (no double backward) and CPU-only; `rest_kernels_available` says when a
caller may use it.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import torch
from torch.autograd.function import once_differentiable

from torch_diffavatar.sim.ops import extension_op

__all__ = ["RestKernelCall", "fused_rest_terms", "opening_slots", "rest_kernels_available"]

# (kernel name, its arguments after ``uv``): e.g. ("rest_seam_length", (segments, weight))
RestKernelCall = tuple[str, tuple]

KERNELS = ("rest_seam_length", "rest_curvature", "rest_triangle_hinges", "rest_openings")


def rest_kernels_available(rest_uv: torch.Tensor) -> bool:
    """Whether `fused_rest_terms` can evaluate at ``rest_uv``: the compiled kernels exist and ``rest_uv`` is
    one (V, 2) float32/float64 CPU pattern (a batch, another device or dtype take the loss functions)."""
    return (
        rest_uv.dim() == 2
        and rest_uv.device.type == "cpu"
        and rest_uv.dtype in (torch.float32, torch.float64)
        and all(extension_op(name) is not None for name in KERNELS)
    )


def opening_slots(
    edges: Sequence[torch.Tensor], panels: Sequence[torch.Tensor], shares: Sequence[torch.Tensor]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The openings as ``rest_openings`` takes them: every opening's (L_k, 2) rest ``edges``, the panel of
    each edge numbered within its opening (``panels``, `opening_lengths.rest_loop_panels`) and the
    template's share of each of its panels (``shares``, `opening_lengths.rest_loop_shares`) become the
    edges of all (L, 2), each edge's slot (L,) (its panel, numbered over all openings), each slot's opening
    (S,) and the shares of all slots (S,)."""
    offsets = itertools.accumulate((len(s) for s in shares), initial=0)
    slot = torch.cat([p + o for p, o in zip(panels, offsets, strict=False)])
    slot_opening = torch.cat([torch.full((len(s),), k) for k, s in enumerate(shares)])
    return torch.cat(list(edges)), slot, slot_opening, torch.cat(list(shares))


class _FusedRestTerms(torch.autograd.Function):
    """() Σ over ``calls`` of each kernel's weighted value at ``uv`` (V, 2) [m]; backward: the kernels'
    gradient (V, 2) times the incoming one."""

    @staticmethod
    def forward(ctx, uv: torch.Tensor, calls: Sequence[RestKernelCall]) -> torch.Tensor:
        uv_c = uv.detach().contiguous()
        value = uv.new_zeros(())
        grad = torch.zeros_like(uv_c)
        for name, args in calls:
            v, g = extension_op(name)(uv_c, *args)
            value = value + v
            grad = grad + g
        ctx.save_for_backward(grad)
        return value

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out: torch.Tensor):
        (grad,) = ctx.saved_tensors
        return grad * grad_out, None


def fused_rest_terms(rest_uv: torch.Tensor, calls: Sequence[RestKernelCall]) -> torch.Tensor:
    """() the sum of the kernels' weighted values at ``rest_uv`` (V, 2) [m], differentiable in ``rest_uv``
    (first order). ``calls``: (kernel name, its arguments after ``uv``), the constant tensors contiguous,
    on the CPU, in ``rest_uv``'s dtype (indices int64); check `rest_kernels_available` first."""
    return _FusedRestTerms.apply(rest_uv, list(calls))
