"""Layers as interchange formats see them: one RGBA raster per layer, on the canvas, in [0, 1].

OpenRaster and PSD layers are 8-bit RGBA images blended with per-layer clamping in gamma-encoded
sRGB. This module turns a stack's layers into that form and says, with one-line warnings, what the
target cannot express exactly:

* A multiply layer with values y > 1 becomes a multiply layer of min(y, 1) and, directly above it,
  a colour-dodge layer of d = 1 − 1/max(y, 1) with the same alpha and opacity. Colour dodge is
  B(Cb, Cs) = min(1, Cb/(1 − Cs)) (W3C Compositing Level 1), so with α ∈ {0, 1} the pair gives
  Cb·min(y, 1)/(1 − d) = Cb·y, clamped to 1 like every interop blend. For 0 < α < 1 two lerps
  would not compose to one, so alpha × mask × opacity is first baked into the values: over an
  opaque backdrop Cb + α(Cb·y − Cb) = Cb·g with g = 1 + α(y − 1), written as an opaque pair of g
  (exact for any α; the price is that the file's opacity slider no longer scales that layer).
  d is chosen per pixel as the code of the file's depth (8 or 16 bits) whose 1/(1 − d) is nearest y, not the code
  nearest d.
* Paint programs blend "plus" (Krita's Addition, Photoshop's Linear Dodge) as
  Cb + α(min(1, Cb + Cs) − Cb), clamping inside the blend; the W3C plus is min(1, Cb + α·Cs). The
  two differ where Cb + Cs > 1 and 0 < α < 1, so a plus layer with fractional alpha × mask ×
  opacity is written with α baked into its values (Cs' = α·Cs, opaque), on which both agree.
  Values above 1 are split into ⌈max y⌉ plus layers of min(max(y − k, 0), 1): additions of
  non-negative values commute with clamping at 1, so the split is exact.
* A surface layer is written as its rendered multiplier (what it blends as), with its normal map below it as a
  hidden normal layer "<name> (normal map)" (tangent space, +Y up), so readers flatten it as we do; its name carries
  the light when the pixels cannot tell it (`lasagna.export.surface_import.map_name`).
* A dissolve layer is written with our pattern baked into its alpha (0 or 1 per pixel, opacity 1): every
  reader then shows the same pixels (each draws its own pattern for a partial alpha).
* Negative values, colours above 1 in normal/screen layers, ``blend_space="linear"`` and a
  ``clamp="output"`` that changes the result cannot be expressed. The layers are then written as
  they are (values clipped to [0, 0] / [.., 1]), and an opaque top layer "Composite (exact)" holds
  the exact composite, so the file still flattens to our image in any reader; a one-line warning
  says why (hide that layer to edit the others). The merged image is always the exact composite.

* An adjustment layer is left out (psd-tools and the OpenRaster writer make none): the composite goes on top.
* Clipping chains (``groups=True``): every item of a clipped layer has ``clip``; the writers place them (PSD's
  clipping flag; in OpenRaster an isolated stack of the base and ``svg:src-atop`` layers, as Krita writes its
  inherit-alpha). Not exact, the composite then on top: a chain with helper layers, flat export, a non-normal
  clipped layer in OpenRaster (Krita writes only normal ones as src-atop), a clipped group in PSD.
* Groups (``groups=True``, what both formats use) stay groups: OpenRaster nests a ``<stack>`` per group
  (``isolation="isolate"`` with the group's composite-op and opacity, ``"auto"`` for pass-through, as Krita
  writes them), PSD a group record (PASS_THROUGH, or the group's blend mode); their layers carry canvas
  offsets (the groups' offsets added). A group mask, a pass-through group of opacity < 1 (the OpenRaster spec
  renders it isolated; paint programs differ) and, inside an isolated group, the helper layers above (which
  assume an opaque backdrop) are not exact: the composite layer goes on top. With ``groups=False`` a group's
  layers are listed flat: exact for a pass-through group of opacity 1 without a mask (W3C Compositing
  Level 1, section 8.1, group invariance), else not.

Every raster is cropped to the canvas (layers may lie partly outside), with its offset adjusted — but a surface
layer's hidden normal map, which is written whole (``_Walk.normal_map``). A transparent
document (``canvas.background`` null) gets no background layer, and its exact-composite layer carries the
composite's alpha: the file is as transparent as the document.

Memory: an ``ExportLayer`` holds views of the layer's own pixels (float32, not copied) and, where the file stores
something else (baked alpha, dodge codes, the parts of a plus layer), the function that computes it; its codes
are made a band of rows at a time (``ExportLayer.bands``, 8- or 16-bit), so a 12 MP layer never exists as float64.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from lasagna.compose.blend import dissolve_pattern
from lasagna.compose.plan import gradient_tensors, pattern_tensors
from lasagna.compose.surface import layer_surface_tensors, relieved_map
from lasagna.document import LearnedLayer, SolidLayer, SurfaceLayer
from lasagna.errors import ExportError
from lasagna.export.surface_import import map_name
from lasagna.io.png import BitDepth, quantize_band

# ORA/PSD blend names for our blends and the helper layers.
Op = str
NORMALS_DIR = "_normals"
"""A surface layer's hidden normal map is keyed ``_normals/<id>`` (OpenRaster: ``data/_normals/<id>.png``), so an
import tells it from the layer it belongs to (`lasagna.export.surface_import`)."""
COMPOSITE_NAME = "Composite (exact)"  # "normal" | "multiply" | "plus" | "screen" | "color-dodge"


# Rows of a raster turned into codes at a time: 64 rows of an 8192-wide layer are 16 MiB of float64 RGBA.
BAND_ROWS = 64

# What a file of ``depth`` bits stores of a band of a layer's values y (C, rows, w) and alpha × mask α (1, rows, w),
# float64, when it is not the values themselves (baked alpha, dodge codes, a plus layer's parts); clamped to [0, 1]
# afterwards.
Values = Callable[[np.ndarray, np.ndarray, int], tuple[np.ndarray, np.ndarray]]


@dataclass
class ExportLayer:
    """One layer of an interchange file: RGBA in [0, 1] on a canvas rectangle, made a band at a time."""

    name: str
    key: str  # unique, file-name safe: "<id>", "_dodge/<id>", "_plus1/<id>", "_background"
    op: Op
    x: int
    y: int
    color: np.ndarray  # (C, h, w), C ∈ {1, 3} (1: written as gray in RGB): the values, a view (float32 or float64)
    alpha: np.ndarray | None  # (1, h, w) in [0, 1]: layer alpha × mask (not opacity); None: opaque
    opacity: float
    visible: bool
    source: str = ""  # id of the document layer it comes from ("" for the background)
    clip: bool = False  # clipped to the item below (Photoshop's clipping mask; the document's ``clip``)
    values: Values | None = None  # what the file stores of (color, alpha), per band; None: those, clamped

    @property
    def height(self) -> int:
        return int(self.color.shape[1])

    @property
    def width(self) -> int:
        return int(self.color.shape[2])

    def rgba(self, r0: int = 0, r1: int | None = None, depth: BitDepth = 8) -> tuple[np.ndarray, np.ndarray]:
        """Rows ``r0:r1`` as a file of ``depth`` bits stores them: (colour (3, rows, w), alpha (1, rows, w)) float64
        in [0, 1]."""
        r1 = self.height if r1 is None else r1
        c = np.asarray(self.color[:, r0:r1], dtype=np.float64)
        a = np.ones((1, *c.shape[1:])) if self.alpha is None else np.asarray(self.alpha[:, r0:r1], dtype=np.float64)
        if self.values is not None:
            c, a = self.values(c, a, depth)
        c = np.broadcast_to(c, (3, *c.shape[1:]))
        return np.clip(c, 0.0, 1.0), np.clip(a, 0.0, 1.0)

    @property
    def channels(self) -> int:
        """The fewest PNG channels that hold the layer exactly: gray for a 1-channel multiplier (its transforms are
        per element), RGB for colour, and alpha unless the layer has none (then every value's alpha is 1)."""
        return (1 if self.color.shape[0] == 1 else 3) + (0 if self.alpha is None else 1)

    def bands(self, depth: BitDepth = 8, rows: int = BAND_ROWS, *, fit: bool = False):
        """(rows, w, 4) codes from the top: uint8, or uint16 for ``depth`` 16 (rounded to nearest); ``fit``:
        (rows, w, ``channels``) instead, the same values in fewer channels (what an OpenRaster layer PNG holds)."""
        for r0 in range(0, self.height, rows):
            c, a = self.rgba(r0, min(self.height, r0 + rows), depth)
            if fit:
                c = c[:1] if self.color.shape[0] == 1 else c
                planes = c if self.alpha is None else np.concatenate([c, a])
            else:
                planes = np.concatenate([c, a])
            yield quantize_band(planes.transpose(1, 2, 0), depth)

    def rgba_codes(self, depth: BitDepth = 8) -> np.ndarray:
        """(h, w, 4) codes of the whole layer, uint8 or (``depth`` 16) uint16, filled a band at a time."""
        out = np.empty((self.height, self.width, 4), dtype=np.uint16 if depth == 16 else np.uint8)
        for r0, band in zip(range(0, self.height, BAND_ROWS), self.bands(depth)):
            out[r0 : r0 + band.shape[0]] = band
        return out

    def rgba_uint8(self) -> np.ndarray:
        """(h, w, 4) uint8, rounded to nearest."""
        return self.rgba_codes(8)


@dataclass
class ExportGroup:
    """A group of an interchange file: its layers (``ExportLayer`` or ``ExportGroup``, bottom to top) blended
    as one (``isolated``) or passed through."""

    name: str
    key: str
    op: Op
    opacity: float
    visible: bool
    isolated: bool
    layers: list
    source: str = ""
    clip: bool = False


def leaves(layers: list) -> list[ExportLayer]:
    """Every ``ExportLayer`` of a list that may hold groups, bottom to top."""
    out: list[ExportLayer] = []
    for item in layers:
        out.extend(leaves(item.layers) if isinstance(item, ExportGroup) else [item])
    return out


def _warn(warn: Callable[[str], None] | None, message: str) -> None:
    if warn is not None:
        warn(message)
    else:
        warnings.warn(message, stacklevel=3)


def _layer_raster(stack, layer, origin: tuple[int, int] = (0, 0)) -> tuple[np.ndarray, np.ndarray | None] | None:
    """(color (C, h, w), alpha × mask (1, h, w) or None: opaque) values y of a layer, views of its tensors where
    they are float32 on the CPU (no float64 copy), or None if it has no pixels. ``origin``: where the enclosing
    groups put the layer (a gradient or pattern laid out on the canvas needs it)."""
    if isinstance(layer, SolidLayer):
        rgba = list(layer.color)
        size = layer.size
        w, h = (size.width, size.height) if size else (stack.width, stack.height)
        lo, hi = layer.range
        rgb = lo + (hi - lo) * np.asarray(rgba[:3], dtype=np.float64)
        color = np.broadcast_to(rgb[:, None, None], (3, h, w))  # zero-stride: a solid layer costs no memory
        a = rgba[3] if len(rgba) == 4 else 1.0
        return color, None if a == 1.0 else np.broadcast_to(np.float64(a), (1, h, w))
    t = stack.tensors.get(layer.id)
    if layer.kind == "gradient":  # its fill drawn as the compositor draws it (a masked one's tensors hold the mask)
        t = gradient_tensors(layer, stack.width, stack.height, origin, None if t is None else t.mask, "layer")
    elif layer.kind == "pattern" and t is not None:  # its tile repeated over its rectangle, as the compositor does
        t = pattern_tensors(layer, t, stack.width, stack.height, origin, "layer")
    if t is None:
        return None
    if isinstance(layer, SurfaceLayer):  # the multiplier its normal map renders to, as the compositor blends it
        t = layer_surface_tensors(t, layer)[0]
    color = _numpy(t.color)
    if color.ndim != 3:
        raise ExportError(
            f"colour has shape {tuple(color.shape)}; expected (C, h, w) (no batch) to export",
            where=f"layer {layer.id!r}",
        )
    h, w = color.shape[1:]
    alpha = None if t.alpha is None else _numpy(t.alpha).reshape(1, h, w)
    if t.mask is not None:
        mask = _numpy(t.mask).reshape(1, h, w)
        alpha = mask if alpha is None else alpha * mask
    return color, alpha


def _numpy(t: torch.Tensor) -> np.ndarray:
    """A tensor's values as numpy without a copy where they are on the CPU (float32 stays float32)."""
    return t.detach().cpu().numpy()


def _crop(color, alpha, x, y, W, H):
    h, w = color.shape[1:]
    x0, y0, x1, y1 = max(x, 0), max(y, 0), min(x + w, W), min(y + h, H)
    if x0 >= x1 or y0 >= y1:
        return None
    sl = (slice(None), slice(y0 - y, y1 - y), slice(x0 - x, x1 - x))
    return color[sl], None if alpha is None else alpha[sl], x0, y0


def dodge_codes(y: np.ndarray, depth: int = 8) -> np.ndarray:
    """Colour-dodge values d (multiples of 1/m, m = 2^depth − 1) whose m/(m − m·d) is nearest y ≥ 1."""
    m = float(2**depth - 1)
    y = np.maximum(y, 1.0)
    q0 = np.clip(np.floor(m * (1.0 - 1.0 / y)), 0, m - 2)
    gain = lambda q: m / (m - q)  # noqa: E731
    q = np.where(np.abs(gain(q0 + 1) - y) < np.abs(gain(q0) - y), q0 + 1, q0)
    return q / m


def background_layer(stack) -> ExportLayer | None:
    """An opaque canvas-size layer of the background colour (files flatten to our opaque composite); None for a
    transparent document, which has no background."""
    background = stack.document.canvas.background
    if background is None:
        return None
    W, H = stack.width, stack.height
    color = np.broadcast_to(np.asarray(background, dtype=np.float64)[:, None, None], (3, H, W))
    return ExportLayer("Background", "_background", "normal", 0, 0, color, None, 1.0, True)


def composite_layer(composite, alpha=None) -> ExportLayer:
    """The exact composite (3, H, W) in [0, 1] as a top layer: opaque, or of ``alpha`` (1, H, W) for a
    transparent document's."""
    color = _as_array(composite)
    return ExportLayer(
        COMPOSITE_NAME, "_composite", "normal", 0, 0, color, None if alpha is None else _as_array(alpha), 1.0, True
    )


def _as_array(x) -> np.ndarray:
    return _numpy(x) if isinstance(x, torch.Tensor) else np.asarray(x)


def export_layers(
    stack,
    composite,
    *,
    target: str,
    warn: Callable[[str], None] | None = None,
    groups: bool = False,
    alpha=None,
) -> list:
    """The stack's layers as interchange layers, bottom to top: background first (none for a transparent
    document), and on top, when the layers cannot reproduce it, the exact ``composite`` (3, H, W) with its
    ``alpha`` (1, H, W) for a transparent document (see the module docstring).

    ``target`` names the format in warnings ("OpenRaster", "PSD"). ``groups``: groups become ``ExportGroup``
    entries (nested); otherwise their layers are listed flat in their place.
    """
    layers, inexact = _layers(stack, target, warn, groups)
    if stack.document.clamp == "output" and _clamp_matters(stack, composite):
        inexact.append("clamp='output' (intermediate values outside [0, 1]; paint programs clamp after every layer)")
    if inexact:
        _warn(
            warn,
            f"{target} cannot express {'; '.join(inexact)}: the layers are written as they are, and a top layer "
            f"{COMPOSITE_NAME!r} holds the exact composite so the file flattens to it (hide it to edit the layers)",
        )
        layers.append(composite_layer(composite, alpha))
    return layers


def _clamp_matters(stack, composite) -> bool:
    """Whether clamping after every layer changes the 8-bit composite of a clamp='output' stack."""
    from lasagna.io.render import render_stack
    from lasagna.io.stack import Stack

    interop = Stack(stack.document.replace(clamp="layer"), stack.folder, stack.tensors, stack.bit_depths)
    codes = lambda img: np.rint(np.clip(np.asarray(img, dtype=np.float64), 0, 1) * 255)  # noqa: E731
    return bool((codes(render_stack(interop, dtype=torch.float64).image.numpy()) != codes(_as_array(composite))).any())


class _Walk:
    """What exporting the layers of one stack collects: the canvas size, what is not exact, the target."""

    def __init__(self, stack, target: str, warn, groups: bool):
        self.stack, self.target, self.warn, self.groups = stack, target, warn, groups
        self.W, self.H = stack.width, stack.height
        self.inexact: list[str] = []
        self.fills: dict[str, list[str]] = {}  # fill layers (gradient, pattern) by kind, written as their pixels

    def items(self, layers, origin: tuple[int, int], shown: bool, isolated_in: bool) -> list:
        """Export items of ``layers`` (bottom to top) whose offsets are relative to ``origin``; ``shown``: every
        enclosing group is visible (flat export only); ``isolated_in``: over transparency (inside an isolated
        group, or a transparent document's top level)."""
        out: list = []
        for i, layer in enumerate(layers):
            if layer.kind == "group":
                made = self.group(layer, origin, shown, isolated_in)
            elif layer.kind == "adjustment":  # no writer here makes adjustment layers: the composite shows it
                made = []
                if layer.visible and shown:
                    self.inexact.append(f"{layer.adjustment.type} adjustment layer {layer.id!r} (left out)")
            else:
                made = self.leaf(layer, origin, shown, isolated_in)
            out.extend(made)
            if layer.clip or (i + 1 < len(layers) and layers[i + 1].clip):
                self.clipping(layer, made)
        return out

    def clipping(self, layer, made: list) -> None:
        """Mark the items of a layer of a clipping chain (base or clipped), and say what the target cannot hold."""
        if not self.groups:
            self.inexact.append(f"the clipping chain of layer {layer.id!r} (groups are written flat)")
        elif len(made) != 1:
            self.inexact.append(f"layer {layer.id!r} in a clipping chain (written as {len(made)} layers)")
        elif layer.clip and layer.blend not in ("normal", "alpha-linear") and self.target == "OpenRaster":
            self.inexact.append(
                f"the {layer.blend} blend of clipped layer {layer.id!r} (Krita's ORA clips normal only)"
            )
        elif layer.clip and layer.kind == "group" and self.target == "PSD":
            self.inexact.append(f"clipped group {layer.id!r} (Photoshop clips layers, not groups)")
        for item in made:
            item.clip = bool(layer.clip)

    def group(self, layer, origin, shown, isolated_in) -> list:
        offset = (origin[0] + layer.offset.x, origin[1] + layer.offset.y)
        if not self.groups:
            if layer.isolated or layer.opacity != 1.0 or layer.mask is not None:
                what = "isolated" if layer.isolated else ("masked" if layer.mask is not None else "partly opaque")
                self.inexact.append(f"{what} group {layer.id!r} (its layers are written flat, outside any group)")
            return self.items(layer.layers, offset, shown and layer.visible, isolated_in)
        if layer.mask is not None:
            self.inexact.append(f"the mask of group {layer.id!r} (written without it)")
        if layer.isolated and layer.blend == "dissolve":
            self.inexact.append(f"the dissolve pattern of group {layer.id!r} (each reader draws its own)")
        if not layer.isolated and layer.opacity != 1.0:
            self.inexact.append(f"pass-through group {layer.id!r} of opacity {layer.opacity:g} (readers differ on it)")
        children = self.items(layer.layers, offset, True, isolated_in or layer.isolated)
        op = layer.blend if layer.isolated else "normal"
        return [
            ExportGroup(
                layer.name,
                layer.id,
                op,
                float(layer.opacity),
                bool(layer.visible),
                bool(layer.isolated),
                children,
                source=layer.id,
            )
        ]

    def leaf(self, layer, origin, shown, isolated_in) -> list[ExportLayer]:
        stack, target, W, H = self.stack, self.target, self.W, self.H
        raster = _layer_raster(stack, layer, origin)
        if layer.kind in ("gradient", "pattern"):
            self.fills.setdefault(layer.kind, []).append(layer.id)
        if raster is None:
            if isinstance(layer, LearnedLayer):
                why = f"layer {layer.id!r} is not rendered (run `lasagna render`); left out of the {target} file"
                _warn(self.warn, why)
            return []
        color, alpha = raster
        bad = int((~np.isfinite(color)).sum()) + (0 if alpha is None else int((~np.isfinite(alpha)).sum()))
        if bad:
            raise ExportError(
                f"{bad} values are NaN or infinite; expected finite values to export", where=f"layer {layer.id!r}"
            )
        dissolved = layer.blend == "dissolve"
        if dissolved:
            # Every reader draws its own dissolve pattern: bake ours (α ∈ {0, 1}, opacity 1), on which they agree.
            h, w = color.shape[1:]
            u = dissolve_pattern(torch.arange(h)[:, None], torch.arange(w)[None]).numpy()[None]
            alpha = (u < (1.0 if alpha is None else alpha) * float(layer.opacity)).astype(np.float64)
        cropped = _crop(color, alpha, layer.offset.x + origin[0], layer.offset.y + origin[1], W, H)
        if cropped is None:
            return []  # entirely outside the canvas: contributes nothing
        color, alpha, x, y = cropped
        lo, hi = (float(v) for v in (color.min(initial=0.0), color.max(initial=0.0)))
        if lo < 0.0:  # written as 0: the codes are clamped to [0, 1] (ExportLayer.rgba)
            self.inexact.append(f"the negative values of layer {layer.id!r} (min {lo:.4g}; written as 0)")
        opacity = 1.0 if dissolved else float(layer.opacity)
        common = dict(x=x, y=y, opacity=opacity, visible=shown and layer.visible, source=layer.id)
        fractional = _fractional(alpha, opacity)
        out: list[ExportLayer] = []
        if layer.blend == "multiply":
            above_one = hi > 1.0
            if above_one and isolated_in:
                self.inexact.append(
                    f"multiplier values above 1 of layer {layer.id!r} over transparency (isolated group, no background)"
                )
            gain, dodge = None, _dodge
            if above_one and fractional:
                # Over an opaque backdrop a multiply with alpha is a multiply by the gain
                # g = 1 + α(y − 1): bake α into the values, so the pair is exact for any α.
                gain = _gain(opacity)
                dodge = _gain(opacity, dodge=True)
                common.update(opacity=1.0)
            out.append(ExportLayer(layer.name, layer.id, "multiply", color=color, alpha=alpha, values=gain, **common))
            if above_one:
                out.append(
                    ExportLayer(
                        f"{layer.name} (colour dodge: values above 1)",
                        f"_dodge/{layer.id}",
                        "color-dodge",
                        color=color,
                        alpha=alpha,
                        values=dodge,
                        **common,
                    )
                )
        elif layer.blend == "plus":
            top = hi
            if fractional:
                if isolated_in:
                    self.inexact.append(
                        f"partial alpha of plus layer {layer.id!r} over transparency (isolated group, no background)"
                    )
                # Paint programs clamp inside the blend, Cb + α(min(1, Cb + Cs) − Cb), where the
                # W3C plus is min(1, Cb + α·Cs); with α baked in (Cs' = α·Cs, opaque) both agree.
                top = _baked_max(color, alpha, opacity)
                common.update(opacity=1.0)
            parts = max(1, int(np.ceil(max(top, 0.0) - 1e-12)))
            for k in range(parts):
                name = layer.name if k == 0 else f"{layer.name} (part {k + 1})"
                key = layer.id if k == 0 else f"_plus{k + 1}/{layer.id}"
                values = _plus_part(k, opacity if fractional else None)
                out.append(ExportLayer(name, key, "plus", color=color, alpha=alpha, values=values, **common))
        else:
            if hi > 1.0:
                self.inexact.append(
                    f"the values above 1 of {layer.blend} layer {layer.id!r} (max {hi:.4g}; written as 1)"
                )
            out.append(ExportLayer(layer.name, layer.id, layer.blend, color=color, alpha=alpha, **common))
        if isinstance(layer, SurfaceLayer):
            out.insert(0, self.normal_map(layer, origin))
        return out

    def normal_map(self, layer, origin) -> ExportLayer:
        """A surface layer's normal map as a hidden normal layer (tangent space, +Y up) below its rendered
        multiplier: a reader flattens the file as we do, and an artist can show or reuse the map (its relief times
        the layer's ``relief``, so the map lights as the layer renders). Its name is ``map_name``'s: what the
        import needs to read the pair back as the layer (`lasagna.export.surface_import`). Unlike every other
        raster it is written whole where the canvas cuts the layer (a hidden layer is not flattened, and its
        cast shadows, occlusion and point lights are the whole map's); a layer wholly off the canvas, whose
        multiplier is not written, gets a 1 × 1 transparent stand-in."""
        color = _numpy(relieved_map(self.stack.tensors[layer.id].color, layer.relief))
        x, y = layer.offset.x + origin[0], layer.offset.y + origin[1]
        alpha = None
        if _crop(color, None, x, y, self.W, self.H) is None:
            color, alpha, x, y = color[:, :1, :1], np.zeros((1, 1, 1)), 0, 0
        return ExportLayer(
            map_name(layer),
            f"{NORMALS_DIR}/{layer.id}",
            "normal",
            x=x,
            y=y,
            color=color,
            alpha=alpha,
            opacity=1.0,
            visible=False,
            source=layer.id,
        )


def _fractional(alpha: np.ndarray | None, opacity: float) -> bool:
    """Whether alpha × mask × opacity takes a value strictly between 0 and 1 somewhere."""
    if opacity == 0.0:
        return False
    if alpha is None:
        return opacity != 1.0
    if opacity != 1.0:
        return bool((alpha != 0).any())
    return not bool(np.isin(alpha, (0.0, 1.0)).all())


def _gain(opacity: float, dodge: bool = False) -> Values:
    """A multiply layer's values with its α = alpha × mask × opacity baked in: the gain g = 1 + α(y − 1), opaque
    (``dodge``: g's colour-dodge codes)."""

    def values(c: np.ndarray, a: np.ndarray, depth: int) -> tuple[np.ndarray, np.ndarray]:
        g = 1.0 + (a * opacity) * (c - 1.0)
        return (dodge_codes(g, depth) if dodge else g), np.ones_like(a)

    return values


def _dodge(c: np.ndarray, a: np.ndarray, depth: int) -> tuple[np.ndarray, np.ndarray]:
    return dodge_codes(c, depth), a


def _plus_part(k: int, baked: float | None) -> Values:
    """Part k of a plus layer, min(max(y − k, 0), 1); ``baked``: the opacity, with α baked in (y' = α·y, opaque)."""

    def values(c: np.ndarray, a: np.ndarray, depth: int) -> tuple[np.ndarray, np.ndarray]:
        if baked is None:
            return c - k, a
        return (a * baked) * c - k, np.ones_like(a)

    return values


def _baked_max(color: np.ndarray, alpha: np.ndarray | None, opacity: float) -> float:
    """max of α·y (α = alpha × mask × opacity) in float64, a band of rows at a time."""
    top = 0.0
    for r0 in range(0, color.shape[1], BAND_ROWS):
        c = np.asarray(color[:, r0 : r0 + BAND_ROWS], dtype=np.float64)
        a = 1.0 if alpha is None else np.asarray(alpha[:, r0 : r0 + BAND_ROWS], dtype=np.float64)
        top = max(top, float(((a * opacity) * c).max(initial=0.0)))
    return top


def _layers(stack, target: str, warn, groups: bool = False) -> tuple[list, list[str]]:
    walk = _Walk(stack, target, warn, groups)
    if stack.document.blend_space == "linear":
        walk.inexact.append("blend_space='linear' (paint programs blend sRGB-encoded values)")
    background = background_layer(stack)
    # A transparent document's top level is composited over transparency, as an isolated group's layers are: the
    # helper layers that assume an opaque backdrop (dodge pairs, baked alpha) are not exact there either.
    top = walk.items(stack.document.layers, (0, 0), True, background is None)
    for kind, ids in walk.fills.items():
        _warn(warn, f"{kind} layer(s) {', '.join(map(repr, ids))} written to {target} as their pixels (the "
              f"live {kind} fill is not written)")  # fmt: skip
    out = [*([background] if background is not None else []), *top]
    return out, walk.inexact
