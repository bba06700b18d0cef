"""Fused blend kernels (opt-in): each W3C mode's formula compiled into one loop by ``torch.compile``.

In eager PyTorch a piecewise mode is a chain of elementwise passes, each writing a band-sized
temporary: overlay and hard-light about 8, colour dodge and burn about 10, soft-light about 18, the
non-separable four 25–40 (``blend.py``). Inductor, ``torch.compile``'s CPU back end, turns the whole
``lerp(Cb, B(Cb, Cs), α)`` of a mode into one C++/OpenMP loop that reads each input once and writes
the band in place. Measured on this project's box (2 vCPU AMD EPYC, torch 2.13.0+cpu, 2048² RGB in
bands, 2 threads): overlay 12.4 → 2.7 ms opaque, 11.9 → 3.6 ms with a per-pixel α; see
``benchmarks/compositing.py`` (``mode_ms_fused``) for every mode.

Opt-in, because compiling costs seconds per mode, dtype and α kind (a Python float α is passed as a 0-d
tensor so it is one kind): it pays in a long-lived process that composites large stacks often (an
editor, a training loop over big canvases, a batch of renders), not in one ``lasagna composite`` call.
Inductor keeps compiled kernels in its on-disk cache: with a cold cache a mode takes 3–12 s, with a warm
one 0.1–1 s (the first mode of a process ~2.5 s, dynamo's own start-up). Turn it on with
``set_fused(True)`` or ``LASAGNA_FUSED=1`` in the environment; it needs a C++ compiler at run time (the
one inductor finds, usually ``g++``). If compiling a mode fails, that mode warns once and runs eagerly
from then on.

Where it is used: the banded no-grad forward (``engine.run_fast``: ``render`` without gradients, the
``Renderer``, the forward of the banded backward). The autograd paths keep the eager kernels, whose
subgradients at the kinks are the documented ones (``blend.py``). The fused kernels compute the same
formulas in the same order; inductor may contract a multiply and an add into one fused multiply-add,
so results may differ from the eager kernels in the last bit (tested: within 2 ulp of float32 on
random stacks with every mode's kinks; float64 references within the eager kernels' own bounds).

The four basic modes (normal, multiply, screen, plus) are one or two in-place passes already
(``BLEND_INPLACE``) and are not compiled.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from lasagna.compose.blend import KERNELS_INPLACE, W3C_B, Alpha

ENV = "LASAGNA_FUSED"

# Each mode gets its own function object *and code object*: dynamo keys its compiled graphs on the code
# object and stops recompiling one after ``recompile_limit`` (8) variants, so one closure shared by 13
# modes × dtypes × α kinds would fall back to eager after the eighth.
_TEMPLATE = """
def fused_{ident}_(out, cs, a):
    b = B(out, cs)
    if a is None:
        out.copy_(b)
    else:
        out.copy_(torch.lerp(out, b, a))
"""

_state: dict[str, Any] = {"enabled": None}
_compiled: dict[str, Callable[[Tensor, Tensor, Tensor | None], None]] = {}
_wrappers: dict[str, Callable[[Tensor, Tensor, Alpha], Tensor]] = {}
_failed: set[str] = set()


def set_fused(on: bool) -> None:
    """Use the compiled kernels (True) or the eager ones (False) from now on, in this process."""
    _state["enabled"] = bool(on)


def fused_enabled() -> bool:
    """Whether fused kernels are on: ``set_fused``'s last word, else ``LASAGNA_FUSED`` (1/true/yes/on)."""
    if _state["enabled"] is None:
        _state["enabled"] = os.environ.get(ENV, "").strip().lower() in ("1", "true", "yes", "on")
    return bool(_state["enabled"])


def _make(blend: str) -> Callable[[Tensor, Tensor, Tensor | None], None]:
    ident = blend.replace("-", "_")
    namespace: dict[str, Any] = {"B": W3C_B[blend], "torch": torch}
    exec(compile(_TEMPLATE.format(ident=ident), f"<lasagna fused {blend}>", "exec"), namespace)  # noqa: S102
    fn = namespace[f"fused_{ident}_"]
    # dynamic: bands differ in height (the last one), regions in width; one graph serves them all.
    return torch.compile(fn, dynamic=True, fullgraph=True)


def fused_inplace(blend: str) -> Callable[[Tensor, Tensor, Alpha], Tensor] | None:
    """The compiled in-place kernel of a W3C mode, ``BLEND_INPLACE``'s signature; None where there is
    none: fused kernels off, a basic mode, or a mode whose compile failed before."""
    if blend not in W3C_B or blend in _failed or not fused_enabled():
        return None
    if blend not in _wrappers:
        _wrappers[blend] = _wrap(blend)
    return _wrappers[blend]


def _wrap(blend: str) -> Callable[[Tensor, Tensor, Alpha], Tensor]:
    def kernel_(out: Tensor, cs: Tensor, a: Alpha) -> Tensor:
        if blend in _failed:
            return KERNELS_INPLACE[blend](out, cs, a)
        if a is not None and not isinstance(a, Tensor):
            a = torch.tensor(float(a), dtype=out.dtype, device=out.device)
        try:
            fn = _compiled.get(blend)
            if fn is None:
                fn = _compiled[blend] = _make(blend)
            fn(out, cs, a)
        except Exception as e:  # noqa: BLE001 (any compiler failure: no C++ compiler, an inductor bug)
            # Compiling happens before the kernel writes anything, so ``out`` is untouched here.
            _failed.add(blend)
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            warnings.warn(
                f"fused kernel for blend {blend!r} could not be compiled ({type(e).__name__}: {first[:200]}); "
                "using the eager kernel",
                RuntimeWarning,
                stacklevel=2,
            )
            return KERNELS_INPLACE[blend](out, cs, a)
        return out

    return kernel_


def kernel_inplace(blend: str) -> Callable[[Tensor, Tensor, Alpha], Tensor]:
    """The in-place kernel the banded forward runs for ``blend``: fused where on and available, else eager."""
    return fused_inplace(blend) or KERNELS_INPLACE[blend]


__all__ = ["ENV", "fused_enabled", "fused_inplace", "kernel_inplace", "set_fused"]
