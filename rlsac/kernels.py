"""The dense products of the training networks: ATen's (the record's) or oneDNN's, one function of one name each.

Why a choice: in the portable numeric mode (rlsac.numerics) torch's matmuls go to MKL's vendor-independent branch
(``MKL_CBWR=COMPATIBLE``), about 3x slower on this machine than MKL's own; oneDNN, which the same mode pins to AVX2
(``ONEDNN_MAX_CPU_ISA``), chooses its kernels by instruction set, not vendor, and runs the SAC update's products
at full speed (benchmarks/sac_update.py). Its bytes differ from MKL's in the last bits, so the record's runs keep
``aten`` (TrainConf.kernels, its default); ``onednn`` is an option of new runs, measured and named where used.

    linear(x, w, b) -> x @ w.T + b    x (..., I), w (O, I), b (O,) or None -> (..., O)
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F

KERNELS = ("aten", "onednn")


def _mm(a: torch.Tensor, b_t: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
    """a (R, I) @ b_t.T (+ bias): oneDNN's inner-product primitive, b_t (O, I) as a linear layer's weight."""
    return torch.ops.mkldnn._linear_pointwise(a, b_t, bias, "none", [], "")


class _OneDNNLinear(torch.autograd.Function):
    """y = x w^T + b with oneDNN's products forward and backward (grad_x = g w, grad_w = g^T x, grad_b = sum g)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, w: torch.Tensor, b: torch.Tensor | None) -> torch.Tensor:
        x2 = x.reshape(-1, x.shape[-1])
        ctx.save_for_backward(x2, w)
        ctx.shape, ctx.has_bias = x.shape, b is not None
        return _mm(x2, w, b).view(*x.shape[:-1], w.shape[0])

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        x2, w = ctx.saved_tensors
        g = grad.reshape(-1, w.shape[0])
        gx = gw = gb = None
        if ctx.needs_input_grad[0]:
            gx = _mm(g, w.t().contiguous()).view(ctx.shape)
        if ctx.needs_input_grad[1]:
            gw = _mm(g.t().contiguous(), x2.t())
        if ctx.has_bias and ctx.needs_input_grad[2]:
            gb = g.sum(0)
        return gx, gw, gb


def onednn_linear(x: torch.Tensor, w: torch.Tensor, b: torch.Tensor | None = None) -> torch.Tensor:
    if x.device.type != "cpu":  # oneDNN is the CPU's; a GPU's products are fast already
        return F.linear(x, w, b)
    return _OneDNNLinear.apply(x, w.contiguous(), b)


def linear_for(name: str) -> Callable[..., torch.Tensor]:
    """The ``linear`` of kernels ``name`` (one of KERNELS)."""
    if name == "aten":
        return F.linear
    if name == "onednn":
        return onednn_linear
    raise ValueError(f"kernels must be one of {', '.join(KERNELS)}, got {name!r}")
