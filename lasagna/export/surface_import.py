"""Surface layers read back from OpenRaster and PSD: a rendered multiplier over its hidden normal map made a surface.

Our writers (`lasagna.export.rasters`) put a surface layer in a file as two layers: its rendered multiplier
(multiply, what readers flatten) and, directly below it, its normal map as a hidden normal layer named
"<name> (normal map)". Krita, GIMP and Photoshop keep both through a save. Read back, the pair would be paint —
the stack could no longer be re-lit. So an import looks for that pair and asks whether the multiplier is still the
map's rendering: under one light fitted to the pixels (`lasagna.export.light_fit`: a shading or a relight ratio,
in a coloured light too, checked at every pixel), or under the render fields the map's name carries.

What the pixels cannot tell, the map's name does. A layer whose multiplier is not one light's Lambert rendering —
a point light, several lights, a highlight, cast shadows, ambient occlusion, a coloured relight ratio — is written
with its render fields after the suffix, as compact JSON (``map_name``): "Shape (normal map) {"light":"x=0.3,…",
"shadows":0.7}". Paint programs keep a layer's name through a save, so the import reads the fields there — and
still renders them from the file's map and keeps them only if they match the file's multiplier within
``MATCH_TOLERANCE`` at every pixel: the name proposes, the pixels confirm.

Where the canvas cuts a surface layer, the file holds its multiplier's part on the canvas and its normal map whole
(`lasagna.export.rasters`): the multiplier is checked against its part of the map's render, and the layer comes
back whole, at the map's place. Then the pair becomes one surface layer with the multiplier's id, name, opacity,
visibility and clip, and the hidden map is dropped. Otherwise — a brush stroke over the multiplier, or, in a file
whose map's name carries no fields, a coloured relight ratio, cast shadows, a highlight, a point light, several
lights — the two stay as they were read, with one warning line that says why: nothing is guessed."""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import torch

from lasagna.export.light_fit import MATCH_TOLERANCE, fit_light

NORMAL_MAP_SUFFIX = " (normal map)"
"""What our writers append to a surface layer's name for its hidden normal-map layer (`lasagna.export.rasters`)."""
DODGE_SUFFIX = " (colour dodge: values above 1)"
CLAMP_SUFFIX = " (clamp to 1)"
"""The names of the helper layers a PSD holds a multiplier above 1 in (`lasagna.export.rasters`, `.psd`)."""
DODGE_FLOOR = 1.0 / 65535.0
"""1 − d is read no smaller than one 16-bit step (a full dodge code is an infinite multiplier)."""
SHADOW_EDGE = 0.5 / 255.0
"""A pixel is in a cast shadow where it renders more than this below the same light unshadowed."""
SHADOW_REACH = 2
"""On a shadow and within this many traced pixels of it (`lasagna.compose.shadow.SHADOW_MAX_SIDE`: a traced pixel is
one of the map's up to 512 on a side, four at 2048) the named fields' render may take any value of that
neighbourhood that a shadow could give the pixel itself — between (1 − s)·u and u, u its unshadowed render, s the
layer's ``shadows`` (the shadow factor 1 − s·(1 − V) scales each light's direct term, never the ambient). The file's
8-bit map integrates to heights a little off the stored map's, and a grazing light turns a small height error into a
longer shift of a shadow's edge: measured, one traced pixel for directional lights at 60° from the view axis over a
deep relief, two for a point light a third of the map's side above it (`tests/export/test_surface_import.py`)."""
CUT_NAME = 255
"""GIMP saves a PSD layer's name cut to this many characters (the Pascal string's limit; Krita and Photoshop's
Unicode name keep more): fields that need a longer name (many extra lights) do not survive GIMP."""
NAMED_FIELDS = (
    "light",
    "source_light",
    "ambient",
    "light_color",
    "light_intensity",
    "extra_lights",
    "gloss",
    "shininess",
    "shadows",
    "shadow_depth",
    "occlusion",
)
"""The render fields a hidden map's name may carry (``map_name``); the relief is in the map itself."""


def map_name(layer) -> str:
    """The hidden normal map's name for surface ``layer`` (`lasagna.export.rasters`): "<name> (normal map)", and,
    when the fit could not read its multiplier back (a point light, several lights, a highlight, cast shadows,
    ambient occlusion, a coloured relight ratio), its non-default render fields as compact JSON after a space."""
    from lasagna.document.condition import parse_point

    plain = f"{layer.name}{NORMAL_MAP_SUFFIX}"
    fitted = (
        parse_point(layer.light) is None
        and not layer.extra_lights
        and layer.gloss == 0.0
        and layer.shadows == 0.0
        and layer.occlusion == 0.0
        and (layer.source_light is None or tuple(layer.light_color) == (1.0, 1.0, 1.0))
    )
    if fitted:
        return plain
    fields = layer.model_dump(mode="json", include=set(NAMED_FIELDS), exclude_defaults=True)
    return f"{plain} {json.dumps({k: fields[k] for k in NAMED_FIELDS if k in fields}, separators=(',', ':'))}"


def _pairs(layers: list) -> Iterator[tuple[Any, Any, list]]:
    """(multiplier, hidden map, helpers) at any depth: a multiply pixels layer directly above a hidden normal pixels
    layer named after it, with the helpers a PSD holds a multiplier above 1 in directly above it — its colour-dodge
    half ``DODGE_SUFFIX`` and the white darken layer ``CLAMP_SUFFIX`` (`lasagna.export.psd`); an OpenRaster import
    has merged the dodge half already (``lasagna.export.ora_import``)."""
    for i, (below, above) in enumerate(zip(layers, layers[1:])):
        if (
            below.kind == "pixels"
            and above.kind == "pixels"
            and not below.visible
            and below.blend == "normal"
            and above.blend == "multiply"
            and below.name.startswith(above.name + NORMAL_MAP_SUFFIX)
            and below.name[len(above.name + NORMAL_MAP_SUFFIX) :][:2] in ("", " {")
        ):
            helpers = []
            for suffix, blend in ((DODGE_SUFFIX, "color-dodge"), (CLAMP_SUFFIX, "darken")):
                k = i + 2 + len(helpers)
                if k < len(layers) and layers[k].name == above.name + suffix and layers[k].blend == blend:
                    helpers.append(layers[k])
            yield above, below, helpers
    for layer in layers:
        if layer.kind == "group":
            yield from _pairs(list(layer.layers))


def restore_surfaces(stack, warn: Callable[[str], None], where: str):
    """``stack`` (just imported) with each multiplier-over-normal-map pair made one surface layer when the
    multiplier is its map's rendering under a light fitted to it or the fields the map's name holds (module
    docstring); the others kept, one ``warn`` line each. Returns the stack."""
    for multiplier, hidden, helpers in list(_pairs(list(stack.document.layers))):
        reason, surface = _surface_of(stack, multiplier, hidden, helpers)
        if surface is None:
            warn(
                f"{where}: layer {multiplier.name!r} over its hidden normal map stays pixels: {reason}; expected the "
                "map's rendering under one light, or under the fields its name holds, that `lasagna export` writes"
            )
            continue
        _swap(stack, multiplier, [hidden, *helpers], surface)
    return stack


def _surface_of(stack, multiplier, hidden, helpers: list) -> tuple[str, dict | None]:
    """(why not, None) or ("", the surface layer's light fields) for one pair (and its PSD helpers)."""
    m_t, n_t = stack.tensors[multiplier.id], stack.tensors[hidden.id]
    (mh, mw), (hh, hw) = m_t.color.shape[-2:], n_t.color.shape[-2:]
    left, top = multiplier.offset.x - hidden.offset.x, multiplier.offset.y - hidden.offset.y
    if left < 0 or top < 0 or left + mw > hw or top + mh > hh:
        return "its map does not cover it (they differ in size or place)", None
    window = (slice(None), slice(top, top + mh), slice(left, left + mw))  # the multiplier's part of the map
    if n_t.color.shape[0] != 3:
        return "the map is not RGB", None
    if any(t is not None and not bool((t == 1).all()) for t in (m_t.alpha, m_t.mask, n_t.alpha, n_t.mask)):
        return "it or the map has transparent pixels or a mask", None
    m = m_t.color.double().numpy()
    dodge = next((h for h in helpers if h.blend == "color-dodge"), None)
    if dodge is not None:  # y = m/(1 − d): the pair `lasagna.export.rasters` splits a multiplier above 1 into
        d_t = stack.tensors[dodge.id]
        if d_t.color.shape != m_t.color.shape or (dodge.offset.x, dodge.offset.y) != (
            multiplier.offset.x,
            multiplier.offset.y,
        ):
            return "its colour-dodge half differs in size or place", None
        m = m / np.maximum(1.0 - d_t.color.double().numpy(), DODGE_FLOOR)
    clamp = next((h for h in helpers if h.blend == "darken"), None)
    if clamp is not None and not bool((stack.tensors[clamp.id].color == 1).all()):
        return "its white clamp layer was painted on", None  # dropped only while it is the identity it was written as
    note = hidden.name[len(multiplier.name + NORMAL_MAP_SUFFIX) :].strip()
    if note:
        return _named(n_t.color, window, hidden.name, note, m, coarse=stack.bit_depths.get(hidden.id, 8) < 16)
    return fit_light(n_t.color[window], m)


def _named(codes, window: tuple, name: str, note: str, m: np.ndarray, coarse: bool) -> tuple[str, dict | None]:
    """(why not, None) or ("", the layer's render fields) for a map whose name carries them (``map_name``): kept
    when the layer they make, rendered from the file's whole map by the compositor's own path (its shadows and
    point lights are the whole map's), matches the file's multiplier ``m`` (C, h, w) on its part of the map
    (``window``) within ``MATCH_TOLERANCE`` at every pixel. ``coarse``: the file's map is 8-bit (its line then
    names the cure for shadows and occlusion over a steep relief)."""
    from pydantic import ValidationError

    from lasagna.compose.layer import LayerTensors
    from lasagna.compose.surface import layer_surface_tensors
    from lasagna.document import SurfaceLayer
    from lasagna.errors import LasagnaError

    try:
        fields = json.loads(note)
    except (ValueError, RecursionError):  # a hostile name may nest deeper than the parser recurses
        fields = None
    if not isinstance(fields, dict) or "light" not in fields or not set(fields) <= set(NAMED_FIELDS):
        if fields is None and len(name) == CUT_NAME:
            return f"its map's name was cut at {CUT_NAME} characters (GIMP's limit) inside its light fields", None
        return f"its map's name ends in {note[:60]!r}, not the light fields `lasagna export` writes", None
    try:
        layer = SurfaceLayer.model_validate({"id": "named", "source": "named.png", "blend": "multiply", **fields})
        rendered = layer_surface_tensors(LayerTensors(codes, None, None), layer)[0].color
    except (ValidationError, LasagnaError) as e:
        return f"its map's name holds light fields no surface layer takes ({str(e).splitlines()[0]})", None
    r = rendered.double().numpy()
    lo = hi = r
    if layer.shadows > 0.0:  # a shadow may move a traced pixel: on and beside it, a value of its neighbourhood
        from lasagna.compose.shadow import SHADOW_MAX_SIDE

        unshadowed = layer_surface_tensors(LayerTensors(codes, None, None), layer.model_copy(update={"shadows": 0.0}))
        u = unshadowed[0].color.double().numpy()
        reach = SHADOW_REACH * math.ceil(max(r.shape[-2:]) / SHADOW_MAX_SIDE)  # traced pixels, in the map's
        near = _pool(torch.from_numpy(np.abs(u - r).max(0) > SHADOW_EDGE).double()[None, None], reach)
        near = near.numpy()[0] > 0
        # ... which a shadow could give the pixel itself: between (1 − s)·u (every light hidden) and u (none hidden)
        lowest = -_pool(-torch.from_numpy(r)[None], reach).numpy()[0]
        lo = np.where(near, np.maximum(lowest, (1.0 - layer.shadows) * u), r)
        hi = np.where(near, np.minimum(_pool(torch.from_numpy(r)[None], reach).numpy()[0], u), r)
    lo, hi = lo[window], hi[window]  # the whole map rendered (its shadows), compared where the multiplier is
    err = float((np.maximum(np.maximum(lo - m, m - hi), 0.0) / np.maximum(1.0, m) ** 2).max())
    if err > MATCH_TOLERANCE:
        traced = coarse and (layer.shadows > 0.0 or layer.occlusion > 0.0)
        why = (
            "paint over it, or its shadows and occlusion traced over the file's 8-bit normal map, whose rounding a "
            "steep relief's heights magnify (a PSD written with `lasagna export --depth 16` keeps them)"
            if traced
            else "paint over it"
        )
        return f"its render under the light its map's name gives is {err * 255:.1f} codes off ({why})", None
    return "", layer.model_dump(mode="json", include=set(NAMED_FIELDS))


def _pool(x: torch.Tensor, reach: int) -> torch.Tensor:
    """The maximum of (B, C, h, w) ``x`` over each pixel's (2·reach + 1)² neighbourhood, edges replicated: a running
    maximum down the columns, then along the rows (separable: 2k comparisons a pixel, not k²)."""
    import torch.nn.functional as F

    k = 2 * reach + 1
    x = F.max_pool2d(F.pad(x, (0, 0, reach, reach), mode="replicate"), (k, 1), stride=1)
    return F.max_pool2d(F.pad(x, (reach, reach, 0, 0), mode="replicate"), (1, k), stride=1)


def _swap(stack, multiplier, gone: list, fields: dict) -> None:
    """The multiplier replaced in ``stack`` by one surface layer of the map's normals (``gone[0]``, the hidden map)
    at the map's place (where the canvas cut the multiplier, the whole layer again) with the render ``fields`` (the
    layer's own names and values); the map and the helpers removed."""
    from lasagna.compose.layer import LayerTensors
    from lasagna.document import SurfaceLayer
    from lasagna.io.stack import stored_map

    layer = {
        "id": multiplier.id,
        "kind": "surface",
        "name": multiplier.name,
        "blend": "multiply",
        "opacity": multiplier.opacity,
        "visible": multiplier.visible,
        "offset": {"x": gone[0].offset.x, "y": gone[0].offset.y},  # the whole map's: the layer as it was
        "clip": multiplier.clip,
        "source": f"layers/{multiplier.id}.png",
        **fields,
    }
    SurfaceLayer.model_validate(layer)
    codes = stored_map(stack.tensors[gone[0].id].color)
    document = stack.document.swapped_layer(multiplier.id, layer)
    for other in gone:
        document = document.without_layer(other.id)
        stack.tensors.pop(other.id)
        stack.bit_depths.pop(other.id, None)
    stack.document = document
    stack.tensors[multiplier.id] = LayerTensors(codes, None, None)
    stack.bit_depths[multiplier.id] = 16


__all__ = ["MATCH_TOLERANCE", "NORMAL_MAP_SUFFIX", "map_name", "restore_surfaces"]
