"""Reading a layered PSD into a stack (``lasagna import-psd``), through psd-tools (the optional extra).

What each PSD thing becomes:

* a pixel layer → a ``pixels`` layer: its RGBA at its offset, ``blend`` the psd-tools ``BlendMode`` of the
  same name (``LINEAR_DODGE`` → ``linear-dodge``: Photoshop's, clamped inside the blend), ``opacity`` = opacity
  × fill (for a layer without effects the two fade its paint alike, except under Photoshop's eight modes whose
  fill acts inside the blend — color burn/dodge, linear burn/dodge, vivid/linear light, hard mix, difference:
  a fill below 255 there is one warning line), ``visible``; its user mask (enabled, cut to the layer's
  rectangle, the mask's background colour outside the stored bbox) → ``mask``;
* a group → a ``group`` layer: blend ``PASS_THROUGH`` → ``isolated: false`` (pass-through), any other →
  ``isolated: true`` with that blend (W3C Compositing Level 1, section 8); its mask → a canvas-size group mask;
* a clipping mask (a layer or group with clipping layers over it) → the base and its clipped layers, each with
  ``clip: true`` (a clipping chain), when psd-tools would read each as it is; a clipping layer that clips to
  nothing (the bottom of its list, or above a clipped group: psd-tools and Photoshop draw none) is left out with
  a warning line;
* an adjustment layer of a kind the compositor has (levels, curves, hue/saturation with its colour ranges and its
  colorize, brightness/contrast new and legacy, exposure, invert, posterize, threshold; channel mixer, color
  balance, vibrance, black & white, gradient map, photo filter: ``psd_adjust.py``) → an ``adjustment`` layer with
  its parameters (``adjustment_params``), its blend, opacity × fill and its mask on the canvas (the mask's
  background colour outside its data);
* a solid colour fill layer without a mask, vector mask or effects → a ``solid`` layer of its colour (canvas size);
* a gradient fill layer (custom stops) without a vector mask, effects or clipping layers → a ``gradient`` layer of
  its settings (``psd_adjust.gradient_fill``) over the layer's rectangle (the canvas when it has none), with its mask;
* a pattern fill layer whose RGB pattern is in the file, without a vector mask, effects or clipping layers → a
  ``pattern`` layer (``psd_adjust.pattern_fill``: scale, phase, align; its tile the pattern's pixels) over the
  layer's rectangle, with its mask; one whose pattern is missing or not RGB is one warning line;
* another fill layer → a ``pixels`` layer of the fill Photoshop stored in its channels, with its mask (psd-tools'
  rendering when none is stored);
* layers psd-tools can draw but a stack cannot hold as such — type, shape and smart-object layers, a layer with
  effects, a clipping base whose chain holds one of those — → a ``pixels`` layer of psd-tools' rendering of it
  (``Layer.composite``), one warning line each saying what was rasterised;
* what cannot be represented at all — other adjustment layers, a group's fill opacity, knockout — one warning
  line each; nothing is dropped without one.

The PSD's top level is composited over transparency, and so is a transparent document's (``canvas.background``
null): unless the bottom visible layer is an opaque, full-canvas normal one, the stack is transparent and its
composite carries the PSD's alpha (psd-tools' composite, not laid over anything); with such a base nothing shows
through, and the background is white (W3C section 8.3, the page group's backdrop). Refused in one line: a file psd-
tools cannot read, a colour mode other than RGB or grayscale, a canvas, layer or mask over the pixel limit, decoding
over the memory budget, groups nested deeper than a stack may hold (``lasagna.limits``). A name with control
characters is imported with each replaced by U+FFFD, with a warning line (the document's name rule,
``lasagna.document.types.check_name``).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from lasagna.document.pattern import tile_problem
from lasagna.document.types import sanitise_name, unique_id
from lasagna.errors import ExportError, ImageError
from lasagna.export.psd_adjust import READERS, descriptor_color, gradient_fill, hue_ranges, pattern_fill
from lasagna.export.psd_tools_api import INSTALL_HINT, psd_blend_modes
from lasagna.io.png import DEFAULT_MAX_PIXELS
from lasagna.limits import MAX_GROUP_DEPTH, check_memory

# Page group backdrop (W3C Compositing Level 1, section 8.3: "composited with a backdrop color of white").
PAGE_BACKGROUND = (1.0, 1.0, 1.0)
# Bytes a decoded layer pixel costs on import: float32 RGBA read by psd-tools, then our float32 tensors
# (colour, alpha), and the 16-bit PNG bytes written: ~2 copies of 4 float32 channels. Kept until saved.
IMPORT_BYTES_PER_PIXEL = 2 * 4 * 4
# A mask pixel on the rectangle it is cut to (the layer's, or the canvas for a group): the float64 array it
# is cut into, our float32 tensor, the PNG's bytes. Kept until saved.
MASK_BYTES_PER_PIXEL = 8 + 4 + 4
# A pixel of a mask's stored rectangle while it is decoded (one at a time): the inflated channel bytes and
# psd-tools' copy of them, Pillow's image (16/32-bit masks go through a 4-byte image), the 8-bit copy.
MASK_DECODE_BYTES = {8: 4, 16: 2 * 2 + 2 * 4 + 2, 32: 2 * 4 + 2 * 4 + 2}
# A canvas pixel while psd-tools renders a rasterised layer (Layer.composite): its float colour, shape and
# alpha arrays for the layer and each clipping layer's, and the RGBA image returned (one layer at a time).
COMPOSITE_BYTES_PER_PIXEL = 3 * IMPORT_BYTES_PER_PIXEL
# Photoshop's eight modes whose Fill blends differently from Opacity (the "special eight" of Photoshop tutorials,
# e.g. photoshoptrainingchannel.com, "Opacity vs. Fill with blend modes"); how is not published, so not modelled.
FILL_INSIDE_BLEND = frozenset(
    {"color-burn", "linear-burn", "color-dodge", "linear-dodge"}
    | {"vivid-light", "linear-light", "hard-mix", "difference"}
)
# psd-tools layer kinds rasterised by its own renderer (their stored channels may be stale or absent).
RASTERISED_KINDS = {"type": "type layer", "shape": "shape layer", "smartobject": "smart object"}


def _signed16(v: int) -> int:
    """A legacy brightness/contrast value: stored as an unsigned 16-bit integer, read as a signed one."""
    return v - 65536 if v >= 32768 else v


def _levels(records, warn: Callable[[str], None], what: str) -> dict | None:
    """Levels' records (composite, red, green, blue, … in codes, gamma × 100) as the document's parameters."""
    out: dict[str, Any] = {"type": "levels"}
    for name, r in zip(("rgb", "red", "green", "blue"), records):
        lo, hi = r.input_floor / 255.0, r.input_ceiling / 255.0
        if lo >= hi:
            warn(f"{what}: levels {name} input points {r.input_floor} ≥ {r.input_ceiling}; that channel left as is")
            continue
        gamma = min(max(r.gamma / 100.0, 0.01), 9.99)  # Photoshop's dialog range (psd-tools clamps alike)
        out[name] = dict(
            in_black=lo, in_white=hi, gamma=gamma, out_black=r.output_floor / 255.0, out_white=r.output_ceiling / 255.0
        )
    return out


def _curve_points(points) -> list[list[float]]:
    """A curve's (output, input) code pairs as [x, y] in [0, 1], sorted by x, each x once."""
    seen: dict[int, int] = {}
    for out_code, in_code in points:
        seen.setdefault(int(in_code), int(out_code))
    return [[x / 255.0, seen[x] / 255.0] for x in sorted(seen)]


def adjustment_params(layer, warn: Callable[[str], None], what: str, depth: int = 8) -> dict | None:
    """The document's ``adjustment`` of a psd-tools adjustment layer (or a legacy brightness/contrast pixel
    layer), or None (with a warning line) for a kind the compositor does not have."""
    from psd_tools.constants import Tag

    kind = layer.kind
    if kind == "pixel":  # psd-tools reads Photoshop's legacy brightness/contrast block as a layer without pixels
        b = layer.tagged_blocks.get_data(Tag.BRIGHTNESS_AND_CONTRAST)
        return dict(
            type="brightness-contrast",
            brightness=float(_signed16(b.brightness)),
            contrast=float(_signed16(b.contrast)),
            legacy=True,
        )
    if kind == "levels":
        return _levels(layer.data or [], warn, what)
    if kind == "curves":
        out: dict[str, Any] = {"type": "curves"}
        for item in layer.extra or []:
            name = {0: "rgb", 1: "red", 2: "green", 3: "blue"}.get(item.channel_id)
            pts = _curve_points(item.points)
            if name is not None and len(pts) >= 2:
                out[name] = pts
        return out
    if kind == "brightnesscontrast":
        return dict(
            type="brightness-contrast",
            brightness=float(layer.brightness),
            contrast=float(layer.contrast),
            legacy=bool(layer.use_legacy),
        )
    if kind == "exposure":
        return dict(
            type="exposure",
            exposure=float(layer.exposure or 0.0),
            offset=float(layer.exposure_offset or 0.0),
            gamma=min(max(float(layer.gamma or 1.0), 0.01), 9.99),
        )
    if kind == "huesaturation":
        h, sat, light = layer.master or (0, 0, 0)
        out = dict(type="hue-saturation", hue=float(h), saturation=float(sat), lightness=float(light))
        out["ranges"] = hue_ranges(layer.data)
        if layer.enable_colorization:
            ch, cs, cl = layer.colorization or (0, 25, 0)
            out["colorize"] = dict(hue=float(ch % 360), saturation=float(cs), lightness=float(cl))
        return out
    if kind == "invert":
        return dict(type="invert")
    if kind == "posterize":
        return dict(type="posterize", levels=min(max(int(layer.posterize or 4), 2), 255), bits=16 if depth > 8 else 8)
    if kind == "threshold":
        # Photoshop compares the luminosity's codes with the level: half a code below it is met.
        code = min(max(int(layer.threshold or 128), 1), 255) / 255.0
        return dict(type="threshold", level=code - (0.5 / 255.0 if depth <= 8 else 0.5 / 65535.0))
    if kind in READERS:
        return READERS[kind](layer, warn, what)
    warn(f"{what}: {kind} adjustment layer cannot be represented in a stack; left out")
    return None


def _legacy_adjustment(layer) -> bool:
    """A pixel layer that is Photoshop's legacy brightness/contrast adjustment (psd-tools has no class for it)."""
    from psd_tools.constants import Tag

    return layer.kind == "pixel" and Tag.BRIGHTNESS_AND_CONTRAST in layer.tagged_blocks


def _require():
    try:
        from psd_tools import PSDImage
        from psd_tools.api.layers import AdjustmentLayer, FillLayer
        from psd_tools.constants import BlendMode, ColorMode
    except ImportError:
        raise ExportError(f"PSD import needs psd-tools, which is not installed; expected it: {INSTALL_HINT}") from None
    return PSDImage, BlendMode, ColorMode, AdjustmentLayer, FillLayer


class _Reader:
    """One PSD's layers → document dicts and tensors (module docstring), with its warnings."""

    def __init__(self, psd, where: str, max_pixels: int, warn: Callable[[str], None]):
        _, self.BlendMode, self.ColorMode, self.AdjustmentLayer, self.FillLayer = _require()
        self.psd, self.where, self.max_pixels, self.warn = psd, where, max_pixels, warn
        self.modes = {mode: name for name, mode in psd_blend_modes(self.BlendMode).items()}
        self.taken: set[str] = set()
        self.tensors: dict[str, Any] = {}
        self.clipped: list[Any] = []  # clipping layers imported with their chain

    def layers(self, group, path: str) -> list[dict]:
        out: list[dict] = []
        for layer in group:
            here = f"{path}/{layer.name}" if path else layer.name
            if layer.clipping:
                if not any(layer is c for c in self.clipped):
                    self.warn(
                        f"{self.where}: layer {here!r} is clipped to no layer (the bottom of its list, or above a "
                        "clipped group); left out, as Photoshop draws it"
                    )
                continue  # imported with the layer it clips to (see clip_chain)
            entry = self.layer(layer, here)
            if entry is not None:
                out.append(entry)
                out.extend(self.clip_chain(layer, entry, path))
        return out

    def _drawn_by_psd_tools(self, layer) -> bool:
        return (
            layer.kind in RASTERISED_KINDS
            or layer.has_effects()
            or (isinstance(layer, self.FillLayer) and not _has_pixels(layer))
        )

    def _chain_splits(self, layer) -> bool:
        """Whether the layers clipped to ``layer`` are imported as a clipping chain (each its own layer, ``clip``)
        rather than rasterised with it: the base and every clipped layer are read as they are."""
        return not self._drawn_by_psd_tools(layer) and not any(self._drawn_by_psd_tools(c) for c in layer.clip_layers)

    def clip_chain(self, layer, entry: dict, path: str) -> list[dict]:
        """The entries of the layers clipped to ``layer`` (``clip``: true), when its chain splits."""
        if not layer.has_clip_layers(visible=False) or not self._chain_splits(layer):
            return []
        if layer.fill_opacity != 255 and not layer.is_group():
            self.warn(
                f"{self.where}: layer {layer.name!r} is a clipping base of fill {layer.fill_opacity}/255, imported as "
                "opacity: it fades its clipped layers too"
            )
        out = []
        for c in layer.clip_layers:
            self.clipped.append(c)
            clipped = self.layer(c, f"{path}/{c.name}" if path else c.name)
            if clipped is not None:
                out.append({**clipped, "clip": True})
        return out

    def _blend(self, layer, what: str) -> str:
        mode = layer.blend_mode
        if mode in self.modes:
            return self.modes[mode]
        self.warn(f"{what}: blend mode {mode.name} has no stack equivalent; imported as normal")
        return "normal"

    def layer(self, layer, path: str) -> dict | None:
        what = f"{self.where}: layer {path!r}"
        adjustment = None
        if isinstance(layer, self.AdjustmentLayer) or _legacy_adjustment(layer):
            adjustment = adjustment_params(layer, self.warn, what, self.psd.depth)
            if adjustment is None:
                return None
        name = sanitise_name(layer.name)
        if name != layer.name:
            self.warn(f"{what}: name holds control characters; imported as {name!r}")
        lid = unique_id(name, self.taken)
        entry: dict[str, Any] = {
            "id": lid,
            "name": name or lid,
            "opacity": layer.opacity / 255.0,
            "visible": bool(layer.visible),
        }
        if adjustment is not None:
            # Fill fades an adjustment as opacity does (psd-tools' _get_const: shape × opacity).
            entry.update(kind="adjustment", blend=self._blend(layer, what), adjustment=adjustment)
            entry["opacity"] *= layer.fill_opacity / 255.0
            mask = self._mask(layer, (0, 0, self.psd.width, self.psd.height), what)
            if mask is not None:
                entry["mask"] = f"masks/{lid}.png"
                from lasagna.io.stack import group_mask_tensors

                self.tensors[lid] = group_mask_tensors(_tensor(mask))
            return entry
        if layer.is_group():
            entry.update(kind="group", layers=self.layers(layer, path))
            if layer.blend_mode == self.BlendMode.PASS_THROUGH:
                entry.update(isolated=False, blend="normal")
            else:
                entry.update(isolated=True, blend=self._blend(layer, what))
            if layer.fill_opacity != 255:
                self.warn(f"{what}: a group's fill opacity ({layer.fill_opacity}/255) cannot be represented; ignored")
            if layer.has_effects():
                self.warn(f"{what}: a group's layer effects cannot be represented; left out")
            mask = self._mask(layer, (0, 0, self.psd.width, self.psd.height), what)
            if mask is not None:
                entry["mask"] = f"masks/{lid}.png"
                from lasagna.io.stack import group_mask_tensors

                self.tensors[lid] = group_mask_tensors(_tensor(mask))
            return entry
        solid = self._solid_fill(layer, what)
        if solid is not None:  # a solid colour fill over the canvas, no mask: a solid layer (its colour, any size)
            entry.update(kind="solid", color=solid, blend=self._blend(layer, what))
            entry["opacity"] *= layer.fill_opacity / 255.0
            return entry
        gradient = self._gradient_fill(layer, what)
        if gradient is not None:  # a live gradient over the layer's rectangle (the canvas if it has none), its mask
            rect = layer.bbox if _area(layer.bbox) else (0, 0, self.psd.width, self.psd.height)
            entry.update(kind="gradient", gradient=gradient, blend=self._blend(layer, what))
            entry["opacity"] *= layer.fill_opacity / 255.0
            if tuple(rect) != (0, 0, self.psd.width, self.psd.height):
                entry.update(offset={"x": int(rect[0]), "y": int(rect[1])})
                entry.update(size={"width": int(rect[2] - rect[0]), "height": int(rect[3] - rect[1])})
            mask = self._mask(layer, rect, what)
            if mask is not None:
                from lasagna.io.stack import group_mask_tensors

                entry["mask"] = f"masks/{lid}.png"
                self.tensors[lid] = group_mask_tensors(_tensor(mask))
            return entry
        pattern = self._pattern_fill(layer, what)
        if pattern is not None:  # a live pattern over the layer's rectangle (the canvas if it has none), its mask
            settings, color, alpha = pattern
            rect = layer.bbox if _area(layer.bbox) else (0, 0, self.psd.width, self.psd.height)
            entry.update(kind="pattern", source=f"layers/{lid}.png", pattern=settings, blend=self._blend(layer, what))
            entry["opacity"] *= layer.fill_opacity / 255.0
            if tuple(rect) != (0, 0, self.psd.width, self.psd.height):
                entry.update(offset={"x": int(rect[0]), "y": int(rect[1])})
                entry.update(size={"width": int(rect[2] - rect[0]), "height": int(rect[3] - rect[1])})
            mask = self._mask(layer, rect, what)
            if mask is not None:
                entry["mask"] = f"masks/{lid}.png"
            from lasagna.compose.pattern import TileTensors

            alpha_t = None if alpha is None else _tensor(alpha)
            self.tensors[lid] = TileTensors(_tensor(color), alpha_t, None if mask is None else _tensor(mask))
            return entry
        rgba, bbox, baked = self._raster(layer, what)
        if rgba is None:
            self.warn(f"{what}: {layer.kind} layer has no pixels; left out")
            return None
        blend = self._blend(layer, what)
        fill = 1.0 if baked else layer.fill_opacity / 255.0
        entry.update(
            kind="pixels",
            source=f"layers/{lid}.png",
            blend=blend,
            opacity=1.0 if baked else entry["opacity"] * fill,
            offset={"x": int(bbox[0]), "y": int(bbox[1])},
        )
        mask = None if baked else self._mask(layer, bbox, what)
        if blend in FILL_INSIDE_BLEND and not baked and layer.fill_opacity != 255:
            self.warn(
                f"{what}: fill opacity {layer.fill_opacity}/255 of a {blend} layer imported as opacity (Photoshop "
                "applies fill inside this mode's blend): the composite may differ"
            )
        color, alpha = _tensor(rgba[:3]), _tensor(rgba[3:])
        if mask is not None:
            entry["mask"] = f"masks/{lid}.png"
        from lasagna.compose.layer import LayerTensors

        self.tensors[lid] = LayerTensors(color, alpha, None if mask is None else _tensor(mask))
        return entry

    def _solid_fill(self, layer, what: str) -> list[float] | None:
        """A solid colour fill layer's RGB when a ``solid`` layer holds it exactly (no mask, vector mask or effects;
        psd-tools' ``draw_solid_color_fill`` covers the canvas); None otherwise (its stored pixels are read)."""
        if layer.kind != "solidcolorfill" or layer.has_effects() or layer.has_vector_mask() or layer.has_clip_layers():
            return None
        if layer.has_mask() and layer.mask is not None and not layer.mask.disabled:
            return None
        rgb = descriptor_color(layer.data, self.warn, what)
        return None if rgb is None else list(rgb)

    def _gradient_fill(self, layer, what: str) -> dict | None:
        """A gradient fill layer's ``gradient`` when a ``gradient`` layer holds it (no vector mask, effects or clipping
        layers); None otherwise (its stored pixels are read)."""
        if layer.kind != "gradientfill" or layer.has_effects() or layer.has_vector_mask() or layer.has_clip_layers():
            return None
        return gradient_fill(layer._data, self.warn, what)

    def _pattern_fill(self, layer, what: str) -> tuple[dict, np.ndarray, np.ndarray | None] | None:
        """A pattern fill layer's (``pattern``, tile colour (3, th, tw), tile alpha (1, th, tw) or None) when a
        ``pattern`` layer holds it (no vector mask, effects or clipping layers; its pattern in the file, RGB, within
        ``MAX_PATTERN_PIXELS``); None otherwise (its stored pixels are read, with one warning saying why)."""
        if layer.kind != "patternfill" or layer.has_effects() or layer.has_vector_mask() or layer.has_clip_layers():
            return None
        # The reading's notes (a rounded phase, an angle read as 0°) matter only if the live layer is kept: a fill
        # imported as its pixels gets the one line that says why, not those as well.
        notes: list[str] = []
        read = pattern_fill(layer._data, notes.append, what)
        if read is None:
            for note in notes:  # the reason its pixels are read
                self.warn(note)
            return None
        ident, settings = read
        pattern = self.psd._get_pattern(ident)
        why = None
        if pattern is None:
            why = f"its pattern {ident!r} is not in the file"
        elif pattern.image_mode != self.ColorMode.RGB:
            why = f"its pattern is {pattern.image_mode.name} (a pattern layer's tile is RGB or RGBA)"
        else:
            top, left, bottom, right = pattern.data.rectangle
            why = tile_problem(bottom - top, right - left, settings["scale"])
        if why is not None:
            self.warn(f"{what}: a pattern fill is imported as its pixels: {why}")
            return None
        from psd_tools.api import numpy_io

        tile = numpy_io.get_pattern(pattern).transpose(2, 0, 1)  # (C, th, tw) in [0, 1], colour then alpha
        channels = numpy_io.get_pattern_color_channels(pattern)
        if channels != 3:
            self.warn(f"{what}: a pattern fill is imported as its pixels: its tile has {channels} colour channels")
            return None
        for note in notes:
            self.warn(note)
        return settings, tile[:3], tile[3:4] if tile.shape[0] > 3 else None

    def _raster(self, layer, what: str) -> tuple[np.ndarray | None, tuple[int, int, int, int], bool]:
        """(RGBA (4, h, w) float64, bbox, baked): the stored pixels, or psd-tools' rendering of the layer
        (``baked``: mask, opacity, fill, effects and clipping layers are in it)."""
        reasons = []
        if layer.kind in RASTERISED_KINDS or (isinstance(layer, self.FillLayer) and not _has_pixels(layer)):
            reasons.append(RASTERISED_KINDS.get(layer.kind, f"{layer.kind} fill layer"))
        if layer.has_effects():
            reasons.append("layer effects (drawn with the layer's blend mode, not their own)")
        clips = [c.name for c in layer.clip_layers] if layer.has_clip_layers() and not self._chain_splits(layer) else []
        if clips:
            self.clipped.extend(layer.clip_layers)
        if clips:
            reasons.append(f"clipping layers {', '.join(map(repr, clips))}")
        if not reasons:
            bbox = layer.bbox
            self._check_size(bbox, what)
            arr = layer.numpy()
            if arr is None or bbox[2] <= bbox[0] or bbox[3] <= bbox[1]:
                return None, bbox, False
            return _rgba(arr), bbox, False
        bbox = (0, 0, self.psd.width, self.psd.height)
        self._check_size(bbox, what)
        pil = layer.composite(viewport=bbox, color=0.0, alpha=0.0)
        if pil is None:
            return None, bbox, True
        self.warn(f"{what}: {', '.join(reasons)} rasterised by psd-tools into one pixels layer")
        arr = np.asarray(pil.convert("RGBA"), dtype=np.float64) / 255.0
        return arr.transpose(2, 0, 1), bbox, True

    def _mask(self, layer, bbox: tuple[int, int, int, int], what: str) -> np.ndarray | None:
        """The layer's enabled user mask over ``bbox`` (1, h, w), its background colour outside its data."""
        if not layer.has_mask() or layer.mask is None or layer.mask.disabled:
            return None
        m = layer.mask.data  # the user mask's own rectangle and colour: what topil(real=False) returns
        raw = layer.mask.topil(real=False)
        out = np.full((1, bbox[3] - bbox[1], bbox[2] - bbox[0]), m.background_color / 255.0)
        if raw is not None:
            x, y = m.left - bbox[0], m.top - bbox[1]
            w, h = raw.size
            y0, y1, x0, x1 = max(y, 0), min(y + h, out.shape[1]), max(x, 0), min(x + w, out.shape[2])
            if y0 < y1 and x0 < x1:  # only the part on the layer is converted (the rest may be huge)
                part = raw.crop((x0 - x, y0 - y, x1 - x, y1 - y)).convert("L")
                out[0, y0:y1, x0:x1] = np.asarray(part, dtype=np.float64) / 255.0
        if layer.has_vector_mask():
            self.warn(f"{what}: a vector mask cannot be represented; only the pixel mask is imported")
        return out

    def _check_size(self, bbox, what: str) -> None:
        _check_pixels(_area(bbox), self.max_pixels, what)


def _has_pixels(layer) -> bool:
    """Whether a fill layer's channels hold its rendered fill (Photoshop stores it; psd-tools' writer may not)."""
    bbox = layer.bbox
    return bbox[2] > bbox[0] and bbox[3] > bbox[1] and layer.has_pixels()


def _area(bbox) -> int:
    return max(0, bbox[2] - bbox[0]) * max(0, bbox[3] - bbox[1])


def import_bytes(psd, layers_in_file: list, max_pixels: int, where: str) -> int:
    """Peak bytes ``read_psd`` needs, from the layer records alone (nothing is decoded): every raster it
    keeps until the stack is saved — each layer's pixels (canvas-size for one psd-tools rasterises), each
    mask cut to its layer's rectangle (the canvas for a group's) — plus the largest one-at-a-time transient,
    a mask's whole stored rectangle being decoded or a layer being rendered. A layer or mask rectangle over
    ``max_pixels`` is refused (``ImageError``) here, before anything is decoded."""
    _, _, _, AdjustmentLayer, FillLayer = _require()
    canvas = psd.width * psd.height
    depth = psd.depth if psd.depth in MASK_DECODE_BYTES else 32
    kept = transient = 0
    for layer in layers_in_file:
        what = f"{where}: layer {layer.name!r}"
        if layer.is_group() or isinstance(layer, AdjustmentLayer) or _legacy_adjustment(layer):
            target = canvas  # a group's or an adjustment's mask is cut to the canvas (pixels: none)
        elif (
            layer.kind in RASTERISED_KINDS
            or (isinstance(layer, FillLayer) and not _has_pixels(layer))
            or layer.has_effects()
            or layer.has_clip_layers()
        ):
            kept += canvas * IMPORT_BYTES_PER_PIXEL
            transient = max(transient, canvas * COMPOSITE_BYTES_PER_PIXEL)
            continue  # its mask is drawn into the rendering, not decoded on its own
        else:
            target = _area(layer.bbox)
            _check_pixels(target, max_pixels, what)
            kept += target * IMPORT_BYTES_PER_PIXEL
        if layer.has_mask() and layer.mask is not None and not layer.mask.disabled:
            stored = layer.mask.data.width * layer.mask.data.height
            _check_pixels(stored, max_pixels, f"{what}'s mask")
            kept += target * MASK_BYTES_PER_PIXEL
            transient = max(transient, stored * MASK_DECODE_BYTES[depth])
    return kept + transient


def _check_pixels(pixels: int, max_pixels: int, what: str) -> None:
    if pixels > max_pixels:
        raise ImageError(f"holds {pixels} pixels, over the limit of {max_pixels}; expected fewer", what)


def _group_depth(psd) -> int:
    """How deep the PSD's groups nest (0: no group), without recursion."""
    deepest, todo = 0, [(psd, 0)]
    while todo:
        group, depth = todo.pop()
        deepest = max(deepest, depth)
        todo.extend((child, depth + 1) for child in group if child.is_group())
    return deepest


def _first_line(exc: BaseException) -> str:
    """``Type: message`` on one line (psd-tools' messages may span several), at most 200 characters."""
    text = f"{type(exc).__name__}: {exc}".splitlines()[0] if str(exc) else type(exc).__name__
    return text[:200]


def _rgba(arr: np.ndarray) -> np.ndarray:
    """psd-tools' (h, w, C) float array as (4, h, w) float64 RGBA (gray broadcast, opaque if no alpha)."""
    a = np.asarray(arr, dtype=np.float64).transpose(2, 0, 1)
    if a.shape[0] in (1, 2):  # gray, gray+alpha
        a = np.concatenate([np.repeat(a[:1], 3, axis=0), a[1:]])
    if a.shape[0] == 3:
        a = np.concatenate([a, np.ones_like(a[:1])])
    return a[:4]


def _tensor(x: np.ndarray):
    import torch  # only once a file passed its checks

    return torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32))


def _opaque_base(layers: list[dict], stack_tensors: dict, width: int, height: int) -> bool:
    """Whether the bottom visible layer covers the canvas opaquely with blend normal (the canvas is then
    opaque from it on: the document keeps an opaque background; otherwise it is a transparent document)."""
    for entry in layers:
        if not entry["visible"]:
            continue
        t = stack_tensors.get(entry["id"])
        return (
            entry["kind"] == "pixels"
            and entry["blend"] == "normal"
            and entry["opacity"] == 1.0
            and entry.get("offset") == {"x": 0, "y": 0}
            and t is not None
            and tuple(t.color.shape[-2:]) == (height, width)
            and bool((t.alpha == 1.0).all())
            and (t.mask is None or bool((t.mask == 1.0).all()))
        )
    return False


def read_psd(
    path: str | os.PathLike,
    *,
    max_pixels: int = DEFAULT_MAX_PIXELS,
    warn: Callable[[str], None] | None = None,
    surfaces: bool = True,
):
    """A PSD file as a :class:`~lasagna.io.stack.Stack` (module docstring); ``warn`` receives one line per
    thing that was rasterised or could not be represented (default: ``warnings.warn``). A surface layer's rendered
    multiplier over its hidden normal map is made one surface layer again (``lasagna.export.surface_import``) unless
    ``surfaces`` is false."""
    import warnings

    PSDImage, _, ColorMode, _, _ = _require()
    where = str(path)
    warn = warn or (lambda message: warnings.warn(message, stacklevel=2))
    file = Path(path)
    if not file.is_file():
        raise ImageError("does not exist or is not a file; expected a PSD file", where=where)
    try:
        psd = PSDImage.open(file)
    except Exception as exc:  # psd-tools raises many kinds on a corrupt or foreign file
        raise ImageError(f"psd-tools cannot read it ({_first_line(exc)}); expected a PSD file", where) from None
    if psd.color_mode not in (ColorMode.RGB, ColorMode.GRAYSCALE):
        raise ImageError(f"colour mode {psd.color_mode.name}; expected an RGB or grayscale PSD", where=where)
    if not (1 <= psd.width <= 32768 and 1 <= psd.height <= 32768) or psd.width * psd.height > max_pixels:
        raise ImageError(
            f"canvas is {psd.width}x{psd.height}; expected sides in [1, 32768] and at most {max_pixels} pixels", where
        )
    nesting = _group_depth(psd)
    if nesting > MAX_GROUP_DEPTH:
        raise ImageError(
            f"groups nest {nesting} deep; expected at most {MAX_GROUP_DEPTH} levels (a stack's limit)", where
        )
    layers_in_file = list(psd.descendants())
    needed = import_bytes(psd, layers_in_file, max_pixels, where)
    check_memory(needed, f"decoding the PSD's {len(layers_in_file)} layers and their masks", where)
    reader = _Reader(psd, where, max_pixels, warn)
    try:
        layers = reader.layers(psd, "")
    except (ImageError, ExportError):
        raise
    except Exception as exc:  # a layer psd-tools fails to decode
        raise ImageError(f"psd-tools cannot decode a layer ({_first_line(exc)}); expected a valid PSD", where) from None
    if not layers:
        raise ImageError("has no layer a stack can hold; expected at least one pixel layer or group", where=where)
    # Not over an opaque base: a transparent document, composited over transparency as the PSD is.
    background = list(PAGE_BACKGROUND) if _opaque_base(layers, reader.tensors, psd.width, psd.height) else None
    from lasagna.document import Document
    from lasagna.io.stack import Stack

    doc = Document.from_dict(
        {
            "format": "lasagna.stack",
            "version": 1,
            "canvas": {"width": psd.width, "height": psd.height, "background": background},
            "layers": layers,
            "metadata": {"imported_from": Path(where).name},
        },
        where=where,
    )
    depth = 16 if psd.depth > 8 else 8
    from lasagna.export.surface_import import restore_surfaces

    stack = Stack(doc, None, reader.tensors, {id: depth for id in reader.tensors})
    return restore_surfaces(stack, warn, where) if surfaces else stack
