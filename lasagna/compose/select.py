"""A fast, exact per-pixel select for the compose kernels: ``torch.where`` as arithmetic.

On this CPU build ``torch.where`` — like any op that reads a bool tensor — runs ~20× slower than an
arithmetic pass: over a 2048² RGB float32 canvas in 2^18-pixel bands, ``where`` takes 40 ms and a
comparison into a bool 3.9 ms, against 0.9 ms for the comparison written into a float tensor and 1.9 ms
for ``lerp`` (one thread; ``benchmarks/compositing.py``'s ``mode_ms`` shows the effect per mode). The
piecewise formulas of W3C Compositing Level 1 (hard-light, overlay, soft-light, colour dodge and burn,
ClipColor) and the sRGB curves select per pixel, so the select was most of their cost.

``step(op, x, t)`` is the comparison ``x op t`` as 0./1. in ``x``'s dtype (no gradient). ``pick(w, a, b)``
is ``where(w, a, b)`` computed as ``lerp(b, a, w)``: for w ∈ {0, 1} and finite a and b it returns exactly
``b`` (b + 0·(a − b)) or exactly ``a`` (a − (a − b)·0), and its gradient is the select's: w·g to ``a`` and
(1 − w)·g to ``b`` (tested bit for bit against ``torch.where``, values and gradients). The sign of a zero
may differ (−0 + 0 = +0), which no comparison sees. Both branches must be finite: where either is ±inf the
lerp gives NaN (0·inf) where ``torch.where`` gave the selected value. The kernels' branches are finite for
every finite input below ~1e15 in magnitude (products of two values, a soft-light polynomial of min(Cb, ¼),
quotients with saturated or clamped denominators; the sRGB decode's x^2.4 overflows float32 above ~1e16);
colours and multipliers are O(1) (the largest range a bundled preset uses is [0, 4]), and at such
magnitudes most of the ``torch.where`` forms overflowed in their *selected* branch as well.

Where it is not used: half precision (float16, bfloat16) keeps ``torch.where`` (``FAST_DTYPES``). There a
branch that is not selected can overflow to ±inf for a finite input (a soft-light polynomial of a large
backdrop, a quotient near a pole), and 0·inf would turn a finite pixel into NaN; in float32 and float64
every branch of the kernels is finite for finite input of any magnitude the package admits (the kernels
clamp their branches' domains, as ``torch.where`` needed for finite gradients anyway).
"""

from __future__ import annotations

import torch
from torch import Tensor

# dtypes where pick() is the lerp form; others use torch.where (see the module docstring).
FAST_DTYPES = (torch.float32, torch.float64)

_COMPARE = {"<=": torch.le, "<": torch.lt, ">=": torch.ge, ">": torch.gt, "==": torch.eq, "!=": torch.ne}


def step(op: str, x: Tensor, t: float) -> Tensor:
    """``x op t`` (op one of ``<= < >= > == !=``) as 0./1. in ``x``'s dtype; a bool tensor for half dtypes."""
    compare = _COMPARE[op]
    x = x.detach()
    if x.dtype not in FAST_DTYPES:
        return compare(x, t)
    return compare(x, t, out=torch.empty(x.shape, dtype=x.dtype, device=x.device))


def pick(w: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """``torch.where(w, a, b)`` for a mask ``w`` from ``step``: ``lerp(b, a, w)`` in float32/float64."""
    if w.dtype == torch.bool:
        return torch.where(w, a, b)
    return torch.lerp(b, a, w)


def as_value(w: Tensor, like: Tensor) -> Tensor:
    """A ``step`` mask as 0./1. values of ``like``'s dtype (the spec's "B = 1 where Cb ≠ 0" cases)."""
    return w.to(like.dtype) if w.dtype != like.dtype else w
