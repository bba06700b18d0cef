"""Per-layer PNG export: each layer's raw values, exactly as a stack folder stores them.

Never min–max normalised: a pixel stores v = (y − lo)/(hi − lo) for the layer's ``range``
[lo, hi] (16-bit for a range other than [0, 1] and for learned layers, so a multiplier round-trips to
within 1/65535 of its range), alpha in the PNG's alpha. ``DIR/<id>.png`` per layer, ``DIR/masks/<id>.png``
per mask, and ``DIR/layers.json`` listing, bottom to top, each file with what is needed to read the
values back: blend, range, offset, bit depth. Solid layers are written as rectangles of their colour, gradient
and pattern layers as their fill's pixels (16-bit; the index keeps the ``gradient`` or ``pattern`` record), a surface
layer as its stored 16-bit normal map (the index keeps its ``surface`` record: the map's convention, its light and
every render field, so a reader can light it as the stack does); learned layers not rendered yet are listed without a
file.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import torch

from lasagna.atomic import atomic_write_all
from lasagna.compose.plan import gradient_tensors, pattern_tensors
from lasagna.compose.resample import downsample
from lasagna.compose.surface import integrate_normals, relieved_map
from lasagna.document import AdjustmentLayer, GroupLayer, LearnedLayer, SolidLayer, SurfaceLayer
from lasagna.errors import ExportError
from lasagna.export.surface_import import NAMED_FIELDS
from lasagna.io.png import encode_png
from lasagna.io.stack import NOT_RENDERED, encode_layer

SURFACE_MAP_CONVENTION = "tangent space, n -> (n + 1)/2, +Y up (OpenGL)"
"""How a surface layer's file in a per-layer export holds its normals (its index entry's ``surface.normal_map``)."""


def layer_pngs(stack, *, clip: bool = False) -> tuple[dict[str, bytes], dict]:
    """The files of a per-layer export (relative name → bytes) and the index written as layers.json."""
    files: dict[str, bytes] = {}
    index = []
    origins: dict[str, tuple[int, int]] = {}  # where each layer's enclosing groups put it

    def place(layers, origin: tuple[int, int]) -> None:
        for layer in layers:
            origins[layer.id] = origin
            if isinstance(layer, GroupLayer):
                place(layer.layers, (origin[0] + layer.offset.x, origin[1] + layer.offset.y))

    place(stack.document.layers, (0, 0))
    for path, layer in stack.document.walk():
        entry = {
            "id": layer.id,
            "name": layer.name,
            "kind": layer.kind,
            "blend": layer.blend,
            "offset": {"x": layer.offset.x, "y": layer.offset.y},
            "opacity": layer.opacity,
            "visible": layer.visible,
        }
        if len(path.split(".")) > 1:  # inside a group: its offset adds the groups' (layers[i].layers[j])
            entry["path"] = path
        if isinstance(layer, (GroupLayer, AdjustmentLayer)):  # no pixels: the index records it, and its mask
            if isinstance(layer, GroupLayer):
                entry.update(isolated=layer.isolated, layers=[child.id for child in layer.layers], file=None)
            else:
                entry.update(adjustment=layer.adjustment.model_dump(mode="json"), file=None)
            t = stack.tensors.get(layer.id)
            if layer.mask is not None and t is not None and t.mask is not None:
                files[f"masks/{layer.id}.png"] = encode_png(
                    np.clip(t.mask.detach().double().numpy(), 0.0, 1.0), bit_depth=8, where=f"group {layer.id!r} mask"
                )
                entry["mask"] = f"masks/{layer.id}.png"
            index.append(entry)
            continue
        entry["range"] = list(layer.range)
        lo, hi = layer.range
        if isinstance(layer, SolidLayer):
            w, h = (layer.size.width, layer.size.height) if layer.size else (stack.width, stack.height)
            rgba = list(layer.color)
            color = np.broadcast_to(np.asarray(rgba[:3], dtype=np.float64)[:, None, None], (3, h, w))
            alpha = np.full((1, h, w), rgba[3]) if len(rgba) == 4 else None
            depth = 8 if tuple(layer.range) == (0.0, 1.0) else 16
            files[f"{layer.id}.png"] = encode_png(color, alpha, bit_depth=depth, where=f"layer {layer.id!r}")
            entry.update(file=f"{layer.id}.png", bit_depth=depth)
        elif layer.kind in ("gradient", "pattern") and (layer.kind == "gradient" or layer.id in stack.tensors):
            t = stack.tensors.get(layer.id)
            mask = None if t is None else t.mask
            if layer.kind == "gradient":
                g = gradient_tensors(layer, stack.width, stack.height, origins[layer.id], mask, path)
                entry["gradient"] = layer.gradient.model_dump(mode="json")
            else:
                g = pattern_tensors(layer, t, stack.width, stack.height, origins[layer.id], path)
                entry["pattern"] = layer.pattern.model_dump(mode="json")
            color = g.color.detach().double().numpy()
            alpha = None if g.alpha is None else g.alpha.detach().double().numpy()
            files[f"{layer.id}.png"] = encode_png(color, alpha, bit_depth=16, where=f"layer {layer.id!r}")
            entry.update(file=f"{layer.id}.png", bit_depth=16)
            if mask is not None:
                m = np.clip(mask.detach().double().numpy().reshape(1, *mask.shape[-2:]), 0.0, 1.0)
                files[f"masks/{layer.id}.png"] = encode_png(m, bit_depth=8, where=f"layer {layer.id!r} mask")
                entry["mask"] = f"masks/{layer.id}.png"
        elif layer.id in stack.tensors:
            data, mask = encode_layer(stack, layer.id, clip=clip)
            files[f"{layer.id}.png"] = data
            entry.update(file=f"{layer.id}.png", bit_depth=int.from_bytes(data[24:25], "big"))
            if isinstance(layer, SurfaceLayer):  # the file is its normal map: the index keeps what lights it
                entry["surface"] = {
                    "normal_map": SURFACE_MAP_CONVENTION,
                    **layer.model_dump(mode="json", include={*NAMED_FIELDS, "relief"}),
                }
            if mask is not None:
                files[f"masks/{layer.id}.png"] = mask
                entry["mask"] = f"masks/{layer.id}.png"
        elif isinstance(layer, LearnedLayer):
            entry["file"] = None
            entry["note"] = NOT_RENDERED
        index.append(entry)
    meta = {
        "format": "lasagna.layers",
        "version": 1,
        "canvas": {"width": stack.width, "height": stack.height},
        "values": "each PNG stores v = (y - lo) / (hi - lo) for range [lo, hi]; alpha is not mapped",
        "layers": index,
    }
    return files, meta


def export_layer_pngs(stack, folder: str | os.PathLike, *, clip: bool = False) -> list[Path]:
    """Write every layer's raw values into ``folder`` (see the module docstring), all files or none
    (``lasagna.atomic.atomic_write_all``); returns the files."""
    files, meta = layer_pngs(stack, clip=clip)
    folder = Path(folder)
    outputs = [(folder / name, data) for name, data in files.items()]
    outputs.append((folder / "layers.json", (json.dumps(meta, indent=2) + "\n").encode("utf-8")))
    return atomic_write_all(outputs)


def normal_map_png(stack, layer_id: str | None = None, *, directx: bool = False) -> bytes:
    """PNG bytes of surface layer ``layer_id``'s normal map (default: the topmost surface layer) on the canvas:
    16-bit RGB, tangent space, n ↦ (n + 1)/2 with +Y up (the OpenGL convention Blender, Krita's tangent-normal
    brush and Godot's ``CanvasTexture.normal_texture`` read) or, with ``directx``, +Y down: green g ↦ 1 − g, the
    DirectX convention of Unreal and Substance's DirectX preset (a 16-bit code k becomes 65535 − k exactly). Outside
    the layer, and where its mask or alpha is 0, the map holds the flat normal (0.5, 0.5, 1.0). The relief is the
    layer's (``relief`` ≠ 1: the stored map deepened, `compose.surface.relieved_map`), so it lights as the layer
    renders."""
    layer, codes = canvas_normal_map(stack, layer_id)
    if directx:
        codes = codes.copy()
        codes[1] = 1.0 - codes[1]
    return encode_png(codes, bit_depth=16, where=f"layer {layer.id!r} normal map")


def height_map_png(stack, layer_id: str | None = None) -> tuple[bytes, float]:
    """(PNG bytes, peak) of surface layer ``layer_id``'s height map (default: the topmost surface layer) on the
    canvas: the heights whose slopes best fit the normal map ``normal_map_png`` writes (least squares,
    Frankot–Chellappa: `compose.surface.integrate_normals`), 16-bit grey, black the lowest point and white ``peak``
    pixels above it (0 for a flat map: all black, `NORMAL_CODE_SLOPE`) — a displacement or parallax map for Blender
    or a game engine, whose strength is ``peak`` in the canvas's pixels. A normal map holds slopes only, so a step (an
    object's outline against what lies behind it) comes back as the steepest slope a normal allows, not as a jump."""
    layer, codes, heights = canvas_heights(stack, layer_id)
    size = tuple(codes.shape[-2:])
    if tuple(heights.shape[-2:]) != size:
        heights = torch.nn.functional.interpolate(heights, size=size, mode="bilinear", align_corners=False)
    heights = heights[0] * (size[1] / 2.0)  # canvas units (2 across) to pixels
    peak = float(heights.max())
    if peak <= NORMAL_CODE_SLOPE * sum(codes.shape[-2:]):
        heights, peak = torch.zeros_like(heights), 0.0
    else:
        heights = heights / peak
    return encode_png(heights.numpy(), bit_depth=16, where=f"layer {layer.id!r} height map"), peak


def canvas_heights(stack, layer_id: str | None = None):
    """(the surface layer, its normal map's codes on the canvas as `canvas_normal_map` gives them, the heights
    (1, 1, h, w) in canvas units whose slopes best fit them — `compose.surface.integrate_normals` — at most
    ``HEIGHT_MAX_SIDE`` on a side)."""
    layer, codes = canvas_normal_map(stack, layer_id)
    normals = torch.nn.functional.normalize(torch.from_numpy(codes)[None] * 2.0 - 1.0, dim=1)
    size = tuple(codes.shape[-2:])
    scale = min(1.0, HEIGHT_MAX_SIDE / max(size))
    if scale < 1.0:  # integrated at most at HEIGHT_MAX_SIDE (heights are in canvas units, whatever the size)
        small = (max(1, round(size[0] * scale)), max(1, round(size[1] * scale)))
        normals = torch.nn.functional.normalize(downsample(normals, small), dim=1)
    return layer, codes, integrate_normals(normals)


def occlusion_map_png(stack, layer_id: str | None = None) -> bytes:
    """PNG bytes of surface layer ``layer_id``'s ambient-occlusion map (default: the topmost surface layer) on the
    canvas: 16-bit grey, the share of a cosine-weighted sky each point of its heights sees (`canvas_heights`;
    `compose.shadow.occlusion`, what the layer's ``occlusion`` darkens its ambient by) — white open, darker in
    creases and at the feet of walls: an AO map for a game engine or a 2D-lighting tool."""
    from lasagna.compose.shadow import occlusion

    layer, codes, heights = canvas_heights(stack, layer_id)
    seen = occlusion(heights, tuple(codes.shape[-2:]))[0]
    return encode_png(seen.numpy(), bit_depth=16, where=f"layer {layer.id!r} occlusion map")


HEIGHT_MAX_SIDE = 1024
"""The longest side a height map is integrated at: its FFT works on a mirrored image of twice the size in complex
float64 (about 330 MB at 1024); a larger canvas is integrated reduced and its heights enlarged bilinearly."""
NORMAL_CODE_SLOPE = 2.0 / 65535.0
"""One 16-bit code of a normal map's x or y (n = 2v − 1): the slope a flat map's 0.5, stored as 32768, is off by at
most. A height map whose peak is within that slope across the canvas's height plus width (in pixels) is a flat map's
quantisation: written black, peak 0."""


def canvas_normal_map(stack, layer_id: str | None = None):
    """(the surface layer, its normal map's codes (3, H, W) float64 on the canvas) as ``normal_map_png`` writes
    them; ``layer_id`` None: the topmost surface layer."""
    surfaces = [layer for _, layer in stack.document.walk() if isinstance(layer, SurfaceLayer)]
    if not surfaces:
        raise ExportError("the stack has no surface layer; expected one to write its normal map", "normal map")
    if layer_id is None:
        layer = surfaces[-1]
    else:
        named = [layer for layer in surfaces if layer.id == layer_id]
        if not named:
            ids = ", ".join(layer.id for layer in surfaces)
            raise ExportError(f"no surface layer {layer_id!r}; expected one of {ids}", "normal map")
        layer = named[0]
    t = stack.tensors[layer.id]
    h_, w_ = stack.height, stack.width
    out = np.empty((3, h_, w_))
    out[:] = np.array([0.5, 0.5, 1.0])[:, None, None]
    color = relieved_map(t.color.detach(), layer.relief).cpu().double().numpy()
    keep = np.ones(color.shape[1:], dtype=bool)
    for extra in (t.alpha, t.mask):
        if extra is not None:
            keep &= extra.detach().cpu().double().numpy().reshape(color.shape[1:]) > 0
    x0, y0 = layer.offset.x, layer.offset.y
    ys, xs = slice(max(0, y0), min(h_, y0 + color.shape[1])), slice(max(0, x0), min(w_, x0 + color.shape[2]))
    src = (slice(None), slice(ys.start - y0, ys.stop - y0), slice(xs.start - x0, xs.stop - x0))
    if ys.start < ys.stop and xs.start < xs.stop:
        region = out[:, ys, xs]
        out[:, ys, xs] = np.where(keep[src[1:]][None], color[src], region)
    return layer, out
