"""The editor's views of the open stack: composites at zoom levels, layer thumbnails and exports.

``SessionViews`` is a part of ``EditSession`` (``lasagna.serve.session``): it reads the session's stack and
caches (``levels``, ``reduced``, ``thumbs``) and asks ``_admit`` before it allocates.

* **Views** are composites at a power-of-two reduction ``level`` (0 = the canvas), each level with its own
  prefix-cache ``Renderer`` (``lasagna.compose.renderer``): toggling or dragging layer k recomputes from k up,
  at the size on screen. Layers are reduced once per level with an area filter and cached by tensor identity.
  Level 0 is exactly ``lasagna composite``; a reduced level is the composite of reduced layers (a preview:
  blends are not linear, so it differs slightly from a reduced composite).
* **Light drags** are a view with a surface layer's ``light`` overridden: the layers below come from the level's
  cached prefix, and only the surface (re-rendered from its stored map, ``compose.surface.surface_tensors``)
  and the layers above it are blended again. **Normal maps** are a surface layer's stored map at a level.
* **Thumbnails** are a layer's stored values reduced to about twice ``THUMB_SIDE``, cached by tensor identity.
* **Exports** (ORA, PSD, the composite PNG) encode a copy of the stack outside the session's lock.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from lasagna.compose.layer import LayerTensors
from lasagna.compose.pattern import TileTensors
from lasagna.compose.plan import plan_from_document, solid_tensors
from lasagna.compose.render import render
from lasagna.compose.renderer import Renderer
from lasagna.compose.surface import layer_occlusion, relieved_map
from lasagna.document import Document
from lasagna.document.condition import parse_direction, parse_surface_light
from lasagna.document.models import MAX_LIGHT_INTENSITY, MAX_RELIEF
from lasagna.errors import LasagnaError
from lasagna.io.render import BAND_ROWS, composite_codes, encode_composite, render_bytes, tensor_bytes
from lasagna.io.stack import Stack, group_mask_tensors
from lasagna.limits import FLOAT_BYTES, memory_budget_scope

SURFACE_MAPS = ("normal-map", "height-map", "occlusion-map")
"""The editor's downloads of a surface layer's maps (``/api/export/<map>?id=…``), as ``lasagna export`` writes them."""

THUMB_SIDE = 96
"""Long side of a layer thumbnail in the layers panel, in pixels."""
MAX_LEVEL = 6
"""Coarsest view: the canvas reduced 64×."""


@dataclass
class _Level:
    renderer: Renderer
    key: tuple[Any, ...]


def _reduce(t: torch.Tensor | None, size: tuple[int, int]) -> torch.Tensor | None:
    if t is None:
        return None
    if tuple(t.shape[-2:]) == size:
        return t
    return F.interpolate(t.unsqueeze(0).float(), size=size, mode="area")[0].to(t.dtype)


def _reduced_side(n: int, level: int) -> int:
    return max(1, math.ceil(n / 2**level))


class SessionViews:
    """Views at zoom levels, thumbnails and exports of ``EditSession``'s stack (module docstring)."""

    # Provided by ``EditSession`` (lasagna.serve.session).
    folder: Path
    stack: Stack
    budget: int
    _guard: Any
    _admit: Any
    levels: dict[int, _Level]
    reduced: dict[tuple[str, int], tuple[object, LayerTensors]]
    thumbs: dict[str, tuple[object, Any, bytes]]

    # ---- exports -------------------------------------------------------------------------------------

    def export(self, kind: str, layer_id: str | None = None, directx: bool = False) -> tuple[bytes, str, str]:
        """(bytes, file name, media type) of the current stack as ``ora``, ``psd`` or ``png`` (the composite), or
        of surface layer ``layer_id``'s ``normal-map`` (``directx``: +Y down), ``height-map`` or ``occlusion-map``
        on the canvas, as ``lasagna export --normal-map`` (``--directx``), ``--height-map`` and ``--occlusion-map``
        write them (`lasagna.export.png`)."""
        if kind not in ("ora", "psd", "png", *SURFACE_MAPS):
            raise LasagnaError(f"unknown export {kind!r}; expected ora, psd, png, {', '.join(SURFACE_MAPS)}", "export")
        if kind in SURFACE_MAPS and layer_id is None:
            raise LasagnaError(f"the {kind} export is a surface layer's; expected ?id=LAYER", "id")
        if kind not in SURFACE_MAPS and layer_id is not None:
            raise LasagnaError(f"the {kind} export is the stack's; expected no ?id= (a surface map takes one)", "id")
        if directx and kind != "normal-map":
            raise LasagnaError(f"directx is a normal map's convention, not a {kind}'s; expected normal-map", "directx")
        if kind in SURFACE_MAPS:
            return self._surface_map_export(kind, str(layer_id), directx)
        with self._guard():
            self._admit(self._render_bytes(encode_layers=kind != "png"), f"the {kind} export", f"export {kind}")
            stack = Stack(self.stack.document, self.folder, dict(self.stack.tensors), dict(self.stack.bit_depths))
        with memory_budget_scope(self.budget):
            return self._encode_export(stack, kind)

    def _surface_map_export(self, kind: str, layer_id: str, directx: bool) -> tuple[bytes, str, str]:
        from lasagna.export.png import height_map_png, normal_map_png, occlusion_map_png

        with self._guard():
            self._admit(self._render_bytes(encode_layers=False), f"the {kind} export", f"export {kind}")
            stack = Stack(self.stack.document, self.folder, dict(self.stack.tensors), dict(self.stack.bit_depths))
        with memory_budget_scope(self.budget):
            if kind == "normal-map":
                data = normal_map_png(stack, layer_id, directx=directx)
            elif kind == "height-map":
                data = height_map_png(stack, layer_id)[0]
            else:
                data = occlusion_map_png(stack, layer_id)
        suffix = "-directx" if directx else ""
        return data, f"{self.folder.name}-{layer_id}-{kind}{suffix}.png", "image/png"

    def _encode_export(self, stack: Stack, kind: str) -> tuple[bytes, str, str]:
        result = stack.render()
        name = self.folder.name
        if kind == "ora":
            from lasagna.export.ora import encode_ora

            return encode_ora(stack, composite=result), f"{name}.ora", "image/openraster"
        if kind == "psd":
            from lasagna.export.psd import encode_psd

            return encode_psd(stack, composite=result), f"{name}.psd", "image/vnd.adobe.photoshop"
        return encode_composite(result), f"{name}.png", "image/png"

    def _render_bytes(self, *, encode_layers: bool) -> int:
        """What a full-size render of the stack allocates (``render_stack``'s output canvas) and, with
        ``encode_layers`` (saves, ORA and PSD), a layer's stored codes while it is encoded: float64 values and
        codes of the largest layer, four times its float32 tensors."""
        need = render_bytes(self.stack.width, self.stack.height)
        if encode_layers:
            need += 4 * max((tensor_bytes(lt.tensors()) for lt in self.stack.tensors.values()), default=0)
        return need

    # ---- views ----------------------------------------------------------------------------------------

    def max_level(self) -> int:
        side = max(self.stack.width, self.stack.height)
        return max(0, min(MAX_LEVEL, int(math.floor(math.log2(side))) - 4)) if side > 16 else 0

    def _level_tensors(self, doc: Document, level: int) -> dict[str, LayerTensors]:
        """Every layer's tensors reduced by 2**level (cached by the source tensors' identity)."""
        out: dict[str, LayerTensors] = {}
        for _, layer in doc.walk():  # groups' children too
            t = self._layer_at(layer, level)
            if t is not None:
                out[layer.id] = t
        return out

    def _layer_at(self, layer, level: int) -> LayerTensors | None:
        """Layer ``layer``'s tensors reduced by 2**level (None for a layer without pixels): a solid's are
        zero-stride views of its size at that level, a group's hold its mask (``group_mask_tensors``)."""
        if layer.kind == "solid":
            lo, hi = tuple(layer.range)
            w, h = (
                (layer.size.width, layer.size.height)
                if layer.size is not None
                else (self.stack.width, self.stack.height)
            )
            key = (layer.id, level)
            stamp = (tuple(layer.color), w, h, lo, hi)
            hit = self.reduced.get(key)
            if hit is None or hit[0] != stamp:
                rw, rh = _reduced_side(w, level), _reduced_side(h, level)
                shape = type("Solid", (), {"color": layer.color, "size": None})()  # its size is the one given
                hit = (stamp, solid_tensors(shape, lo, hi, rw, rh, layer.id))
                self.reduced[key] = hit
            return hit[1]
        t = self.stack.tensors.get(layer.id)  # a group's tensors hold only its mask
        if t is None or level == 0:
            return t
        key = (layer.id, level)
        hit = self.reduced.get(key)
        if hit is None or hit[0] is not t:
            if layer.kind == "group":
                size = (_reduced_side(t.mask.shape[-2], level), _reduced_side(t.mask.shape[-1], level))
                hit = (t, group_mask_tensors(_reduce(t.mask, size)))
            elif layer.kind == "pattern":  # the tile and its rectangle's mask, each reduced on its own
                tile = (_reduced_side(t.color.shape[-2], level), _reduced_side(t.color.shape[-1], level))
                mask = (
                    None
                    if t.mask is None
                    else (_reduced_side(t.mask.shape[-2], level), _reduced_side(t.mask.shape[-1], level))
                )
                reduced = (
                    _reduce(t.color, tile),
                    _reduce(t.alpha, tile),
                    None if mask is None else _reduce(t.mask, mask),
                )
                hit = (t, TileTensors(*reduced))
            else:
                size = (_reduced_side(t.color.shape[-2], level), _reduced_side(t.color.shape[-1], level))
                reduced = (_reduce(t.color, size), _reduce(t.alpha, size), _reduce(t.mask, size))
                hit = (t, LayerTensors(*reduced, reduced_by=2**level))
            self.reduced[key] = hit
        return hit[1]

    def _reduction_bytes(self, layers, level: int) -> int:
        """Bytes ``_layer_at`` would allocate for ``layers`` at ``level`` (reductions not cached yet; a solid's
        and level 0's cost nothing)."""
        need = 0
        for layer in layers:
            t = self.stack.tensors.get(layer.id)
            if level == 0 or layer.kind == "solid" or t is None:
                continue
            hit = self.reduced.get((layer.id, level))
            if hit is not None and hit[0] is t:
                continue
            for x in t.tensors():
                if x is not None and x.stride(-1) != 0:  # a zero-stride view (a group's ones) is reduced to one
                    rows, cols = _reduced_side(x.shape[-2], level), _reduced_side(x.shape[-1], level)
                    need += x.shape[0] * rows * cols * FLOAT_BYTES
        return need

    def view(
        self,
        level: int = 0,
        *,
        opacity: dict[str, float] | None = None,
        solo: str | None = None,
        upto: str | None = None,
        light: dict[str, str] | None = None,
        source: dict[str, str] | None = None,
        relief: dict[str, float] | None = None,
        ambient: dict[str, float] | None = None,
        color: dict[str, tuple[float, float, float]] | None = None,
        intensity: dict[str, float] | None = None,
        gloss: dict[str, float] | None = None,
        shadows: dict[str, float] | None = None,
        occlusion: dict[str, float] | None = None,
        shadow_depth: dict[str, float] | None = None,
    ) -> tuple[bytes, int, int]:
        """The composite at reduction ``level`` as RGBA8 bytes (row-major), with transient overrides that are
        not changes (``opacity`` while a slider is dragged; ``light`` of a surface layer while its light is
        dragged: the stored map drawn under it, as ``set_light`` would; ``source`` likewise, a relight surface
        layer's source light while it is dragged; ``relief``, ``ambient``, ``color``, ``intensity``, ``gloss``,
        ``shadows``, ``occlusion`` and ``shadow_depth`` a surface layer's relief gain, ambient term, light colour,
        intensity, gloss, shadows, occlusion and shadow depth while their controls are moved;
        ``solo`` one
        layer alone; ``upto`` a layer: the stack up to and including it, the "before" of a before/after split). Layers
        are named at any depth: a soloed layer inside a group shows with the groups that hold it."""
        self._check_level(level)
        with self._guard():
            doc = self.stack.document
            named = [
                *(opacity or {}),
                *(light or {}),
                *(source or {}),
                *(relief or {}),
                *(ambient or {}),
                *(color or {}),
                *(intensity or {}),
                *(gloss or {}),
                *(shadows or {}),
                *(occlusion or {}),
                *(shadow_depth or {}),
                *([solo] if solo else []),
                *([upto] if upto else []),
            ]
            for id in named:
                doc.layer(id)  # DocumentError naming the ids
            for id, v in (opacity or {}).items():
                if not (isinstance(v, (int, float)) and 0.0 <= float(v) <= 1.0):
                    raise LasagnaError(f"expected an opacity in [0, 1], got {v!r}", f"opacity.{id}")
            for id, text in (light or {}).items():
                kind = doc.layer(id).kind
                if kind != "surface":
                    raise LasagnaError(f"layer {id!r} is a {kind} layer; expected a surface layer", "light")
                parse_surface_light(text)  # a ConditionError naming what a light is
            for id, text in (source or {}).items():
                if doc.layer(id).kind != "surface" or doc.layer(id).source_light is None:
                    raise LasagnaError(f"layer {id!r} has no source light; expected a relight surface layer", "source")
                parse_direction(text)
            # Each slider's value: a surface layer's, finite, within its field's range (the document model's).
            sliders = (
                ("relief", relief, True, MAX_RELIEF, "a relief gain"),
                ("intensity", intensity, True, MAX_LIGHT_INTENSITY, "a light intensity"),
                ("gloss", gloss, False, 1.0, "a gloss"),
                ("shadows", shadows, False, 1.0, "a shadows strength"),
                ("occlusion", occlusion, False, 1.0, "an occlusion strength"),
                ("shadow_depth", shadow_depth, True, MAX_RELIEF, "a shadow depth"),
            )
            for name, given, open_low, top, what in sliders:
                for id, v in (given or {}).items():
                    if doc.layer(id).kind != "surface":
                        raise LasagnaError(
                            f"layer {id!r} is a {doc.layer(id).kind} layer; expected a surface layer", name
                        )
                    number = isinstance(v, (int, float)) and math.isfinite(v)
                    if not (number and (0.0 < float(v) if open_low else 0.0 <= float(v)) and float(v) <= top):
                        span = f"{'(' if open_low else '['}0, {top:g}]"
                        raise LasagnaError(f"expected {what} in {span}, got {v!r}", f"{name}.{id}")
            for id, v in (ambient or {}).items():
                layer = doc.layer(id)
                if layer.kind != "surface":
                    raise LasagnaError(f"layer {id!r} is a {layer.kind} layer; expected a surface layer", "ambient")
                low = 0.0 if layer.source_light is None else math.nextafter(0.0, 1.0)  # a ratio needs a > 0
                if not (isinstance(v, (int, float)) and math.isfinite(v) and low <= float(v) < 1.0):
                    bound = "[0, 1)" if layer.source_light is None else "(0, 1) (a relight ratio)"
                    raise LasagnaError(f"expected an ambient term in {bound}, got {v!r}", f"ambient.{id}")
            for id in color or {}:
                if doc.layer(id).kind != "surface":
                    raise LasagnaError(
                        f"layer {id!r} is a {doc.layer(id).kind} layer; expected a surface layer", "color"
                    )
            layers = _overridden(
                doc,
                opacity or {},
                solo,
                upto,
                light or {},
                source or {},
                relief or {},
                ambient or {},
                color or {},
                intensity or {},
                gloss or {},
                shadows or {},
                occlusion or {},
                shadow_depth or {},
            )
            w, h = _reduced_side(self.stack.width, level), _reduced_side(self.stack.height, level)
            # The layers reduced to this level, the canvas and the renderer's snapshot below the top layer
            # (``lasagna.compose.renderer``), and the RGBA8 bytes returned.
            need = self._reduction_bytes([layer for _, layer in doc.walk()], level) + 2 * render_bytes(w, h) + 4 * w * h
            self._admit(need, f"the {w}x{h} view (level {level})", "view")
            tensors = self._level_tensors(doc, level)
            f = 2**level
            specs = plan_from_document(_Scaled(doc, layers, w, h, f), tensors, cull=True, dtype=torch.float32).layers
            alpha = None
            if doc.canvas.background is None:  # a transparent document: its alpha shows the page's checkerboard
                # (the prefix-cache Renderer composites onto an opaque canvas only; this view renders whole)
                result = render(specs, canvas=(h, w), background=None, blend_space=doc.blend_space, clamp=doc.clamp)
                image, alpha = result.image, result.alpha
            else:
                key = (w, h, tuple(doc.canvas.background), doc.blend_space, doc.clamp)
                lv = self.levels.get(level)
                if lv is None or lv.key != key:
                    lv = _Level(Renderer((h, w), tuple(doc.canvas.background), doc.blend_space, doc.clamp), key)
                    self.levels[level] = lv
                image = lv.renderer.render(specs).image
            rgba = np.empty((h, w, 4), np.uint8)
            rgba[..., 3] = 255
            for y in range(0, h, BAND_ROWS):  # a band at a time: no canvas-sized float64 copy
                planes = image[:, y : y + BAND_ROWS]
                if alpha is not None:
                    planes = torch.cat([planes, alpha[:, y : y + BAND_ROWS]])
                codes = composite_codes(planes) if level == 0 else (planes.clamp(0, 1) * 255.0).round().to(torch.uint8)
                rgba[y : y + BAND_ROWS, :, : codes.shape[0]] = codes.permute(1, 2, 0).numpy()
            return rgba.tobytes(), w, h

    def normal_map(self, id: str, level: int = 0) -> tuple[bytes, int, int]:
        """Surface layer ``id``'s normal map at reduction ``level`` as RGBA8 bytes of the view's size (the map's RGB
        codes where the layer lies, at its offset; transparent elsewhere), its relief times the layer's ``relief``
        as the exports write it (`compose.surface.relieved_map`): the surface the layer lights, not how it is lit."""
        return self._surface_map(id, level, "normals", "normal map", _relieved_codes)

    def occlusion_map(self, id: str, level: int = 0) -> tuple[bytes, int, int]:
        """Surface layer ``id``'s ambient occlusion at reduction ``level`` as RGBA8 bytes of the view's size: grey,
        the share of the sky each pixel of its heights sees (`compose.surface.layer_occlusion`, its relief and shadow
        depth applied; white open), where the layer lies; transparent elsewhere — what its ``occlusion`` darkens."""
        return self._surface_map(id, level, "occlusion", "occlusion map", _occlusion_codes)

    def _surface_map(self, id: str, level: int, what: str, label: str, codes_of) -> tuple[bytes, int, int]:
        """A surface layer's map ``codes_of(layer, its tensors at the level)`` (3, h, w) in [0, 1] placed at its
        offset on the view of ``level``, RGBA8 (transparent where the layer is not); refusals name ``what``."""
        self._check_level(level)
        with self._guard():
            layer = self.stack.document.layer(id)
            if layer.kind != "surface":
                raise LasagnaError(f"layer {id!r} is a {layer.kind} layer; expected a surface layer", what)
            w, h = _reduced_side(self.stack.width, level), _reduced_side(self.stack.height, level)
            self._admit(self._reduction_bytes([layer], level) + 4 * w * h, f"the {label} of {id}", what)
            t = self._layer_at(layer, level)
            full = codes_of(layer, t)
        rgba = np.zeros((h, w, 4), np.uint8)
        f = 2**level
        x0, y0 = layer.offset.x // f, layer.offset.y // f  # as the view places it (_ScaledLayer)
        mh, mw = t.color.shape[-2:]
        top, left = max(0, y0), max(0, x0)
        bottom, right = min(h, y0 + mh), min(w, x0 + mw)
        if bottom > top and right > left:
            part = full[:, top - y0 : bottom - y0, left - x0 : right - x0]
            rgba[top:bottom, left:right, :3] = (part.clamp(0, 1) * 255.0).round().to(torch.uint8).permute(1, 2, 0)
            rgba[top:bottom, left:right, 3] = 255
        return rgba.tobytes(), w, h

    def _check_level(self, level: Any) -> None:
        if isinstance(level, bool) or not isinstance(level, int) or not 0 <= level <= self.max_level():
            raise LasagnaError(f"expected a level in [0, {self.max_level()}], got {level!r}", "level")

    def thumbnail(self, id: str) -> bytes:
        """A small PNG of layer ``id``'s stored values (RGB codes v and alpha), as the layers panel shows it,
        made from the layer reduced to about twice the thumbnail's side (a reduced view level's tensors)."""
        from PIL import Image

        with self._guard():
            layer = self.stack.document.layer(id)
            side = max(self.stack.width, self.stack.height)
            level = max(0, int(math.log2(max(1, side // (2 * THUMB_SIDE)))))
            need = self._reduction_bytes([layer], level) + 8 * 4 * THUMB_SIDE * THUMB_SIDE
            self._admit(need, f"the thumbnail of {id}", f"layer {id!r}")
            t = self._layer_at(layer, level)
            rng = tuple(layer.range) if layer.kind != "group" else (0.0, 1.0)  # a group's tensors: its mask
        if t is None:  # a learned layer not rendered yet
            rgba = np.zeros((8, 8, 4), np.uint8)
        else:
            hit = self.thumbs.get(id)
            if hit is not None and hit[0] is t and hit[1] == rng:
                return hit[2]
            lo, hi = rng
            h, w = t.color.shape[-2:]
            s = min(1.0, THUMB_SIDE / max(h, w))
            size = (max(1, round(h * s)), max(1, round(w * s)))
            # Reduced first, then mapped to codes: the map is linear, so the area average commutes with it.
            color = ((_reduce(t.color, size) - lo) / (hi - lo)).clamp(0, 1).expand(3, *size)
            alpha = _reduce(t.alpha, size) if t.alpha is not None else torch.ones(1, *size)
            rgba = (torch.cat([color, alpha.clamp(0, 1)]) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
        buf = io.BytesIO()
        Image.fromarray(np.ascontiguousarray(rgba), "RGBA").save(buf, "PNG")
        data = buf.getvalue()
        if t is not None:
            self.thumbs[id] = (t, rng, data)
        return data


def _relieved_codes(layer, tensors) -> torch.Tensor:
    """A surface layer's stored map with its relief applied (3, h, w): what the normal-map view shows."""
    return relieved_map(tensors.color, layer.relief)


def _occlusion_codes(layer, tensors) -> torch.Tensor:
    """A surface layer's share of the sky as grey (3, h, w): what the occlusion view shows."""
    return layer_occlusion(tensors, layer)[0].expand(3, -1, -1)


def _overridden(
    doc: Document,
    opacity: dict[str, float],
    solo: str | None,
    upto: str | None,
    light: dict[str, str],
    source: dict[str, str] | None = None,
    relief: dict[str, float] | None = None,
    ambient: dict[str, float] | None = None,
    color: dict[str, tuple[float, float, float]] | None = None,
    intensity: dict[str, float] | None = None,
    gloss: dict[str, float] | None = None,
    shadows: dict[str, float] | None = None,
    occlusion: dict[str, float] | None = None,
    shadow_depth: dict[str, float] | None = None,
) -> list:
    """``doc``'s layer tree with a view's transient overrides (``EditSession.view``), layers named at any depth:
    ``opacity`` per layer; ``light`` (and ``source``, a relight's source light, ``relief``, ``ambient``, ``color``,
    ``intensity``, ``gloss``, ``shadows``, ``occlusion``, ``shadow_depth``) per surface layer; ``solo``: that layer
    (with what it holds) alone, the groups holding it shown; ``upto``: every layer after it in the tree's order (depth
    first, a group before its layers) hidden, except its own layers."""
    order = [layer.id for _, layer in doc.walk()]
    inside: dict[str, set[str]] = {}  # group id → ids of every layer it holds, at any depth
    holders: dict[str, list[str]] = {}  # layer id → ids of the groups holding it, outermost first

    def index(layers, path: list[str]) -> None:
        for layer in layers:
            holders[layer.id] = list(path)
            for g in path:
                inside.setdefault(g, set()).add(layer.id)
            if layer.kind == "group":
                inside.setdefault(layer.id, set())
                index(layer.layers, [*path, layer.id])

    index(doc.layers, [])
    shown: set[str] | None = None
    if solo is not None:
        shown = {solo, *holders[solo], *inside.get(solo, ())}
    hidden: set[str] = set()
    if upto is not None:
        after = order[order.index(upto) + 1 :]
        hidden = set(after) - inside.get(upto, set())

    numbers = (
        ("relief", relief),
        ("ambient", ambient),
        ("light_intensity", intensity),
        ("gloss", gloss),
        ("shadows", shadows),
        ("occlusion", occlusion),
        ("shadow_depth", shadow_depth),
    )

    def visit(layers) -> list:
        out = []
        for layer in layers:
            changes: dict[str, Any] = {}
            if layer.id in opacity:
                changes["opacity"] = float(opacity[layer.id])
            if layer.id in light:
                changes["light"] = light[layer.id]
            if source and layer.id in source:
                changes["source_light"] = source[layer.id]
            for field, given in numbers:  # a surface layer's sliders: their fields, as set_light would set them
                if given and layer.id in given:
                    changes[field] = float(given[layer.id])
            if color and layer.id in color:
                changes["light_color"] = tuple(color[layer.id])
            if shown is not None and layer.id == solo:
                changes["visible"] = True
            elif shown is not None and layer.id not in shown:
                changes["visible"] = False
            if layer.id in hidden:
                changes["visible"] = False
            if layer.kind == "group":
                changes["layers"] = tuple(visit(layer.layers))
            out.append(layer.model_copy(update=changes) if changes else layer)
        return out

    return visit(doc.layers)


class _Scaled:
    """A document seen at a reduced view level: the canvas, offsets and solid sizes divided by ``f``, and the
    layer list with transient overrides (read through attributes only, as ``plan_from_document`` does)."""

    def __init__(self, doc: Document, layers, w: int, h: int, f: int):
        self.canvas = type("Canvas", (), {"width": w, "height": h, "background": doc.canvas.background})()
        self.blend_space = doc.blend_space
        self.clamp = doc.clamp
        self.layers = [_ScaledLayer(layer, f) for layer in layers] if f > 1 else layers


class _ScaledLayer:
    """A layer whose offset is divided by ``f`` (its other attributes are the layer's; a group's children
    are scaled too, and a gradient's rectangle)."""

    def __init__(self, layer, f: int):
        self._layer = layer
        self.offset = type("Offset", (), {"x": layer.offset.x // f, "y": layer.offset.y // f})()
        if layer.kind == "group":
            self.layers = [_ScaledLayer(child, f) for child in layer.layers]
        if layer.kind == "pattern":  # its phase in reduced pixels (its tile is reduced with the view)
            self.pattern = layer.pattern.model_copy(update={"phase": tuple(v // f for v in layer.pattern.phase)})
        if layer.kind in ("gradient", "pattern") and layer.size is not None:  # its rectangle, its reduced mask's size
            level = f.bit_length() - 1
            w, h = _reduced_side(layer.size.width, level), _reduced_side(layer.size.height, level)
            self.size = type("Size", (), {"width": w, "height": h})()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._layer, name)


__all__ = ["MAX_LEVEL", "THUMB_SIDE", "SessionViews"]
