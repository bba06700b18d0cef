"""Surface layers read back from OpenRaster and PSD: a rendered multiplier over its hidden normal map made a surface.

Our writers (`lasagna.export.rasters`) put a surface layer in a file as two layers: its rendered multiplier
(multiply, what readers flatten) and, directly below it, its normal map as a hidden normal layer named
"<name> (normal map)". Krita, GIMP and Photoshop keep both through a save. Read back, the pair would be paint —
the stack could no longer be re-lit. So an import looks for that pair and asks whether the multiplier is still one
light's rendering of the map, by fitting the light to the pixels (nothing is read from anywhere but the layers):

* shading, M = a + (1 − a)·k·max(0, n·l): linear in (a, w = (1 − a)·k·l) over the lit pixels (n·w > 0), solved by
  least squares in float64 and the lit set updated until it stops changing (``FIT_ROUNDS``);
* a relight ratio, M = S(l)/S(l_s) with S = a + (1 − a)·max(0, n·l): where both lights light a pixel,
  a(M − 1) + M·n·u − n·v = 0 with u = (1 − a)·l_s, v = (1 − a)·l, homogeneous in (a, u, v) — the smallest right
  singular vector, scaled so |u| = 1 − a — with the lit sets updated likewise.

A fit is kept only if the layer it makes renders the multiplier back (`lasagna.compose.surface.surface_tensors`,
the compositor's own path) within ``MATCH_TOLERANCE`` at every pixel; a whole-degree direction, a named light, an
ambient of 0.25 and an intensity of 1 are preferred when they render as well. Then the pair becomes one surface
layer with the multiplier's id, name, opacity, visibility, offset and clip, lit by the fitted light, and the hidden
map is dropped. A coloured light's shading (three channels) is fitted per channel and read as one light of a colour
when the three fits agree on it (``COLOUR_AGREE_DEG``). Otherwise — a brush stroke over the multiplier, or, in a
file whose map's name carries no fields (below), a coloured relight ratio, cast shadows, a highlight, a point light,
several lights — the two stay as they were read, with one warning line that says why: nothing is guessed.

What the pixels cannot tell, the map's name does. A layer whose multiplier is not one light's Lambert rendering —
a point light, several lights, a highlight, cast shadows, ambient occlusion, a coloured relight ratio — is written
with its render fields after the suffix, as compact JSON (``map_name``): "Shape (normal map) {"light":"x=0.3,…",
"shadows":0.7}". Paint programs keep a layer's name through a save, so the import reads the fields there — and
still renders them from the file's map and keeps them only if they match the file's multiplier within
``MATCH_TOLERANCE`` at every pixel: the name proposes, the pixels confirm.

Where the canvas cuts a surface layer, the file holds its multiplier's part on the canvas and its normal map whole
(`lasagna.export.rasters`): the multiplier is checked against its part of the map's render, and the layer comes
back whole, at the map's place.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import torch

NORMAL_MAP_SUFFIX = " (normal map)"
"""What our writers append to a surface layer's name for its hidden normal-map layer (`lasagna.export.rasters`)."""
DODGE_SUFFIX = " (colour dodge: values above 1)"
CLAMP_SUFFIX = " (clamp to 1)"
"""The names of the helper layers a PSD holds a multiplier above 1 in (`lasagna.export.rasters`, `.psd`)."""
DODGE_FLOOR = 1.0 / 65535.0
"""1 − d is read no smaller than one 16-bit step (a full dodge code is an infinite multiplier)."""
MATCH_TOLERANCE = 3.0 / 255.0
"""Largest difference at any pixel between the file's multiplier y and the fitted layer's render, over max(1, y)²:
three 8-bit codes — an 8-bit multiplier's rounding (half a code) and an 8-bit normal map's (up to about two codes of
shading where the map is steep), as a paint program that re-saves the file at 8 bits leaves them; above 1 the
multiply and colour-dodge pair that holds y, y = m/(1 − d), rounds in steps that grow as y². A stroke that changes
fewer codes than this is not seen."""
FIT_PIXELS = 65536
"""The fit reads about this many pixels of a larger layer (a regular subsample); the check reads all."""
FIT_ROUNDS = 8
"""Rounds of the lit set's update; the fit stops earlier when the set no longer changes."""
LIT_EPS = 1e-6
"""n·w above this counts as lit (a pixel on the terminator takes the ambient either way)."""
FACING_Z = (0.97, 0.9, 0.8)
"""The ratio fit's first round reads only normals this close to the view axis (within 14°, 26° or 37°: each a
start), which both lights light unless one grazes — the lit sets are not known before a first fit."""
MIN_FIT_PIXELS = 8
COLOUR_AGREE_DEG = 0.5
"""A coloured light's three channel fits must find one light within this many degrees of their mean."""
IDENTIFIABLE = 1e-4
"""A fit is made only when its system has one solution: the least singular value of the shading fit's design (the
second least of the ratio's, whose least is the solution's) above this share of the largest; a flat map, or a few
pixels, says nothing of the light, and a light that happens to render them is not read into the file."""
SNAP_SLACK = 1.0 / 255.0
"""A rounder light (whole degrees, a named light), ambient or intensity is kept when its largest error is no more
than this above the exact fit's."""
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
        return _named(n_t.color, window, hidden.name, note, m)
    coloured = m.shape[0] == 3 and not (np.abs(m - m[:1]).max() <= MATCH_TOLERANCE)
    m = m if coloured else m.mean(0, keepdims=True)  # (C, h, w): three channels for a coloured light, else one
    from lasagna.compose.surface import decode_normal_map

    # The fit and the choice among rounder lights on a regular subsample (Lambert is per pixel, so the render of
    # a strided map is the strided render); the chosen layer is checked on every pixel.
    step = max(1, math.ceil(math.sqrt(m[0].size / FIT_PIXELS)))
    part = n_t.color[window]  # one light's Lambert is per pixel: the multiplier's part of the map renders it
    codes = part[:, ::step, ::step].contiguous()
    n = decode_normal_map(codes[None].double())[0].numpy()
    few = m[:, ::step, ::step]
    scored = []
    fits = [_fit_coloured(n, few)] if coloured else [_fit_shading(n, few[0]), _fit_ratio(n, few[0])]
    for fit in fits:
        for candidate in [] if fit is None else _rounder(fit):
            err = _error(codes, candidate, few)
            if err is not None:
                scored.append((err, candidate))
    if not scored:
        return "no light fits (paint over it, cast shadows, a highlight, a point light or several lights)", None
    least = min(err for err, _ in scored)
    chosen = max(((_roundness(c), -err), i, c) for i, (err, c) in enumerate(scored) if err <= least + SNAP_SLACK)[2]
    err = _error(part.contiguous(), chosen, m)
    if err is None or err > MATCH_TOLERANCE:
        return (
            f"the best light's render is {(least if err is None else err) * 255:.1f} codes off (paint over it, cast "
            "shadows, a highlight, a point light or several lights)"
        ), None
    return "", {
        "light": _text(chosen["light"]),
        "source_light": None if chosen["source_light"] is None else _text(chosen["source_light"]),
        "ambient": float(chosen["ambient"]),
        "light_intensity": float(chosen["light_intensity"]),
        **({"light_color": list(chosen["light_color"])} if "light_color" in chosen else {}),
    }


def _named(codes, window: tuple, name: str, note: str, m: np.ndarray) -> tuple[str, dict | None]:
    """(why not, None) or ("", the layer's render fields) for a map whose name carries them (``map_name``): kept
    when the layer they make, rendered from the file's whole map by the compositor's own path (its shadows and
    point lights are the whole map's), matches the file's multiplier ``m`` (C, h, w) on its part of the map
    (``window``) within ``MATCH_TOLERANCE`` at every pixel."""
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
        return (f"its render under the light its map's name gives is {err * 255:.1f} codes off (paint over it)"), None
    return "", layer.model_dump(mode="json", include=set(NAMED_FIELDS))


def _pool(x: torch.Tensor, reach: int) -> torch.Tensor:
    """The maximum of (B, C, h, w) ``x`` over each pixel's (2·reach + 1)² neighbourhood, edges replicated."""
    import torch.nn.functional as F

    return F.max_pool2d(F.pad(x, (reach,) * 4, mode="replicate"), 2 * reach + 1, stride=1)


def _fit_shading(n: np.ndarray, m: np.ndarray) -> dict | None:
    """a, k, l of M = a + (1 − a)·k·max(0, n·l) by least squares over the lit set (module docstring)."""
    nf, mf = n.reshape(3, -1).T, m.reshape(-1)
    lit = mf > mf.min() + 1e-3
    for _ in range(FIT_ROUNDS):
        rows = np.concatenate([np.ones((mf.size, 1)), nf * lit[:, None]], 1)
        x, _, _, sv = np.linalg.lstsq(rows, mf, rcond=None)
        if sv[-1] <= IDENTIFIABLE * sv[0]:
            return None  # the lit normals do not span the light's three directions: many lights render it
        a, w = float(x[0]), x[1:]
        now = nf @ w > LIT_EPS
        if (now == lit).all():
            break
        lit = now
    norm = float(np.linalg.norm(w))
    if not (0.0 <= a < 1.0) or norm <= 1e-9 or w[2] <= 0.0:
        return None
    return {"light": _direction(w / norm), "ambient": a, "light_intensity": norm / (1.0 - a), "source_light": None}


def _fit_coloured(n: np.ndarray, m: np.ndarray) -> dict | None:
    """a, k, c, l of a coloured light's shading M_c = a + (1 − a)·k·c_c·max(0, n·l) (``m`` (3, h, w)): each channel's
    shading fit, kept when the three agree on the light (within ``COLOUR_AGREE_DEG``) and the ambient (within 0.01);
    k the largest channel's gain, c the gains over it. A coloured relight ratio is not read (its source is white)."""
    fits = [_fit_shading(n, channel) for channel in m]
    if any(f is None for f in fits):
        return None
    from lasagna.document.condition import unit_vector

    lights = [np.asarray(unit_vector(*f["light"])) for f in fits]
    mean = sum(lights) / np.linalg.norm(sum(lights))
    if min(float(v @ mean) for v in lights) < math.cos(math.radians(COLOUR_AGREE_DEG)):
        return None
    ambients = [f["ambient"] for f in fits]
    if max(ambients) - min(ambients) > 0.01:
        return None
    gains = [f["light_intensity"] for f in fits]
    k = max(gains)
    return {
        "light": _direction(mean),
        "source_light": None,
        "ambient": float(np.mean(ambients)),
        "light_intensity": k,
        "light_color": tuple(g / k for g in gains),
    }


def _fit_ratio(n: np.ndarray, m: np.ndarray) -> dict | None:
    """a, l, l_s of M = S(l)/S(l_s): the homogeneous least squares of a(M − 1) + M·n·u − n·v = 0 (module
    docstring), the lit sets of u and v updated in turn; started from each of ``FACING_Z``'s sets of pixels facing
    the viewer, the start whose light renders M closest kept."""
    nf, mf = n.reshape(3, -1).T, m.reshape(-1)
    if mf.max() <= 1.0 + 1e-3 and mf.min() >= 1.0 - 1e-3:
        return None  # a flat ratio of one: no light to read
    best: tuple[float, tuple] | None = None
    for facing in FACING_Z:
        x = _ratio_from(nf, mf, nf[:, 2] > facing)
        if x is None:
            continue
        a, u, v = x
        model = (a + nf @ v * (nf @ v > 0)) / (a + nf @ u * (nf @ u > 0))
        err = float((np.abs(model - mf) / np.maximum(1.0, mf) ** 2).max())
        if best is None or err < best[0]:
            best = (err, x)
    if best is None:
        return None
    a, u, v = best[1]
    if min(u[2], v[2]) <= 0.0:
        return None  # a light from behind the surface is no layer's
    return {
        "light": _direction(v / np.linalg.norm(v)),
        "source_light": _direction(u / np.linalg.norm(u)),
        "ambient": a,
        "light_intensity": 1.0,
    }


def _ratio_from(nf: np.ndarray, mf: np.ndarray, use: np.ndarray) -> tuple[float, np.ndarray, np.ndarray] | None:
    """(a, u, v) of the ratio fit started from the pixels ``use`` (both lights taken to light them), or None when
    the start is too small or the fit leaves no valid ambient or light."""
    if use.sum() < MIN_FIT_PIXELS:
        return None
    lit_t = lit_s = use
    x = None
    for _ in range(FIT_ROUNDS):
        rows = np.concatenate([(mf - 1.0)[:, None], mf[:, None] * nf * lit_s[:, None], -nf * lit_t[:, None]], 1)
        _, sv, vt = np.linalg.svd(rows[use], full_matrices=False)
        if sv[-2] <= IDENTIFIABLE * sv[0]:
            break  # more than one solution: the normals do not tell both lights apart
        y = vt[-1]
        y = -y if y[0] < 0 else y  # the singular vector's sign is free; the ambient is positive
        scale = float(np.linalg.norm(y[1:4])) + float(y[0])
        if abs(scale) < 1e-12:
            break
        y = y / scale
        if not 0.0 < y[0] < 1.0:
            break
        x = y
        now_s, now_t = nf @ x[1:4] > LIT_EPS, nf @ x[4:7] > LIT_EPS
        if min(now_s.sum(), now_t.sum()) < MIN_FIT_PIXELS:
            break
        if use.all() and (now_s == lit_s).all() and (now_t == lit_t).all():
            break
        lit_s, lit_t, use = now_s, now_t, np.ones_like(use)
    if x is None or np.linalg.norm(x[1:4]) <= 1e-9 or np.linalg.norm(x[4:7]) <= 1e-9:
        return None
    return float(x[0]), x[1:4], x[4:7]


def _direction(vector: np.ndarray) -> tuple[float, float]:
    """(az, el) in degrees of a unit vector, as `lasagna.document.condition.unit_vector` writes them."""
    x, y, z = (float(c) for c in vector)
    return math.degrees(math.atan2(y, x)) % 360.0, math.degrees(math.acos(max(-1.0, min(1.0, z))))


def _text(direction: tuple[float, float] | str) -> str:
    if isinstance(direction, str):
        return direction
    az, el = direction
    return f"az={az:.6g},el={el:.6g}"


def _rounder(fields: dict) -> list[dict]:
    """The exact fit and the rounder versions of it worth trying (whole degrees, a named light, ambient 0.25,
    intensity 1), the exact one first."""
    from lasagna.document.condition import NAMED_DIRECTIONS, unit_vector

    def named_or_whole(direction):
        if direction is None:
            return [None]
        az, el = direction
        out = [(round(az, 2) % 360.0, round(el, 2)), (float(round(az)) % 360.0, float(round(el)))]
        near = unit_vector(az, el)
        for name, d in NAMED_DIRECTIONS.items():
            if float(np.dot(unit_vector(*d), near)) > math.cos(math.radians(0.5)):
                out.append(name)
        return out

    ambients = [fields["ambient"], round(fields["ambient"], 2), round(fields["ambient"], 3)]
    gains = [fields["light_intensity"], round(fields["light_intensity"], 2), round(fields["light_intensity"], 3)]
    colours = [None] if "light_color" not in fields else [fields["light_color"]]
    if "light_color" in fields:
        colours += [
            tuple(round(c, 2) for c in fields["light_color"]),
            tuple(round(c, 3) for c in fields["light_color"]),
        ]
    out = [fields]
    for light in named_or_whole(fields["light"]):
        for source in named_or_whole(fields["source_light"]):
            for a in ambients:
                for k in gains:
                    for colour in colours:
                        rounder = {"light": light, "source_light": source, "ambient": a, "light_intensity": k}
                        out.append(rounder if colour is None else {**rounder, "light_color": colour})
    return out


def _roundness(fields: dict) -> int:
    """How round a fit's values are: a shading rather than a ratio, named lights (two) or whole degrees (one), an
    ambient and an intensity of two decimals each count."""
    lights = [fields["light"]] + ([] if fields["source_light"] is None else [fields["source_light"]])
    score = int(fields["source_light"] is None)
    score += int(round(fields["ambient"], 2) == fields["ambient"]) + int(
        round(fields["light_intensity"], 2) == fields["light_intensity"]
    )
    score += int(all(round(c, 2) == c for c in fields.get("light_color", ())))
    for light in lights:
        score += 2 if isinstance(light, str) else int(all(float(v).is_integer() for v in light))
    return score


def _error(codes, fields: dict, m: np.ndarray) -> float | None:
    """The largest difference between ``m`` and the surface layer of ``fields`` rendered from the map ``codes``
    (3, h, w) by the compositor's own path; None when the fields are no valid layer."""
    from lasagna.compose.layer import LayerTensors
    from lasagna.compose.surface import surface_tensors
    from lasagna.document.condition import parse_direction
    from lasagna.errors import LasagnaError

    try:
        light = _text(fields["light"])
        source = None if fields["source_light"] is None else _text(fields["source_light"])
        parse_direction(light)
        if source is not None:
            parse_direction(source)
        colour = tuple(float(c) for c in fields.get("light_color", (1.0, 1.0, 1.0)))
        if not 0.0 <= fields["ambient"] < 1.0 or not 0.0 < fields["light_intensity"] <= 16.0:
            return None
        if not all(0.0 <= c <= 1.0 for c in colour):
            return None
        rendered = surface_tensors(
            LayerTensors(codes, None, None),
            light,
            source,
            float(fields["ambient"]),
            1.0,
            colour,
            float(fields["light_intensity"]),
        ).color
    except (LasagnaError, ValueError):
        return None
    # Above 1 a multiplier is a multiply and colour-dodge pair in the file, y = m/(1 − d), whose rounding grows
    # as y²: the difference is measured in the pair's own steps.
    # ``m`` is (C, h, w); a white light renders one channel, a coloured one three (broadcast against each other).
    return float((np.abs(rendered.double().numpy() - m) / np.maximum(1.0, m) ** 2).max())


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
