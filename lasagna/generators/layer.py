"""What a learned edit layer is as a tensor, how a generator's raw output becomes one, and its composite.

``LayerSpec`` fixes a layer's blend, channels and value range (read from a preset). A layer tensor is
``(B, C, H, W)`` with C = 1 (a gray value broadcast over RGB: the Lasagna paper's luminosity
multiplier, f(x, y) = x·y), 3 (RGB) or 4 (RGB + alpha, alpha last, never range-mapped).

**Output parametrisation.** A generator (network or free per-pixel tensor) produces an unconstrained
pre-activation u per channel; the layer value is y = lo + (hi − lo)·s(u) with the squash s:

* ``sigmoid``: s(u) = sigmoid(u), smooth, never exactly on a boundary (the CPU prototype's shading
  layer y = 2·sigmoid(θ));
* ``clamp``: s(u) = clamp(u, 0, 1) whose backward keeps the clamp's gradient inside [0, 1] and,
  outside it, only the part that moves u back into [0, 1] (``clamp_inward``): a boundary value is
  reached exactly, and a pixel pushed past the boundary is not dead — it returns when the gradient
  asks it to (a plain clamp would freeze it; a straight-through clamp would let it drift outwards).
* ``auto`` (default), per channel: ``sigmoid`` where the identity value lies strictly inside the
  range, ``clamp`` where it lies on a boundary.

**Identity edit.** Every generator starts at the edit that changes nothing: a multiplier of exactly
1, a light (``plus``/``screen``) of exactly 0, an alpha of exactly 0 — so the first composite equals
the input. With ``sigmoid`` on an interior identity the start is u₀ = logit((1 − lo)/(hi − lo)) — 0
for the shading range [0, 2], where y = 2·sigmoid(0) = 1 exactly (otherwise within float rounding);
with ``clamp`` it is the identity itself. A ``sigmoid`` forced onto a boundary identity starts at
∓``numerics.IDENTITY_LOGIT``, which leaves 6.1e-6 of the range's width (stated bound). With an alpha
channel the colour starts at the middle of its range (sigmoid(0) = 0.5): at α = 0 the colour gets no
gradient, and α's first gradient is ∝ blend(Cb, Cs) − Cb, which would vanish if the colour started at
the blend's own identity (a per-pixel dead lock; it remains only where the base equals the mid colour).

**Colour over luminance** (``luminance="base"``, the colour preset's): the layer's colour is set to the base's
Rec. 709 luma before it is blended (``lasagna.compose.color.set_luma``), so an alpha-linear layer changes only
the composite's colour: Lum(Cb + α(C − Cb)) = Lum(Cb) for any α, as in the world's colorize task, whose true
layer is the colour image over its own gray. Only its chroma (two degrees of freedom a pixel) is learned.

**Composite.** ``composite(base, layer, spec)`` calls the compositor's blend function
(``lasagna.compose.blend.BLEND_FUNC``) with no clamp: the graph stays differentiable everywhere (a
clamp would zero the gradient of every saturated pixel, so a multiplier that overshoots could never
be pulled back by the prior). The caller clamps once for output (the document's ``clamp="output"``).
"""

from __future__ import annotations

import math
from typing import Literal

import torch
from pydantic import BaseModel, ConfigDict, Field, model_serializer, model_validator
from torch import Tensor

from lasagna.compose.blend import BLEND_FUNC
from lasagna.compose.color import luma, set_luma
from lasagna.document.blend import RANGED_BLENDS, BlendMode
from lasagna.document.preset import Enlarge
from lasagna.errors import LasagnaError
from lasagna.numerics import IDENTITY_LOGIT, LOGIT_EPS

Squash = Literal["auto", "sigmoid", "clamp"]
# The colour value that leaves the backdrop unchanged for an opaque layer of each blend (normal has
# none: an opaque normal layer replaces the base, so a normal layer needs an alpha channel).
_IDENTITY_COLOUR = {"multiply": 1.0, "plus": 0.0, "screen": 0.0}


class LayerSpec(BaseModel):
    """The blend, channels and value range of an edit layer, and how raw outputs are squashed into it."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    blend: BlendMode = Field(description="The blend the layer is composed with.")
    channels: Literal[1, 3, 4] = Field(description="1 gray (broadcast over RGB), 3 RGB, 4 RGBA (alpha last).")
    range: tuple[float, float] = Field(
        (0.0, 1.0), description="[lo, hi] of the colour values (alpha is always [0, 1])."
    )
    squash: Squash = Field(
        "auto", description="sigmoid, clamp (inward-gradient clamp) or auto (see the module docstring)."
    )
    luminance: Literal["free", "base"] = Field(
        "free", description="base: the colour is set to the base's luma (colour over luminance; blend normal only)."
    )
    enlarge: Enlarge = Field(
        "bilinear", description="How the layer is enlarged from the working size: bilinear, or guided by the luma."
    )

    @model_serializer(mode="wrap")
    def _dump(self, handler):
        # "free" is every layer's before colour over luminance: left out, so settings recorded before it read the same.
        data = handler(self)
        if data.get("luminance") == "free":
            del data["luminance"]
        if data.get("enlarge") == "bilinear":  # likewise: every layer's enlargement before the guided one
            del data["enlarge"]
        return data

    @model_validator(mode="after")
    def _rules(self) -> LayerSpec:
        lo, hi = self.range
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f"range [{lo}, {hi}]: expected finite lo < hi")
        if (lo, hi) != (0.0, 1.0) and self.blend not in RANGED_BLENDS:
            raise ValueError(
                f"range [{lo}, {hi}] with blend {self.blend!r}: a range other than [0, 1] is allowed only for "
                "multiply and plus"
            )
        if self.luminance == "base" and self.blend != "normal":
            raise ValueError(
                f"luminance 'base' with blend {self.blend!r}: expected blend normal (colour over luminance)"
            )
        if self.channels != 4:
            if self.blend == "normal":
                raise ValueError(
                    "blend 'normal' without alpha replaces the base, so no layer value is the identity edit; "
                    "expected channels 4 (RGBA)"
                )
            ident = _IDENTITY_COLOUR[self.blend]
            if not lo <= ident <= hi:
                raise ValueError(
                    f"range [{lo}, {hi}] does not contain {ident}, the identity value of blend {self.blend!r}; "
                    "expected a range that does"
                )
        return self

    @classmethod
    def from_preset(cls, preset, squash: Squash = "auto") -> LayerSpec:
        """The spec of a ``lasagna.document.Preset`` (blend, channels, range)."""
        return cls(
            blend=preset.blend,
            channels=preset.channels,
            range=tuple(preset.range),
            squash=squash,
            luminance=preset.luminance,
            enlarge=preset.enlarge,
        )

    @property
    def colour_channels(self) -> int:
        return 3 if self.channels == 4 else self.channels

    @property
    def has_alpha(self) -> bool:
        return self.channels == 4

    def channel_plan(self) -> list[tuple[str, float, float, float]]:
        """Per channel: (squash, lo, hi, identity value y₀), the squash resolved from ``auto``."""
        lo, hi = self.range
        plan = []
        for c in range(self.channels):
            if self.has_alpha and c == 3:
                clo, chi, y0 = 0.0, 1.0, 0.0  # alpha: identity 0, never range-mapped
            elif self.has_alpha:
                clo, chi, y0 = lo, hi, lo + 0.5 * (hi - lo)  # colour under alpha: the middle (see the docstring)
            else:
                clo, chi, y0 = lo, hi, _IDENTITY_COLOUR[self.blend]
            squash = self.squash
            if squash == "auto":
                squash = "sigmoid" if clo < y0 < chi else "clamp"
            plan.append((squash, clo, chi, y0))
        return plan

    def identity_preactivation(self) -> Tensor:
        """u₀ (C,) float64: the raw output whose layer is the identity edit (see the module docstring)."""
        out = []
        for squash, lo, hi, y0 in self.channel_plan():
            v = (y0 - lo) / (hi - lo)
            if squash == "clamp":
                out.append(v)
            elif 0.0 < v < 1.0:
                out.append(math.log(v / (1.0 - v)))
            else:
                out.append(IDENTITY_LOGIT if v >= 1.0 else -IDENTITY_LOGIT)
        return torch.tensor(out, dtype=torch.float64)

    def identity_layer(
        self, batch: int, height: int, width: int, dtype: torch.dtype = torch.float32, device=None
    ) -> Tensor:
        """The identity edit's layer values (B, C, H, W) (the exact y₀, not the squashed u₀)."""
        y0 = torch.tensor([p[3] for p in self.channel_plan()], dtype=dtype, device=device)
        return y0.view(1, -1, 1, 1).expand(batch, -1, height, width).clone()


# -- the squash ----------------------------------------------------------------------------------
class _ClampInward(torch.autograd.Function):
    """clamp(u, lo, hi) whose gradient outside [lo, hi] keeps only the part pointing back inside."""

    @staticmethod
    def forward(ctx, u: Tensor, lo: float, hi: float) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(u)
        ctx.bounds = (lo, hi)
        return u.clamp(lo, hi)

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        (u,) = ctx.saved_tensors
        lo, hi = ctx.bounds
        # Gradient descent moves u by −grad: below lo keep grad < 0 (u rises), above hi keep grad > 0.
        keep = ((u >= lo) & (u <= hi)) | ((u < lo) & (grad < 0)) | ((u > hi) & (grad > 0))
        return torch.where(keep, grad, torch.zeros((), dtype=grad.dtype, device=grad.device)), None, None


def clamp_inward(u: Tensor, lo: float = 0.0, hi: float = 1.0) -> Tensor:
    """``u.clamp(lo, hi)`` with the inward gradient described in the module docstring."""
    return _ClampInward.apply(u, lo, hi)


def activate(u: Tensor, spec: LayerSpec) -> Tensor:
    """Raw output u (B, C, H, W) → layer values y = lo + (hi − lo)·s(u) per channel (alpha in [0, 1])."""
    if u.dim() != 4 or u.shape[1] != spec.channels:
        raise LasagnaError(f"raw output has shape {tuple(u.shape)}; expected (B, {spec.channels}, H, W)", "layer")
    parts = []
    start = 0
    for squash, lo, hi, count in _groups(spec):
        x = u[:, start : start + count]
        s = torch.sigmoid(x) if squash == "sigmoid" else clamp_inward(x, 0.0, 1.0)
        parts.append(s if (lo, hi) == (0.0, 1.0) else lo + (hi - lo) * s)
        start += count
    return parts[0] if len(parts) == 1 else torch.cat(parts, dim=1)


def inverse(y: Tensor, spec: LayerSpec) -> Tensor:
    """A raw output u with ``activate(u) ≈ y``: logit of (y − lo)/(hi − lo) clamped to
    [LOGIT_EPS, 1 − LOGIT_EPS] for sigmoid channels (a boundary value maps to a finite ±13.8), the
    normalised value itself for clamp channels. Values outside the range are an error."""
    if y.dim() != 4 or y.shape[1] != spec.channels:
        raise LasagnaError(f"layer has shape {tuple(y.shape)}; expected (B, {spec.channels}, H, W)", "layer")
    parts, start = [], 0
    for squash, lo, hi, count in _groups(spec):
        x = y[:, start : start + count]
        v = (x - lo) / (hi - lo)
        bad = ~((v >= -1e-6) & (v <= 1 + 1e-6))
        if bool(bad.any()):
            raise LasagnaError(
                f"layer values outside [{lo}, {hi}] (e.g. {float(x[bad][0]):.4g}); expected values in the layer's "
                "range",
                "layer",
            )
        v = v.clamp(0.0, 1.0)
        parts.append(torch.logit(v, eps=LOGIT_EPS) if squash == "sigmoid" else v)
        start += count
    return torch.cat(parts, dim=1)


def _groups(spec: LayerSpec) -> list[tuple[str, float, float, int]]:
    """Runs of consecutive channels with the same (squash, lo, hi): (squash, lo, hi, count)."""
    runs: list[tuple[str, float, float, int]] = []
    for squash, lo, hi, _ in spec.channel_plan():
        if runs and runs[-1][:3] == (squash, lo, hi):
            runs[-1] = (squash, lo, hi, runs[-1][3] + 1)
        else:
            runs.append((squash, lo, hi, 1))
    return runs


# -- the composite -------------------------------------------------------------------------------
def split(layer: Tensor, spec: LayerSpec) -> tuple[Tensor, Tensor | None]:
    """(colour (B, 1 | 3, H, W), alpha (B, 1, H, W) or None) of a layer tensor."""
    if layer.dim() != 4 or layer.shape[1] != spec.channels:
        raise LasagnaError(f"layer has shape {tuple(layer.shape)}; expected (B, {spec.channels}, H, W)", "layer")
    if spec.has_alpha:
        return layer[:, :3], layer[:, 3:]
    return layer, None


def composite(base: Tensor, layer: Tensor, spec: LayerSpec) -> Tensor:
    """The base (B, 3, H, W) with the layer blended over it, unclamped and differentiable in both (a colour over
    luminance first set to the base's luma: module docstring)."""
    colour, alpha = split(layer, spec)
    if spec.luminance == "base":
        colour = set_luma(colour, luma(base))
    return BLEND_FUNC[spec.blend](base, colour, alpha)
