"""Per-layer PNG export: each layer's raw values, exactly as a stack folder stores them.

Never min–max normalised: a pixel stores v = (y − lo)/(hi − lo) for the layer's ``range``
[lo, hi] (16-bit for a range other than [0, 1] and for learned layers, so a multiplier round-trips to
within 1/65535 of its range), alpha in the PNG's alpha. ``DIR/<id>.png`` per layer, ``DIR/masks/<id>.png``
per mask, and ``DIR/layers.json`` listing, bottom to top, each file with what is needed to read the
values back: blend, range, offset, bit depth. Solid layers are written as rectangles of their colour;
learned layers not rendered yet are listed without a file.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from lasagna.atomic import atomic_write_all
from lasagna.document import GroupLayer, LearnedLayer, SolidLayer
from lasagna.io.png import encode_png
from lasagna.io.stack import NOT_RENDERED, encode_layer


def layer_pngs(stack, *, clip: bool = False) -> tuple[dict[str, bytes], dict]:
    """The files of a per-layer export (relative name → bytes) and the index written as layers.json."""
    files: dict[str, bytes] = {}
    index = []
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
        if isinstance(layer, GroupLayer):
            entry.update(isolated=layer.isolated, layers=[child.id for child in layer.layers], file=None)
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
        elif layer.id in stack.tensors:
            data, mask = encode_layer(stack, layer.id, clip=clip)
            files[f"{layer.id}.png"] = data
            entry.update(file=f"{layer.id}.png", bit_depth=int.from_bytes(data[24:25], "big"))
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
