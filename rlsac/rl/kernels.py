"""The training networks' kernels: the dense products, ATen's (the record's) or oneDNN's, and the EdgeConv neighbour
max, eager (the record's) or compiled; one function of one name each.

Why a choice: in the portable numeric mode (rlsac.numerics) torch's matmuls go to MKL's vendor-independent branch
(``MKL_CBWR=COMPATIBLE``), about 3x slower on this machine than MKL's own; oneDNN, which the same mode pins to AVX2
(``ONEDNN_MAX_CPU_ISA``), chooses its kernels by instruction set, not vendor, and runs the SAC update's products
at full speed (benchmarks/sac_update.py). Its bytes differ from MKL's in the last bits, so the record's runs keep
``aten`` (TrainConf.kernels, its default); ``onednn`` is an option of new runs, measured and named where used.

    linear(x, w, b) -> x @ w.T + b    x (..., I), w (O, I), b (O,) or None -> (..., O)

The neighbour max (issue #46, item 3): eager PyTorch spends most of it moving a (k, P, C) gather through memory and,
backward, finding each maximum's neighbour one op at a time (15 ops per layer). ``compiled`` has torch.compile
(inductor: C++ loops, a C++ compiler at run time) fuse the gather with the max and its argmax, and the backward into
one scatter: the same first-winner rule in the same order, so the same bytes as ``eager`` on one thread (checked by
tests/test_kernels.py and benchmarks/sac_update.py), and faster: reports/speed_training.json.

    neighbour_max(b, nbr, k) -> (P, C)    b (P, C), nbr (k P,) neighbour rows, neighbour-major
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch
import torch.nn.functional as F

from rlsac.errors import RlsacError

KERNELS = ("aten", "onednn")
NEIGHBOUR_MAX = ("eager", "compiled")


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


class NeighbourMax(torch.autograd.Function):
    """b (P, C), nbr (k P) neighbour rows, neighbour-major (nbr[j P + p]) -> (P, C) max over each
    point's k neighbours.

    Forward: one gather into (k, P, C) and a max over its outer dimension (vectorised, unlike a max
    over the middle dimension of (P, k, C), and far unlike max-with-indices there: 55% of a SAC update).
    Backward (the gather kept from the forward): each output gradient goes to the first neighbour that
    reaches the max, one (P, C) scatter, instead of amax's backward over the whole gather (an equality
    mask, a count and a product there, then a (P k, C) index_add). SAC update at batch 64, CPU time:
    1.4x (lines) and 1.55x (fundamental) faster than the reference forward. Ties (equal features) give
    the gradient to the first winner where amax splits it: the same total into the tied rows."""

    @staticmethod
    def forward(ctx, b: torch.Tensor, nbr: torch.Tensor, k: int) -> torch.Tensor:
        g = b.index_select(0, nbr).view(k, -1, b.shape[1])
        values = g.amax(dim=0)
        if ctx.needs_input_grad[0]:
            ctx.save_for_backward(g, nbr, values)
            ctx.rows = b.shape[0]
        return values

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        g, nbr, values = ctx.saved_tensors
        k = g.shape[0]
        rows = nbr.view(k, -1, 1)
        winner = rows[k - 1].expand_as(values)
        for j in range(k - 2, -1, -1):  # the first neighbour reaching the max wins
            winner = torch.where(g[j] == values, rows[j], winner)
        return grad.new_zeros(ctx.rows, grad.shape[1]).scatter_add_(0, winner, grad), None, None


def _max_with_winner(b: torch.Tensor, nbr: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """-> the max over each point's k neighbours (P, C) and the first neighbour (0..k-1) that reaches it."""
    return b.index_select(0, nbr).view(k, -1, b.shape[1]).max(dim=0)


def _scatter_to_winner(grad: torch.Tensor, winner: torch.Tensor, nbr: torch.Tensor, rows: int, k: int) -> torch.Tensor:
    """grad (P, C) -> (rows, C): each output gradient added to the row of its winning neighbour, in point order."""
    to = nbr.view(k, -1, 1).expand(k, *winner.shape).gather(0, winner[None])[0]
    return grad.new_zeros(rows, grad.shape[1]).scatter_add_(0, to, grad)


@functools.cache
def _compiled(fn):
    """fn through torch.compile, once per process; one thread, so the scatter adds in point order (inductor's
    parallel scatter adds atomically, in any order: other last bits)."""
    return torch.compile(fn, options={"cpp.threads": 1})


class CompiledNeighbourMax(torch.autograd.Function):
    """NeighbourMax's function and bytes (the first neighbour reaching the max takes the gradient) in two compiled
    kernels: the max with its winner forward, the scatter backward (no (k, P, C) gather kept between them)."""

    @staticmethod
    def forward(ctx, b: torch.Tensor, nbr: torch.Tensor, k: int) -> torch.Tensor:
        values, winner = _compiled(_max_with_winner)(b, nbr, k)
        if ctx.needs_input_grad[0]:
            ctx.save_for_backward(nbr, winner)
            ctx.rows, ctx.k = b.shape[0], k
        return values

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        nbr, winner = ctx.saved_tensors
        return _compiled(_scatter_to_winner)(grad.contiguous(), winner, nbr, ctx.rows, ctx.k), None, None


def compiler_missing() -> str:
    """'' where torch.compile can build CPU kernels here, else why not (inductor calls a C++ compiler)."""
    import shutil

    return "" if shutil.which("g++") or shutil.which("c++") else "no C++ compiler (g++ or c++) on PATH"


def neighbour_max_for(name: str) -> Callable[[torch.Tensor, torch.Tensor, int], torch.Tensor]:
    """The ``neighbour_max`` of ``name`` (one of NEIGHBOUR_MAX)."""
    if name == "eager":
        return NeighbourMax.apply
    if name == "compiled":
        why = compiler_missing()
        if why:
            raise RlsacError(f"neighbour_max compiled needs torch.compile's C++ compiler: {why}")
        return _compiled_apply
    raise ValueError(f"neighbour_max must be one of {', '.join(NEIGHBOUR_MAX)}, got {name!r}")


def _compiled_apply(b: torch.Tensor, nbr: torch.Tensor, k: int) -> torch.Tensor:
    if b.device.type != "cpu":  # inductor's CPU kernels; a GPU runs the eager ops fast
        return NeighbourMax.apply(b, nbr, k)
    return CompiledNeighbourMax.apply(b, nbr, k)
