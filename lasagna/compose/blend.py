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

The other modes of W3C Compositing Level 1 (section 10) compute ``B(Cb, Cs)`` by the spec's formula
and return ``lerp(Cb, B, α)`` (``B`` itself for an opaque source), the form ``normal`` uses:

===========  ==============================================================================
overlay      hard-light(Cs, Cb)
darken       min(Cb, Cs)                       lighten  max(Cb, Cs)
color-dodge  0 if Cb = 0, else 1 if Cs ≥ 1, else min(1, Cb / (1 − Cs))
color-burn   1 if Cb = 1, else 0 if Cs ≤ 0, else 1 − min(1, (1 − Cb) / Cs)
hard-light   Cb·2Cs if Cs ≤ ½, else screen(Cb, 2Cs − 1)
soft-light   Cb − (1 − 2Cs)·Cb(1 − Cb) if Cs ≤ ½, else Cb + (2Cs − 1)(D(Cb) − Cb),
             D(Cb) = ((16Cb − 12)Cb + 4)Cb if Cb ≤ ¼, else √Cb
difference   |Cb − Cs|                         exclusion  Cb + Cs − 2·Cb·Cs
hue          SetLum(SetSat(Cs, Sat(Cb)), Lum(Cb))
saturation   SetLum(SetSat(Cb, Sat(Cs)), Lum(Cb))
color        SetLum(Cs, Lum(Cb))
luminosity   SetLum(Cb, Lum(Cs))
===========  ==============================================================================

Photoshop's other modes (its names; the formulas psd-tools' ``composite/blend.py`` pins against
Photoshop's own renders) are computed the same way, ``lerp(Cb, B, α)``: Photoshop applies a layer's pixel
alpha, mask and opacity as that lerp for every mode, the clamp of the linear modes inside ``B``:

=============  ===============================================================================
linear-burn    max(0, Cb + Cs − 1)
linear-dodge   min(1, Cb + Cs)   (Photoshop's "Linear Dodge (Add)"; W3C ``plus`` is Cb + α·Cs clamped
               after the blend: the two differ where 0 < α < 1 and Cb + Cs > 1)
subtract       max(0, Cb − Cs)
divide         min(1, Cb / Cs); at Cs ≤ 0: 0 where Cb ≤ 0, else 1
vivid-light    Cs ≤ ½: 1 − min(1, (1 − Cb) / 2Cs), 0 at Cs ≤ 0; else min(1, Cb / 2(1 − Cs)), 1 at
               Cs ≥ 1 (the source's pole wins, unlike color-burn/-dodge's backdrop cases)
linear-light   Cs ≤ ½: max(0, Cb + 2Cs − 1); else min(1, Cb + 2Cs − 1)
pin-light      Cs ≤ ½: min(Cb, 2Cs); else max(Cb, 2Cs − 1)
hard-mix       1 where Cb + Cs > 1, or Cb + Cs = 1 and Cb > ½; else 0 (a sum within ``HARD_MIX_TIE_EPS``
               of 1 is the tie: 8-bit codes a + b = 255 sum to 1 only to a few float32 ulps)
darker-color   Cs where Lum(Cs) < Lum(Cb), else Cb (whole pixels; Lum of section 10.3)
lighter-color  Cs where Lum(Cs) > Lum(Cb), else Cb
dissolve       Cs, with α replaced per pixel by 1 where u < α, else 0 (``dissolve_alpha``: u a hash of
               the layer's pixel coordinates and ``DISSOLVE_SEED``, so the pattern moves with the
               layer, and is the same in every band, engine and run)
=============  ===============================================================================

Gradients: hard-mix is piecewise constant (its gradient is 0 everywhere), dissolve's pattern is a step
in α (no gradient reaches alpha, mask or opacity; the colour's does); the clamps of linear-burn/-dodge,
subtract and linear-light pass the gradient where the bound is reached exactly (``clamp``'s convention);
divide's and vivid-light's quotients are only selected away from their poles, where their denominators
are ≥ the values they guard, and read 1 at the pole (as color-dodge does); darker/lighter-color at equal
Lum take Cb (Photoshop's strict comparison).

The non-separable four follow the spec's pseudo-code (section 10.3: Lum with weights 0.3, 0.59,
0.11, ClipColor, SetLum, Sat, SetSat), vectorised: SetSat maps each channel to (C − Cmin)·s /
(Cmax − Cmin), which sets the max to s, the min to 0 and scales the mid, as the spec's sorted form
does (ties included). A 1-channel source or backdrop is gray in RGB for them (expanded to three
channels; a gray backdrop gets channel 0 of the result, all three being equal).

Every per-pixel select of these formulas goes through ``lasagna.compose.select`` (``torch.where``'s value
and gradient as arithmetic: ~20× faster on CPU, bit for bit the same for finite branches).

Gradients at the kinks (subgradients, chosen so every gradient is finite — tested at the kinks):
color-dodge at Cs = 1 and color-burn at Cs = 0 are constant there (1 and 0: the derivative of the
saturated branch, 0), and their quotients are only evaluated with a denominator of 1 where they
are not selected (no epsilon needed: a denominator in (0, 1] near the kink makes the quotient large
but finite and the min saturates it, so its derivative is not selected either). hard-light, overlay
and soft-light at ½ take the ≤ branch. soft-light's √Cb is only selected for Cb > ¼ and reads
max(Cb, ¼) (√'s infinite slope at 0 never enters; D is C¹ at ¼ anyway). darken/lighten at Cb = Cs
split the gradient equally (``torch.minimum``/``maximum``), difference at Cb = Cs gives 0
(``abs``). SetSat of a gray (Cmax = Cmin) divides 0 by 1; ClipColor's denominators are kept ≥
``CLIP_COLOR_EPS`` (``lasagna.numerics``); its branches are strict (n < 0, x > 1), so at n = 0 or x = 1
the colour passes unchanged with derivative 1.

Shapes: ``Cb`` is ``(..., C, h, w)`` with C ∈ {1, 3}; ``Cs`` is ``(..., 1 | C, h, w)`` — one
channel broadcasts over the backdrop's channels (the Lasagna paper's "multiply luminosity" shading
layer, f(x, y) = x·y); ``a`` is ``(..., 1, h, w)``, a 0-d tensor, a Python number in [0, 1], or
``None`` for an opaque source (α = 1; then normal returns ``Cs`` exactly and multiply ``Cb·Cs``).
Leading batch dimensions broadcast. The multiply factor ``1 + α(Cs − 1)`` is computed on ``Cs``'s
channels (one for a luminosity layer) before it broadcasts over RGB: a third of the work.

In-place fast paths (``normal_``, ``multiply_``, ``screen_``, ``plus_``, and ``overlay_`` … for
every other mode, in ``BLEND_INPLACE``) overwrite ``Cb`` and return it (the W3C modes compute ``B``
out of place and then ``Cb.lerp_(B, α)``: one allocation fewer). They run the same kernels in the
same order as the pure functions, so their results are bitwise equal (tested); the renderer uses
them when no gradient is needed.

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
The same holds for darken, lighten and difference (``B`` is a min, a max or |Cb − Cs| of in-range
values, then a lerp). The other W3C modes are in [0, 1] in exact arithmetic only; their rounded ``B``
is not proven to be (a soft-light or a SetLum can land an ulp outside), so they always clamp.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from lasagna.compose.select import as_value, pick, step
from lasagna.document.blend import BLEND_MODES as BLEND_MODES  # the names are declared there, once
from lasagna.errors import LasagnaError
from lasagna.numerics import CLIP_COLOR_EPS, HARD_MIX_TIE_EPS

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


# ---- the other W3C modes: B(Cb, Cs) by the spec's formula, then lerp(Cb, B, α) ----------------------


def _hard_light_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    # Cs ≤ ½: multiply(Cb, 2Cs); else screen(Cb, 2Cs − 1) = Cb + (2Cs − 1)(1 − Cb).
    s2 = Cs * 2.0
    return pick(step("<=", Cs, 0.5), Cb * s2, Cb + (s2 - 1.0) * (1.0 - Cb))


def _overlay_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    return _hard_light_B(Cs, Cb)


def _darken_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    return torch.minimum(Cb, Cs)


def _lighten_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    return torch.maximum(Cb, Cs)


def _color_dodge_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    # The quotient is only selected where Cs < 1; elsewhere it divides by 1 (finite, and its derivative
    # is multiplied by 0). At Cs ≥ 1 (> 1 is not a colour: dodged fully) B is the constant 1, or 0 where
    # Cb = 0 — the spec's first case — so its derivative there is 0.
    pole = step(">=", Cs, 1.0)
    q = torch.div(Cb, pick(pole, torch.ones_like(Cs), 1.0 - Cs)).clamp_max(1.0)
    return pick(pole, as_value(step("!=", Cb, 0.0), q), q)


def _color_burn_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    # The mirror image: at Cs ≤ 0 B is the constant 0, or 1 where Cb = 1 (the spec's first case).
    pole = step("<=", Cs, 0.0)
    q = torch.div(1.0 - Cb, pick(pole, torch.ones_like(Cs), Cs)).clamp_max(1.0)
    return pick(pole, as_value(step("==", Cb, 1.0), q), 1.0 - q)


def _soft_light_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    # D(Cb): the polynomial on Cb ≤ ¼, √Cb above; √ reads max(Cb, ¼) so its slope stays finite, and the
    # polynomial min(Cb, ¼) so a large backdrop cannot overflow it where it is not selected.
    low = Cb.clamp_max(0.25)
    D = pick(step("<=", Cb, 0.25), ((16.0 * low - 12.0) * low + 4.0) * low, Cb.clamp_min(0.25).sqrt())
    s2 = Cs * 2.0
    return pick(step("<=", Cs, 0.5), Cb - (1.0 - s2) * Cb * (1.0 - Cb), Cb + (s2 - 1.0) * (D - Cb))


def _difference_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    return (Cb - Cs).abs()


def _exclusion_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    return Cb + Cs - 2.0 * Cb * Cs


# Non-separable helpers, section 10.3 of the spec. C is (..., 3, h, w); results keep a channel dim of 1.
def _lum(C: Tensor) -> Tensor:
    return 0.3 * C[..., 0:1, :, :] + 0.59 * C[..., 1:2, :, :] + 0.11 * C[..., 2:3, :, :]


def _clip_color(C: Tensor) -> Tensor:
    L = _lum(C)
    n = C.amin(dim=-3, keepdim=True)
    x = C.amax(dim=-3, keepdim=True)  # the spec takes x before the first correction
    C = pick(step("<", n, 0.0), L + (C - L) * L / (L - n).clamp_min(CLIP_COLOR_EPS), C)
    return pick(step(">", x, 1.0), L + (C - L) * (1.0 - L) / (x - L).clamp_min(CLIP_COLOR_EPS), C)


def _set_lum(C: Tensor, l: Tensor) -> Tensor:  # noqa: E741 (the spec's name)
    return _clip_color(C + (l - _lum(C)))


def _sat(C: Tensor) -> Tensor:
    return C.amax(dim=-3, keepdim=True) - C.amin(dim=-3, keepdim=True)


def _set_sat(C: Tensor, s: Tensor) -> Tensor:
    # Max → s, min → 0, mid → (Cmid − Cmin)·s/(Cmax − Cmin); a gray (Cmax = Cmin) gives 0·s/1 = 0.
    lo = C.amin(dim=-3, keepdim=True)
    d = C.amax(dim=-3, keepdim=True) - lo
    return (C - lo) * s / pick(step(">", d, 0.0), d, torch.ones_like(d))


def _rgb(C: Tensor) -> Tensor:
    return C if C.shape[-3] == 3 else C.expand(*C.shape[:-3], 3, *C.shape[-2:])


def _non_separable(f: Callable[[Tensor, Tensor], Tensor]) -> Callable[[Tensor, Tensor], Tensor]:
    def B(Cb: Tensor, Cs: Tensor) -> Tensor:
        out = f(_rgb(Cb), _rgb(Cs))
        return out if Cb.shape[-3] == 3 else out[..., :1, :, :]  # a gray backdrop gives a gray result

    B.__name__ = f.__name__
    return B


@_non_separable
def _hue_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    return _set_lum(_set_sat(Cs, _sat(Cb)), _lum(Cb))


@_non_separable
def _saturation_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    return _set_lum(_set_sat(Cb, _sat(Cs)), _lum(Cb))


@_non_separable
def _color_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    return _set_lum(Cs, _lum(Cb))


@_non_separable
def _luminosity_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    return _set_lum(Cb, _lum(Cs))


# ---- Photoshop's other modes (module docstring) --------------------------------------------------


def _linear_burn_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    return (Cb + Cs - 1.0).clamp_min(0.0)


def _linear_dodge_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    return (Cb + Cs).clamp_max(1.0)


def _subtract_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    return (Cb - Cs).clamp_min(0.0)


def _divide_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    # At Cs ≤ 0 the quotient divides by 1 (not selected); B is 1 where Cb > 0, else 0 (constant: no gradient).
    pole = step("<=", Cs, 0.0)
    q = torch.div(Cb, pick(pole, torch.ones_like(Cs), Cs)).clamp_max(1.0)
    return pick(pole, as_value(step(">", Cb, 0.0), q), q)


def _vivid_light_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    # Burn by 2Cs on Cs ≤ ½ (0 at Cs ≤ 0), dodge by 2(1 − Cs) above (1 at Cs ≥ 1); each quotient reads a
    # denominator of 1 where it is not selected, so both branches stay finite.
    low = step("<=", Cs, 0.5)
    burn_pole, dodge_pole = step("<=", Cs, 0.0), step(">=", Cs, 1.0)
    one = torch.ones_like(Cs)
    burn = 1.0 - torch.div(1.0 - Cb, pick(burn_pole, one, pick(low, 2.0 * Cs, one))).clamp_max(1.0)
    dodge = torch.div(Cb, pick(dodge_pole, one, pick(low, one, 2.0 * (1.0 - Cs)))).clamp_max(1.0)
    burn = pick(burn_pole, torch.zeros_like(burn), burn)
    dodge = pick(dodge_pole, torch.ones_like(dodge), dodge)
    return pick(low, burn, dodge)


def _linear_light_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    s = Cb + 2.0 * Cs - 1.0
    return pick(step("<=", Cs, 0.5), s.clamp_min(0.0), s.clamp_max(1.0))


def _pin_light_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    s2 = 2.0 * Cs
    return pick(step("<=", Cs, 0.5), torch.minimum(Cb, s2), torch.maximum(Cb, s2 - 1.0))


def _hard_mix_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    # Photoshop's tie (Cb + Cs = 1, common in 8-bit codes): 1 only where Cb > ½ (psd-tools #189); a sum within
    # HARD_MIX_TIE_EPS of 1 is the tie (numerics.py). The sum is taken in float32 at least (exact for half
    # inputs). B is piecewise constant: "+ 0·(Cb + Cs)" keeps the graph (a zero gradient, not a missing one)
    # and the NaN policy (a NaN input stays NaN).
    wide = torch.float32 if Cb.dtype not in (torch.float32, torch.float64) else Cb.dtype
    cb = Cb.detach().to(wide)
    off = cb + Cs.detach().to(wide) - 1.0
    tie = off.abs() <= HARD_MIX_TIE_EPS
    levels = (~tie & (off > 0.0)) | (tie & (cb > 0.5))
    return levels.to(Cb.dtype) + (Cb + Cs) * 0.0


def _lum_below(Cb: Tensor, Cs: Tensor, op: str) -> Tensor:
    # Lum(Cs) op Lum(Cb), compared in float32 at least: in half precision the two sums round apart.
    wide = torch.float32 if Cb.dtype not in (torch.float32, torch.float64) else Cb.dtype
    d = _lum(Cs.detach().to(wide)) - _lum(Cb.detach().to(wide))
    w = step(op, d, 0.0)
    return w if Cb.dtype in (torch.float32, torch.float64) else w.to(torch.bool)


@_non_separable
def _darker_color_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    return pick(_lum_below(Cb, Cs, "<"), Cs, Cb)


@_non_separable
def _lighter_color_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    return pick(_lum_below(Cb, Cs, ">"), Cs, Cb)


def _dissolve_B(Cb: Tensor, Cs: Tensor) -> Tensor:
    return Cs.expand(broadcast_shape(Cb.shape, Cs.shape))


# The pattern of dissolve: a pixel (x, y) of the layer shows where u(x, y) < α, u = h / 2^24 with h the top 24
# bits of a 32-bit integer hash of (x, y, DISSOLVE_SEED) (two rounds of a multiply-xorshift mixer; every
# product stays below 2^63, so int64 arithmetic is exact). Fixed, documented, reproducible in numpy.
DISSOLVE_SEED = 0x2545F491
_MIX = 0x045D9F3B
_MASK32 = 0xFFFFFFFF


def dissolve_pattern(y: Tensor, x: Tensor) -> Tensor:
    """u(x, y) ∈ [0, 1) of dissolve (above), float64, for int64 row indices ``y`` (h, 1) and columns ``x`` (1, w)."""
    h = (x * 73856093) ^ (y * 19349663) ^ DISSOLVE_SEED
    h = h & _MASK32
    for _ in range(2):
        h = h ^ (h >> 16)
        h = (h * _MIX) & _MASK32
    h = h ^ (h >> 16)
    return (h >> 8).to(torch.float64) / float(1 << 24)


def dissolve_alpha(a: Alpha, ly: int, lx: int, h: int, w: int, dtype: torch.dtype, device=None) -> Alpha:
    """Dissolve's α over the layer pixels rows ``ly:ly+h``, columns ``lx:lx+w``: 1 where u < α, else 0 (gradient
    0; NaN where α is NaN); None (opaque) stays None."""
    if a is None:
        return None
    ys = torch.arange(ly, ly + h, device=device).unsqueeze(1)
    xs = torch.arange(lx, lx + w, device=device).unsqueeze(0)
    u = dissolve_pattern(ys, xs).to(dtype).unsqueeze(0)  # (1, h, w); exact in float32 (24-bit codes)
    if not isinstance(a, Tensor):
        return torch.lt(u, a).to(dtype)
    return torch.lt(u, a.detach()).to(dtype) + a * 0.0  # 0·α: a zero gradient, and a NaN α stays NaN


# B(Cb, Cs) of Photoshop's other modes, computed as lerp(Cb, B, α) like the W3C ones.
PHOTOSHOP_B: dict[str, Callable[[Tensor, Tensor], Tensor]] = {
    "linear-burn": _linear_burn_B,
    "linear-dodge": _linear_dodge_B,
    "subtract": _subtract_B,
    "divide": _divide_B,
    "vivid-light": _vivid_light_B,
    "linear-light": _linear_light_B,
    "pin-light": _pin_light_B,
    "hard-mix": _hard_mix_B,
    "darker-color": _darker_color_B,
    "lighter-color": _lighter_color_B,
    "dissolve": _dissolve_B,
}


# B(Cb, Cs) of the modes computed as lerp(Cb, B, α).
W3C_B: dict[str, Callable[[Tensor, Tensor], Tensor]] = {
    "overlay": _overlay_B,
    "darken": _darken_B,
    "lighten": _lighten_B,
    "color-dodge": _color_dodge_B,
    "color-burn": _color_burn_B,
    "hard-light": _hard_light_B,
    "soft-light": _soft_light_B,
    "difference": _difference_B,
    "exclusion": _exclusion_B,
    "hue": _hue_B,
    "saturation": _saturation_B,
    "color": _color_B,
    "luminosity": _luminosity_B,
}


def _lerp_kernels(
    B: Callable[[Tensor, Tensor], Tensor],
) -> tuple[Callable[[Tensor, Tensor, Alpha], Tensor], Callable[[Tensor, Tensor, Alpha], Tensor]]:
    """The pure and in-place kernels ``lerp(Cb, B(Cb, Cs), α)`` (``B`` where α is None): same ops, same bits."""

    def kernel(Cb: Tensor, Cs: Tensor, a: Alpha) -> Tensor:
        b = B(Cb, Cs)
        if a is None:
            shape = broadcast_shape(Cb.shape, Cs.shape)
            return b if tuple(b.shape) == shape else b.expand(shape).clone(memory_format=torch.contiguous_format)
        return torch.lerp(Cb, b, a)

    def kernel_(out: Tensor, Cs: Tensor, a: Alpha) -> Tensor:
        b = B(out, Cs)
        return out.copy_(b) if a is None else out.lerp_(b, a)

    return kernel, kernel_


# Every mode computed as lerp(Cb, B, α): the W3C ones and Photoshop's.
LERP_B: dict[str, Callable[[Tensor, Tensor], Tensor]] = {**W3C_B, **PHOTOSHOP_B}

_W3C_KERNELS = {name: _lerp_kernels(B) for name, B in LERP_B.items()}
# dissolve is normal with a dissolved α (``dissolve_alpha``, applied where α is read: ``step._alpha``).
_W3C_KERNELS["dissolve"] = (_normal, _normal_)

KERNELS: dict[str, Callable[[Tensor, Tensor, Alpha], Tensor]] = {
    "normal": _normal,
    "multiply": _multiply,
    "screen": _screen,
    "plus": _plus,
    **{name: k for name, (k, _) in _W3C_KERNELS.items()},
}
KERNELS_INPLACE: dict[str, Callable[[Tensor, Tensor, Alpha], Tensor]] = {
    "normal": _normal_,
    "multiply": _multiply_,
    "screen": _screen_,
    "plus": _plus_,
    **{name: k_ for name, (_, k_) in _W3C_KERNELS.items()},
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


def _public(name: str, inplace: bool) -> Callable[[Tensor, Tensor, Alpha], Tensor]:
    """The checked public function of a W3C mode (``overlay``, ``color_dodge_``, …)."""
    op = name.replace("-", "_") + ("_" if inplace else "")
    kernel = (KERNELS_INPLACE if inplace else KERNELS)[name]

    def fn(Cb: Tensor, Cs: Tensor, a: Alpha = None) -> Tensor:
        _check(op, Cb, Cs, a, inplace=inplace)
        return kernel(Cb, Cs, a)

    fn.__name__ = fn.__qualname__ = op
    fn.__doc__ = (
        f"In-place ``{name}``: ``Cb.lerp_(B(Cb, Cs), α)`` (``Cb.copy_(B)`` if α is None); returns ``Cb``."
        if inplace
        else f"{name.capitalize()} ({'Photoshop' if name in PHOTOSHOP_B else 'W3C Compositing Level 1'}): "
        "``lerp(Cb, B(Cb, Cs), α)``, B in the module docstring; ``B`` if α is None."
    )
    return fn


overlay, overlay_ = _public("overlay", False), _public("overlay", True)
darken, darken_ = _public("darken", False), _public("darken", True)
lighten, lighten_ = _public("lighten", False), _public("lighten", True)
color_dodge, color_dodge_ = _public("color-dodge", False), _public("color-dodge", True)
color_burn, color_burn_ = _public("color-burn", False), _public("color-burn", True)
hard_light, hard_light_ = _public("hard-light", False), _public("hard-light", True)
soft_light, soft_light_ = _public("soft-light", False), _public("soft-light", True)
difference, difference_ = _public("difference", False), _public("difference", True)
exclusion, exclusion_ = _public("exclusion", False), _public("exclusion", True)
hue, hue_ = _public("hue", False), _public("hue", True)
saturation, saturation_ = _public("saturation", False), _public("saturation", True)
color, color_ = _public("color", False), _public("color", True)
luminosity, luminosity_ = _public("luminosity", False), _public("luminosity", True)
linear_burn, linear_burn_ = _public("linear-burn", False), _public("linear-burn", True)
linear_dodge, linear_dodge_ = _public("linear-dodge", False), _public("linear-dodge", True)
subtract, subtract_ = _public("subtract", False), _public("subtract", True)
divide, divide_ = _public("divide", False), _public("divide", True)
vivid_light, vivid_light_ = _public("vivid-light", False), _public("vivid-light", True)
linear_light, linear_light_ = _public("linear-light", False), _public("linear-light", True)
pin_light, pin_light_ = _public("pin-light", False), _public("pin-light", True)
hard_mix, hard_mix_ = _public("hard-mix", False), _public("hard-mix", True)
darker_color, darker_color_ = _public("darker-color", False), _public("darker-color", True)
lighter_color, lighter_color_ = _public("lighter-color", False), _public("lighter-color", True)


def dissolve(Cb: Tensor, Cs: Tensor, a: Alpha = None) -> Tensor:
    """Dissolve (Photoshop): normal with α replaced by ``dissolve_alpha`` (the pattern anchored at the top-left
    pixel of ``Cs``); ``Cs`` if α is None."""
    _check("dissolve", Cb, Cs, a, inplace=False)
    h, w = Cb.shape[-2:]
    return _normal(Cb, Cs, dissolve_alpha(a, 0, 0, h, w, Cb.dtype, Cb.device))


def dissolve_(Cb: Tensor, Cs: Tensor, a: Alpha = None) -> Tensor:
    """In-place ``dissolve``: ``Cb.lerp_(Cs, dissolve_alpha(α))``; returns ``Cb``."""
    _check("dissolve_", Cb, Cs, a, inplace=True)
    h, w = Cb.shape[-2:]
    return _normal_(Cb, Cs, dissolve_alpha(a, 0, 0, h, w, Cb.dtype, Cb.device))


BLEND_FUNC: dict[str, Callable[[Tensor, Tensor, Alpha], Tensor]] = {
    "normal": normal,
    "multiply": multiply,
    "screen": screen,
    "plus": plus,
    "overlay": overlay,
    "darken": darken,
    "lighten": lighten,
    "color-dodge": color_dodge,
    "color-burn": color_burn,
    "hard-light": hard_light,
    "soft-light": soft_light,
    "difference": difference,
    "exclusion": exclusion,
    "hue": hue,
    "saturation": saturation,
    "color": color,
    "luminosity": luminosity,
    "linear-burn": linear_burn,
    "linear-dodge": linear_dodge,
    "subtract": subtract,
    "divide": divide,
    "vivid-light": vivid_light,
    "linear-light": linear_light,
    "pin-light": pin_light,
    "hard-mix": hard_mix,
    "darker-color": darker_color,
    "lighter-color": lighter_color,
    "dissolve": dissolve,
}
BLEND_INPLACE: dict[str, Callable[[Tensor, Tensor, Alpha], Tensor]] = {
    "normal": normal_,
    "multiply": multiply_,
    "screen": screen_,
    "plus": plus_,
    "overlay": overlay_,
    "darken": darken_,
    "lighten": lighten_,
    "color-dodge": color_dodge_,
    "color-burn": color_burn_,
    "hard-light": hard_light_,
    "soft-light": soft_light_,
    "difference": difference_,
    "exclusion": exclusion_,
    "hue": hue_,
    "saturation": saturation_,
    "color": color_,
    "luminosity": luminosity_,
    "linear-burn": linear_burn_,
    "linear-dodge": linear_dodge_,
    "subtract": subtract_,
    "divide": divide_,
    "vivid-light": vivid_light_,
    "linear-light": linear_light_,
    "pin-light": pin_light_,
    "hard-mix": hard_mix_,
    "darker-color": darker_color_,
    "lighter-color": lighter_color_,
    "dissolve": dissolve_,
}


def get_blend(name: str, inplace: bool = False) -> Callable[[Tensor, Tensor, Alpha], Tensor]:
    """The blend function called ``name`` (in-place variant if ``inplace``); raises on unknown names."""
    check_blend_name(name)
    return (BLEND_INPLACE if inplace else BLEND_FUNC)[name]


def clamp_needed(blend: str, lo: float, hi: float) -> tuple[bool, bool]:
    """Which side (below 0, above 1) a ``clamp="layer"`` clamp can change after this blend.

    ``[lo, hi]`` bounds the source values (the layer's measured min/max, or its declared range for a
    layer that carries gradients); the backdrop is in [0, 1] and α in [0, 1]. See the module docstring
    for why normal, multiply, screen, darken, lighten and difference of in-range values need no clamp;
    the other W3C modes always clamp both sides. Plus adds ``α·Cs`` to a backdrop that may already be 1,
    so any positive source can overflow. Unknown bounds (NaN) clamp.
    """
    check_blend_name(blend)
    if not (lo == lo and hi == hi):  # NaN: nothing is proven
        return True, True
    if blend == "plus":
        return lo < 0.0, hi > 0.0
    if blend in LERP_B and blend not in _PROVEN_IN_RANGE:
        return True, True
    return lo < 0.0, hi > 1.0


# W3C modes whose rounded B of in-range values is proven to lie in [0, 1] (module docstring).
# dissolve is normal with α ∈ {0, 1}; darker/lighter-color pick whole in-range pixels, then lerp.
_PROVEN_IN_RANGE = frozenset({"darken", "lighten", "difference", "dissolve", "darker-color", "lighter-color"})
