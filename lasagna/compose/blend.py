"""Blend modes over an opaque backdrop: one pure function per mode, gathered in ``BLEND_FUNC``.

Notation of W3C Compositing and Blending Level 1: ``Cb`` the backdrop colour, ``Cs`` the source
colour, ``α`` the source's effective alpha (layer alpha × mask × opacity). The canvas is opaque
(αb = 1), so the spec's blending step ``Cs' = (1 − αb)·Cs + αb·B(Cb, Cs)`` gives ``Cs' = B(Cb, Cs)``
and its source-over step ``co = αs·Cs' + (1 − αs)·Cb`` gives ``Co = Cb + α·(B(Cb, Cs) − Cb)``:

==========  ==================  =========================================================
mode        B(Cb, Cs)           result, and the form computed here
==========  ==================  =========================================================
normal      Cs                  Cb + α(Cs − Cb)           ``lerp(Cb, Cs, α)``
multiply    Cb·Cs               Cb + α(Cb·Cs − Cb)        ``Cb·(1 + α(Cs − 1))``
screen      Cb + Cs − Cb·Cs     Cb + α(Cs − Cb·Cs)        ``Cb·(1 − αCs) + αCs``
plus        (Porter–Duff plus)  Cb + α·Cs                 ``addcmul(Cb, Cs, α)``
==========  ==================  =========================================================

Shapes: ``Cb`` is ``(..., C, h, w)`` with C ∈ {1, 3}; ``Cs`` is ``(..., 1 | C, h, w)`` — one
channel broadcasts over the backdrop's channels (the Lasagna paper's "multiply luminosity" shading
layer, f(x, y) = x·y); ``a`` is ``(..., 1, h, w)``, a 0-d tensor, a Python number in [0, 1], or
``None`` for an opaque source (α = 1; then normal returns ``Cs`` exactly and multiply ``Cb·Cs``).
Leading batch dimensions broadcast. The multiply factor ``1 + α(Cs − 1)`` is computed on ``Cs``'s
channels (one for a luminosity layer) before it broadcasts over RGB: a third of the work.

In-place fast paths (``normal_``, ``multiply_``, ``screen_``, ``plus_``, in ``BLEND_INPLACE``)
overwrite ``Cb`` and return it. They run the same kernels in the same order as the pure functions,
so their results are bitwise equal (tested); the renderer uses them when no gradient is needed.

NaN policy: IEEE arithmetic, no masking. A NaN in ``Cb``, ``Cs`` or ``α`` at a pixel makes that
pixel NaN even where α = 0 (``0·NaN = NaN``): hiding it would hide corrupt input, and a select per
pixel costs a pass. By construction an opaque normal source (``a=None``) returns ``Cs`` and so does
not carry NaNs of the backdrop below it. (The renderer never reads a layer it culls; its identity
test requires finite colour, so culling cannot make a NaN disappear — see ``layer.py``.)

Clamp policy (``clamp`` of a document, applied by the renderer, not by these functions):
``"layer"`` clamps to [0, 1] after each blend, as GIMP, Krita and Photoshop do on 8/16-bit images;
``"output"`` clamps once at the end; ``None`` never clamps (learned layers keep their gradients).
Under ``"layer"`` a clamp is skipped when it provably cannot change a value: ``clamp_needed`` says,
for a source whose values lie in ``[lo, hi]`` over a backdrop in [0, 1] with α ∈ [0, 1], which
side can leave [0, 1]. The result is a convex combination of in-range values for normal (of Cb and
Cs), multiply (of 0 and Cb, when 0 ≤ lo and hi ≤ 1) and screen (of Cb and 1), and floating-point
rounding is monotone and represents 0 and 1 exactly, so the rounded result stays in [0, 1] as well.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from lasagna.document.blend import BLEND_MODES as BLEND_MODES  # the names are declared there, once
from lasagna.errors import LasagnaError

Alpha = Tensor | float | None


def broadcast_shape(*shapes: tuple[int, ...]) -> tuple[int, ...]:
    """``torch.broadcast_shapes`` in plain Python (that one costs ~30 µs a call, too much per band).

    Raises ``RuntimeError`` like it when two sizes differ and neither is 1.
    """
    n = max((len(s) for s in shapes), default=0)
    out = [1] * n
    for s in shapes:
        for i, d in enumerate(s, start=n - len(s)):
            if d != 1:
                if out[i] != 1 and out[i] != d:
                    raise RuntimeError(f"shapes {shapes} do not broadcast")
                out[i] = d
    return tuple(out)


# ---- kernels: no checks; the renderer calls these in its inner loop --------------------------


def _normal(Cb: Tensor, Cs: Tensor, a: Alpha) -> Tensor:
    if a is None:  # α = 1: the result is Cs exactly (lerp would give NaN for an infinite Cb).
        shape = broadcast_shape(Cb.shape, Cs.shape)
        return Cs.expand(shape).clone(memory_format=torch.contiguous_format)
    return torch.lerp(Cb, Cs, a)


def _normal_(out: Tensor, Cs: Tensor, a: Alpha) -> Tensor:
    return out.copy_(Cs) if a is None else out.lerp_(Cs, a)


def _factor(Cs: Tensor, a: Alpha) -> Tensor:
    # 1 + α(Cs − 1) on Cs's own channels (one for a luminosity multiplier), before broadcasting.
    return torch.mul(Cs - 1.0, a).add_(1.0)


def _multiply(Cb: Tensor, Cs: Tensor, a: Alpha) -> Tensor:
    return Cb * Cs if a is None else Cb * _factor(Cs, a)


def _multiply_(out: Tensor, Cs: Tensor, a: Alpha) -> Tensor:
    return out.mul_(Cs if a is None else _factor(Cs, a))


def _screen(Cb: Tensor, Cs: Tensor, a: Alpha) -> Tensor:
    s = Cs if a is None else Cs * a
    return Cb * (1.0 - s) + s


def _screen_(out: Tensor, Cs: Tensor, a: Alpha) -> Tensor:
    s = Cs if a is None else Cs * a
    return out.mul_(1.0 - s).add_(s)


def _plus(Cb: Tensor, Cs: Tensor, a: Alpha) -> Tensor:
    if a is None:
        return Cb + Cs
    if isinstance(a, Tensor):
        return torch.addcmul(Cb, Cs, a)
    return torch.add(Cb, Cs, alpha=a)


def _plus_(out: Tensor, Cs: Tensor, a: Alpha) -> Tensor:
    if a is None:
        return out.add_(Cs)
    if isinstance(a, Tensor):
        return out.addcmul_(Cs, a)
    return out.add_(Cs, alpha=a)


KERNELS: dict[str, Callable[[Tensor, Tensor, Alpha], Tensor]] = {
    "normal": _normal,
    "multiply": _multiply,
    "screen": _screen,
    "plus": _plus,
}
KERNELS_INPLACE: dict[str, Callable[[Tensor, Tensor, Alpha], Tensor]] = {
    "normal": _normal_,
    "multiply": _multiply_,
    "screen": _screen_,
    "plus": _plus_,
}


# ---- checks ------------------------------------------------------------------------------------


def check_blend_name(name: object, where: str = "blend") -> str:
    """Return ``name`` if it is a blend mode; raise ``LasagnaError`` listing the modes of the kernel table."""
    if name not in KERNELS:
        raise LasagnaError(f"unknown blend {name!r}; expected one of {', '.join(KERNELS)}", where=where)
    return name  # type: ignore[return-value]


def _shape(t: Tensor) -> str:
    return "(" + ", ".join(str(s) for s in t.shape) + ")"


def _check(op: str, Cb: Tensor, Cs: Tensor, a: Alpha, inplace: bool) -> None:
    for name, t in (("Cb", Cb), ("Cs", Cs)):
        if not isinstance(t, Tensor):
            raise LasagnaError(f"{name} is a {type(t).__name__}; expected a tensor (..., C, h, w)", where=op)
        if not t.is_floating_point():
            raise LasagnaError(f"{name} has dtype {t.dtype}; expected a floating-point tensor", where=op)
        if t.ndim < 3:
            raise LasagnaError(f"{name} has shape {_shape(t)}; expected (..., C, h, w)", where=op)
    c = Cb.shape[-3]
    if c not in (1, 3):
        raise LasagnaError(f"Cb has {c} channels (shape {_shape(Cb)}); expected 1 or 3", where=op)
    if Cs.shape[-3] not in (1, c):
        raise LasagnaError(
            f"Cs has {Cs.shape[-3]} channels (shape {_shape(Cs)}); expected 1 (broadcast over the "
            f"backdrop's channels) or {c}",
            where=op,
        )
    if Cs.shape[-2:] != Cb.shape[-2:]:
        raise LasagnaError(
            f"Cs is {Cs.shape[-2]}x{Cs.shape[-1]} but Cb is {Cb.shape[-2]}x{Cb.shape[-1]}; expected the "
            "same height and width (crop the layer to the backdrop's rectangle first)",
            where=op,
        )
    if Cs.dtype != Cb.dtype:
        raise LasagnaError(f"Cs has dtype {Cs.dtype} but Cb has {Cb.dtype}; expected one dtype", where=op)
    batch = [Cb.shape[:-3], Cs.shape[:-3]]
    if isinstance(a, Tensor):
        if not a.is_floating_point():
            raise LasagnaError(f"a has dtype {a.dtype}; expected a floating-point tensor", where=op)
        if a.dtype != Cb.dtype:
            raise LasagnaError(f"a has dtype {a.dtype} but Cb has {Cb.dtype}; expected one dtype", where=op)
        if a.ndim > 0:
            if a.ndim < 3 or a.shape[-3] != 1 or a.shape[-2:] not in (Cb.shape[-2:], (1, 1)):
                raise LasagnaError(
                    f"a has shape {_shape(a)}; expected (..., 1, {Cb.shape[-2]}, {Cb.shape[-1]}), "
                    "(..., 1, 1, 1) or a 0-d tensor",
                    where=op,
                )
            batch.append(a.shape[:-3])
    elif a is not None:
        if isinstance(a, bool) or not isinstance(a, (int, float)):
            raise LasagnaError(f"a is a {type(a).__name__}; expected a tensor, a number or None", where=op)
        if not 0.0 <= a <= 1.0:
            raise LasagnaError(f"a = {a!r}; expected a number in [0, 1]", where=op)
    try:
        out_batch = broadcast_shape(*batch)
    except RuntimeError:
        raise LasagnaError(
            "leading batch dimensions "
            + ", ".join(str(tuple(b)) for b in batch)
            + " do not broadcast; expected equal sizes or 1",
            where=op,
        ) from None
    if inplace and tuple(out_batch) != tuple(Cb.shape[:-3]):
        raise LasagnaError(
            f"the inputs broadcast to batch {tuple(out_batch)} but Cb has batch {tuple(Cb.shape[:-3])}; "
            "an in-place blend cannot grow its output (use the pure function)",
            where=op,
        )


# ---- the public functions ----------------------------------------------------------------------


def normal(Cb: Tensor, Cs: Tensor, a: Alpha = None) -> Tensor:
    """Normal (source-over): ``Cb + α(Cs − Cb)``, computed as ``lerp(Cb, Cs, α)``; ``Cs`` if α is None."""
    _check("normal", Cb, Cs, a, inplace=False)
    return _normal(Cb, Cs, a)


def multiply(Cb: Tensor, Cs: Tensor, a: Alpha = None) -> Tensor:
    """Multiply: ``Cb + α(Cb·Cs − Cb)``, computed as ``Cb·(1 + α(Cs − 1))``; ``Cb·Cs`` if α is None."""
    _check("multiply", Cb, Cs, a, inplace=False)
    return _multiply(Cb, Cs, a)


def screen(Cb: Tensor, Cs: Tensor, a: Alpha = None) -> Tensor:
    """Screen: ``Cb + α(Cs − Cb·Cs)``, computed as ``Cb·(1 − αCs) + αCs``."""
    _check("screen", Cb, Cs, a, inplace=False)
    return _screen(Cb, Cs, a)


def plus(Cb: Tensor, Cs: Tensor, a: Alpha = None) -> Tensor:
    """Plus (Porter–Duff "plus"/"lighter" with an opaque backdrop): ``Cb + α·Cs``."""
    _check("plus", Cb, Cs, a, inplace=False)
    return _plus(Cb, Cs, a)


def normal_(Cb: Tensor, Cs: Tensor, a: Alpha = None) -> Tensor:
    """In-place ``normal``: ``Cb.lerp_(Cs, α)`` (``Cb.copy_(Cs)`` if α is None); returns ``Cb``."""
    _check("normal_", Cb, Cs, a, inplace=True)
    return _normal_(Cb, Cs, a)


def multiply_(Cb: Tensor, Cs: Tensor, a: Alpha = None) -> Tensor:
    """In-place ``multiply``: ``Cb.mul_(1 + α(Cs − 1))``, the factor on ``Cs``'s channels; returns ``Cb``."""
    _check("multiply_", Cb, Cs, a, inplace=True)
    return _multiply_(Cb, Cs, a)


def screen_(Cb: Tensor, Cs: Tensor, a: Alpha = None) -> Tensor:
    """In-place ``screen``: ``Cb.mul_(1 − αCs).add_(αCs)``; returns ``Cb``."""
    _check("screen_", Cb, Cs, a, inplace=True)
    return _screen_(Cb, Cs, a)


def plus_(Cb: Tensor, Cs: Tensor, a: Alpha = None) -> Tensor:
    """In-place ``plus``: ``Cb.addcmul_(Cs, α)``; returns ``Cb``."""
    _check("plus_", Cb, Cs, a, inplace=True)
    return _plus_(Cb, Cs, a)


BLEND_FUNC: dict[str, Callable[[Tensor, Tensor, Alpha], Tensor]] = {
    "normal": normal,
    "multiply": multiply,
    "screen": screen,
    "plus": plus,
}
BLEND_INPLACE: dict[str, Callable[[Tensor, Tensor, Alpha], Tensor]] = {
    "normal": normal_,
    "multiply": multiply_,
    "screen": screen_,
    "plus": plus_,
}


def get_blend(name: str, inplace: bool = False) -> Callable[[Tensor, Tensor, Alpha], Tensor]:
    """The blend function called ``name`` (in-place variant if ``inplace``); raises on unknown names."""
    check_blend_name(name)
    return (BLEND_INPLACE if inplace else BLEND_FUNC)[name]


def clamp_needed(blend: str, lo: float, hi: float) -> tuple[bool, bool]:
    """Which side (below 0, above 1) a ``clamp="layer"`` clamp can change after this blend.

    ``[lo, hi]`` bounds the source values (the layer's measured min/max, or its declared range for a
    layer that carries gradients); the backdrop is in [0, 1] and α in [0, 1]. See the module docstring
    for why normal, multiply and screen of in-range values need no clamp. Plus adds ``α·Cs`` to a
    backdrop that may already be 1, so any positive source can overflow. Unknown bounds (NaN) clamp.
    """
    check_blend_name(blend)
    if not (lo == lo and hi == hi):  # NaN: nothing is proven
        return True, True
    if blend == "plus":
        return lo < 0.0, hi > 0.0
    return lo < 0.0, hi > 1.0
