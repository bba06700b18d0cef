"""A layer's tensors and the statistics a render plan needs to cull it, cached until the pixels change.

``LayerTensors`` holds a layer's colour ``(..., C, h, w)`` (C ∈ {1, 3}; values already mapped to the
layer's range ``y = lo + (hi − lo)·v``), its alpha ``(..., 1, h, w)`` or None (opaque) and its mask
``(..., 1, h, w)`` or None. The effective alpha of a blend is ``alpha × mask × opacity``.

Statistics — value range, "is an identity for its blend", "is fully opaque" — need one pass over the
pixels. They are computed lazily, once, and kept until a tensor is replaced (identity, checked with
a weak reference so a recycled ``id`` cannot fool it) or modified in place (its ``_version``, which
views share with their base). A render plan can therefore cull unchanged layers on every render
without reading their pixels again. Statistics of tensors that require grad are still correct for
their current values, but the plan never culls such a layer by value: its gradient is not zero.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from lasagna.compose.blend import broadcast_shape
from lasagna.compose.color import srgb_to_linear
from lasagna.errors import LasagnaError

_FIELDS = ("color", "alpha", "mask")


def _shape(t: Tensor) -> str:
    return "(" + ", ".join(str(s) for s in t.shape) + ")"


def _key(t: Tensor | None) -> tuple[Any, ...] | None:
    return None if t is None else (id(t), t._version)


# Grid of about SAMPLE_GRID² pixels (per channel and batch entry) read for cheap counterexamples: a
# layer whose sampled pixels are not all neutral cannot be an identity, whatever the rest holds.
SAMPLE_GRID = 16


def _distinct(t: Tensor) -> Tensor:
    """``t`` with every zero-stride (expanded) dimension read once: the same values, so the same min and
    max, without materialising a solid layer's canvas-size view (``torch.aminmax`` copies a view first)."""
    index = tuple(slice(0, 1) if st == 0 and n > 1 else slice(None) for st, n in zip(t.stride(), t.shape))
    return t.detach()[index]


def _grid(t: Tensor) -> Tensor:
    sy, sx = max(1, t.shape[-2] // SAMPLE_GRID), max(1, t.shape[-1] // SAMPLE_GRID)
    return t.detach()[..., ::sy, ::sx]


@dataclass(eq=False)
class LayerTensors:
    """A layer's colour, alpha and mask, with lazily cached statistics (see the module docstring)."""

    color: Tensor
    alpha: Tensor | None = None
    mask: Tensor | None = None
    reduced_by: int = 1  # these are the layer's own tensors reduced by this factor (a zoom level's, 2**level)
    _cache: dict[str, tuple[Any, ...]] = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        self.validate()

    def __setattr__(self, name: str, value: Any) -> None:
        super().__setattr__(name, value)
        if name in _FIELDS and all(hasattr(self, f) for f in _FIELDS) and hasattr(self, "_cache"):
            self.validate()

    # ---- shape -------------------------------------------------------------------------------

    def validate(self) -> None:
        """Raise ``LasagnaError`` naming the field if a tensor has the wrong type, shape or device."""
        c = self.color
        if not isinstance(c, Tensor) or not c.is_floating_point() or c.ndim < 3 or c.shape[-3] not in (1, 3):
            got = _shape(c) + f" {c.dtype}" if isinstance(c, Tensor) else type(c).__name__
            raise LasagnaError(
                f"got {got}; expected a floating-point tensor (..., C, h, w) with C in {{1, 3}}",
                where="LayerTensors.color",
            )
        for name in ("alpha", "mask"):
            t = getattr(self, name)
            if t is None:
                continue
            if not isinstance(t, Tensor) or not t.is_floating_point() or t.ndim < 3 or t.shape[-3] != 1:
                got = _shape(t) + f" {t.dtype}" if isinstance(t, Tensor) else type(t).__name__
                raise LasagnaError(
                    f"got {got}; expected a floating-point tensor (..., 1, h, w) or None", where=f"LayerTensors.{name}"
                )
            if t.shape[-2:] != c.shape[-2:]:
                raise LasagnaError(
                    f"is {t.shape[-2]}x{t.shape[-1]} but the colour is {c.shape[-2]}x{c.shape[-1]}; "
                    "expected the layer's size",
                    where=f"LayerTensors.{name}",
                )
            if t.device != c.device:
                raise LasagnaError(
                    f"is on {t.device} but the colour is on {c.device}; expected one device",
                    where=f"LayerTensors.{name}",
                )
        try:
            _ = self.batch_shape
        except RuntimeError:
            raise LasagnaError(
                "batch dimensions of colour, alpha and mask "
                + ", ".join(_shape(t) for t in self.tensors() if t is not None)
                + " do not broadcast; expected equal sizes or 1",
                where="LayerTensors",
            ) from None

    def tensors(self) -> tuple[Tensor, Tensor | None, Tensor | None]:
        return self.color, self.alpha, self.mask

    @property
    def height(self) -> int:
        return self.color.shape[-2]

    @property
    def width(self) -> int:
        return self.color.shape[-1]

    @property
    def channels(self) -> int:
        return self.color.shape[-3]

    @property
    def batch_shape(self) -> torch.Size:
        return torch.Size(broadcast_shape(*(t.shape[:-3] for t in self.tensors() if t is not None)))

    @property
    def requires_grad(self) -> bool:
        return any(t is not None and t.requires_grad for t in self.tensors())

    def fingerprint(self) -> tuple[Any, ...]:
        """``(id, _version)`` of each tensor: changes when a tensor is replaced or modified in place."""
        return tuple(_key(t) for t in self.tensors())

    # ---- cached statistics --------------------------------------------------------------------

    def note(self, name: str, value: Any) -> None:
        """Remember ``value`` under ``name`` until a tensor is replaced or modified in place (a fact about the
        current pixels that a caller established, e.g. "these are the values a PNG at this range holds")."""
        refs = tuple(None if t is None else weakref.ref(t) for t in self.tensors())
        self._cache[f"note:{name}"] = (self.fingerprint(), refs, value)

    def noted(self, name: str) -> Any:
        """The value ``note`` remembered under ``name`` while the pixels are unchanged, else None."""
        return self._peek(f"note:{name}", self.tensors())

    def _peek(self, name: str, tensors: tuple[Tensor | None, ...]) -> Any:
        """The cached value of ``name`` if it is still valid for ``tensors``, else None."""
        hit = self._cache.get(name)
        if (
            hit is not None
            and hit[0] == tuple(_key(t) for t in tensors)
            and all((r is None and t is None) or (r is not None and r() is t) for r, t in zip(hit[1], tensors))
        ):
            return hit[2]
        return None

    def _cached(self, name: str, tensors: tuple[Tensor | None, ...], compute: Callable[[], Any]) -> Any:
        value = self._peek(name, tensors)
        if value is not None:
            return value
        with torch.no_grad():
            value = compute()
        refs = tuple(None if t is None else weakref.ref(t) for t in tensors)
        self._cache[name] = (tuple(_key(t) for t in tensors), refs, value)
        return value

    def has_color_range(self) -> bool:
        """Whether ``color_range`` is cached for the current colour (no pixel read needed)."""
        return self._peek("color_range", (self.color,)) is not None

    def sample_color_range(self) -> tuple[float, float]:
        """``(min, max)`` over a sparse grid of pixels (the exact range when cached): a cheap
        counterexample, never a proof."""
        exact = self._peek("color_range", (self.color,))
        if exact is not None:
            return exact

        def compute() -> tuple[float, float]:
            lo, hi = torch.aminmax(_grid(self.color))
            return float(lo), float(hi)

        return self._cached("color_sample", (self.color,), compute)

    def color_range(self) -> tuple[float, float]:
        """``(min, max)`` of the colour over every pixel and batch entry (NaN if any value is NaN)."""

        def compute() -> tuple[float, float]:
            lo, hi = torch.aminmax(_distinct(self.color))
            return float(lo), float(hi)

        return self._cached("color_range", (self.color,), compute)

    def alpha_range(self) -> tuple[float, float]:
        """``(min, max)`` of alpha × mask; ``(1, 1)`` when both are None."""
        if self.alpha is None and self.mask is None:
            return 1.0, 1.0

        def compute() -> tuple[float, float]:
            if self.alpha is not None and self.mask is not None:
                lo, hi = torch.aminmax(_distinct(self.alpha) * _distinct(self.mask))  # broadcasts back
            else:
                lo, hi = torch.aminmax(_distinct(self.alpha if self.alpha is not None else self.mask))
            return float(lo), float(hi)

        return self._cached("alpha_range", (self.alpha, self.mask), compute)

    def _sample_alpha_range(self) -> tuple[float, float]:
        if self.alpha is None and self.mask is None:
            return 1.0, 1.0
        exact = self._peek("alpha_range", (self.alpha, self.mask))
        if exact is not None:
            return exact

        def compute() -> tuple[float, float]:
            a = None
            for x in (self.alpha, self.mask):
                if x is not None:
                    a = _grid(x) if a is None else a * _grid(x)
            lo, hi = torch.aminmax(a)
            return float(lo), float(hi)

        return self._cached("alpha_sample", (self.alpha, self.mask), compute)

    def is_opaque(self) -> bool:
        """alpha × mask is exactly 1 everywhere (or both are None)."""
        # A sampled pixel below 1 disproves it without reading the whole layer.
        return self._sample_alpha_range()[0] == 1.0 and self.alpha_range() == (1.0, 1.0)

    def is_transparent(self) -> bool:
        """alpha × mask is exactly 0 everywhere."""
        return self._sample_alpha_range()[1] == 0.0 and self.alpha_range() == (0.0, 0.0)

    def is_identity(self, blend: str) -> bool:
        """Blending this layer leaves every backdrop unchanged, bit for bit.

        True when alpha × mask is 0 everywhere, or the colour is the blend's neutral element: 1 for
        multiply, 0 for plus and screen. The colour must be finite (``0·NaN = NaN`` would otherwise
        change the backdrop), so culling an identity never hides a NaN.
        """
        neutral = {"multiply": 1.0, "plus": 0.0, "screen": 0.0}.get(blend)
        # Cheap rejections first: a sampled pixel that is not neutral and not transparent.
        s_lo, s_hi = self.sample_color_range()
        if not (neutral is not None and s_lo == s_hi == neutral) and self._sample_alpha_range()[1] != 0.0:
            return False
        lo, hi = self.color_range()
        if not (abs(lo) < float("inf") and abs(hi) < float("inf")):  # NaN or inf in the colour
            return False
        if neutral is not None and lo == hi == neutral:
            return True
        return self.is_transparent()

    def decoded_color(self) -> Tensor:
        """The colour decoded from sRGB to linear light, cached (no grad); see ``color.py``."""
        return self._cached("decoded", (self.color,), lambda: srgb_to_linear(self.color))

    @classmethod
    def from_rgba(cls, rgba: Tensor, mask: Tensor | None = None) -> LayerTensors:
        """Split a ``(..., 2 | 4, h, w)`` gray+alpha or RGBA tensor into colour and alpha (views)."""
        if not isinstance(rgba, Tensor) or rgba.ndim < 3 or rgba.shape[-3] not in (2, 4):
            got = _shape(rgba) if isinstance(rgba, Tensor) else type(rgba).__name__
            raise LasagnaError(f"got {got}; expected a tensor (..., 2 | 4, h, w)", where="LayerTensors.from_rgba")
        return cls(rgba[..., :-1, :, :], rgba[..., -1:, :, :], mask)
