"""OpenRaster (.ora) export (the import half is ``lasagna.export.ora_import``).

The file (OpenRaster spec, https://www.openraster.org/baseline/file-layout-spec.html) is a zip whose *first* entry
is ``mimetype``, stored uncompressed, reading exactly ``image/openraster``; then ``stack.xml`` (``<image w
h><stack>`` with layers **topmost first**, each ``<layer name src x y opacity visibility composite-op>``),
``data/*.png`` (8-bit, in the fewest channels that hold the layer: gray for a multiplier, RGB for an opaque layer,
else with alpha; every reader opens any PNG), ``mergedimage.png`` (our exact composite) and
``Thumbnails/thumbnail.png`` (at most 256×256). Blends map to ``svg:src-over`` (normal), ``svg:plus``,
``svg:<name>`` for every W3C mode the OpenRaster spec names (``svg:multiply``, ``svg:overlay``, …,
``svg:luminosity``) and Krita's ``krita:<id>`` for exclusion and Photoshop's modes (``KRITA_OPS``: what Krita writes
and reads; it reads ``svg:exclusion`` as normal); values a reader cannot blend directly are expressed as in
:mod:`lasagna.export.rasters` (multiplier y > 1 as a multiply + ``svg:color-dodge`` pair). A bottom background layer
makes the file flatten to our opaque composite; a transparent document (``canvas.background`` null) has none, and
its merged image and thumbnail are RGBA. Alpha × mask is baked into each PNG's alpha, opacity into ``opacity``.
Layers are encoded a band of rows at a time (``ExportLayer.bands``), so no layer is held as floats beside its own
pixels.

Groups are nested ``<stack>`` elements (``isolation="isolate"`` for an isolated group with its
composite-op and opacity, ``"auto"`` for a pass-through one), their layers at canvas offsets, as Krita
writes them; see :mod:`lasagna.export.rasters` for what is exact. A clipping chain is an isolated ``<stack>``
of the base and its clipped layers, ``svg:src-atop`` (Krita's inherit alpha; ``krita_clip_stacks``); read
back, ``svg:src-atop`` is ``clip``.
"""

from __future__ import annotations

import io
import os
import zipfile
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING
from xml.sax.saxutils import quoteattr

import numpy as np
from PIL import Image

from lasagna.atomic import write_output
from lasagna.document.blend import BLEND_MODES
from lasagna.errors import ExportError
from lasagna.io.png import encode_bands

if TYPE_CHECKING:  # torch and the rasters (which import it) are loaded by the functions that write
    import torch

    from lasagna.compose.render import RenderResult
    from lasagna.export.rasters import ExportLayer

MIMETYPE = b"image/openraster"
THUMBNAIL_MAX = 256
_EPOCH = (1980, 1, 1, 0, 0, 0)  # fixed entry dates: the same stack gives the same bytes

# Krita's composite-op ids (KoCompositeOpRegistry.h) of the blends the OpenRaster spec does not name: Krita writes
# and reads them as "krita:<id>" and reads an svg: name outside the spec's list (svg:exclusion included) as normal
# (kis_open_raster_stack_load_visitor.cpp). Photoshop's Hard Mix is Krita's hard_mix_photoshop ("hard mix" is
# another formula).
KRITA_OPS = {
    "exclusion": "exclusion",
    "linear-burn": "linear_burn",
    "linear-dodge": "linear_dodge",
    "subtract": "subtract",
    "divide": "divide",
    "vivid-light": "vivid_light",
    "linear-light": "linear light",
    "pin-light": "pin_light",
    "hard-mix": "hard_mix_photoshop",
    "darker-color": "darker color",
    "lighter-color": "lighter color",
    "dissolve": "dissolve",
}
# OpenRaster's composite-op for every blend: svg:src-over for normal, "svg:" + the CSS name for the modes the
# OpenRaster spec names (W3C's but exclusion, and svg:plus), "krita:" + Krita's id for the others.
OPS_TO_SVG = {
    mode: "svg:src-over" if mode == "normal" else f"krita:{KRITA_OPS[mode]}" if mode in KRITA_OPS else f"svg:{mode}"
    for mode in BLEND_MODES
}
# Read: every name written, and svg:exclusion (what earlier versions wrote; other readers may too).
SVG_TO_BLEND = {svg: mode for mode, svg in OPS_TO_SVG.items()} | {"svg:exclusion": "exclusion"}
DODGE_PREFIX = "data/_dodge/"  # the src of the colour-dodge half of a multiplier above 1 (rasters.py's key)


# ---- export --------------------------------------------------------------------------------------


def _thumbnail(composite_hwc: np.ndarray) -> bytes:
    im = Image.fromarray(composite_hwc)
    # Halve by box filtering first (reducing_gap): a 12 MP composite is then not resampled by LANCZOS whole.
    im.thumbnail((THUMBNAIL_MAX, THUMBNAIL_MAX), Image.Resampling.LANCZOS, reducing_gap=3.0)
    buf = io.BytesIO()
    im.save(buf, format="PNG")
    return buf.getvalue()


def _layer_xml(layer: ExportLayer, indent: str) -> str:
    attrs = {
        "name": layer.name,
        "src": f"data/{layer.key}.png",
        "x": str(layer.x),
        "y": str(layer.y),
        "opacity": f"{layer.opacity:.6f}",
        "visibility": "visible" if layer.visible else "hidden",
        "composite-op": "svg:src-atop" if layer.clip and layer.op == "normal" else OPS_TO_SVG[layer.op],
    }
    return indent + "<layer " + " ".join(f"{k}={quoteattr(v)}" for k, v in attrs.items()) + " />"


def _items_xml(items: list, indent: str) -> list[str]:
    from lasagna.export.rasters import ExportGroup

    lines = []
    for item in reversed(items):  # topmost first
        if not isinstance(item, ExportGroup):
            lines.append(_layer_xml(item, indent))
            continue
        # A group is a nested stack at x = y = 0 (its layers carry canvas offsets), as Krita writes one;
        # isolation "isolate" | "auto" (pass-through) as the OpenRaster spec and Krita name them.
        attrs = {
            "name": item.name,
            "x": "0",
            "y": "0",
            "opacity": f"{item.opacity:.6f}",
            "visibility": "visible" if item.visible else "hidden",
            "composite-op": OPS_TO_SVG[item.op],
            "isolation": "isolate" if item.isolated else "auto",
        }
        lines.append(indent + "<stack " + " ".join(f"{k}={quoteattr(v)}" for k, v in attrs.items()) + ">")
        lines += _items_xml(item.layers, indent + "  ")
        lines.append(indent + "</stack>")
    return lines


def krita_clip_stacks(items: list) -> list:
    """``items`` (and every group's) with each clipping chain — an item and the ``clip`` items above it — as Krita
    writes one: an isolated ``<stack>`` with the base's composite-op, opacity and visibility, holding the base
    (normal, opaque, visible) and the clipped layers, ``svg:src-atop`` (Krita's inherit alpha: clipped to what
    lies below them in the stack, here the base alone)."""
    from lasagna.export.rasters import ExportGroup

    out: list = []
    for item in items:
        if isinstance(item, ExportGroup) and not item.clip:
            item = replace(item, layers=krita_clip_stacks(item.layers))
        if not item.clip or not out:
            out.append(item)
            continue
        below = out[-1]
        if not (isinstance(below, ExportGroup) and below.key.startswith("_clip/")):
            isolated = {"isolated": True} if isinstance(below, ExportGroup) else {}  # a group base is isolated
            base = replace(below, op="normal", opacity=1.0, visible=True, **isolated)
            below = out[-1] = ExportGroup(
                below.name, f"_clip/{below.source}", below.op, below.opacity, below.visible, True, [base], below.source
            )
        below.layers.append(item)
    return out


def _stack_xml(width: int, height: int, layers: list) -> str:
    lines = ["<?xml version='1.0' encoding='UTF-8'?>", f'<image version="0.0.5" w="{width}" h="{height}">', "  <stack>"]
    lines += _items_xml(layers, "    ")
    lines += ["  </stack>", "</image>", ""]
    return "\n".join(lines)


def composite_uint8(image: torch.Tensor) -> np.ndarray:
    """(3, H, W) composite → (H, W, 3) uint8: clamped to [0, 1], rounded to nearest."""
    import torch

    if not bool(torch.isfinite(image.detach()).all()):
        raise ExportError("composite has NaN or infinite values; expected finite layer values", where="composite")
    return (image.detach().cpu().double().clamp(0.0, 1.0) * 255.0).round().to(torch.uint8).permute(1, 2, 0).numpy()


def composite_result(stack, composite) -> RenderResult:
    """``composite`` as a ``RenderResult``: itself, a render's image (3, H, W) — for a transparent document, whose
    alpha an image does not carry, the stack is rendered again —, or (None) the stack rendered."""
    from lasagna.compose.render import RenderResult
    from lasagna.io.render import render_stack

    if isinstance(composite, RenderResult):
        return composite
    if composite is None or stack.document.canvas.background is None:
        return render_stack(stack)
    return RenderResult(composite, {}, [])


def keep_ora_current(folder: str | os.PathLike) -> Callable:
    """``save_in_place``'s ``extra`` for a stack folder: a folder that holds a stack.ora (one `lasagna edit` wrote)
    gets it re-encoded from the saved stack and its composite, so it never goes stale; any other folder gets none."""
    path = Path(folder) / "stack.ora"

    def extra(stack, result) -> dict[str, bytes]:
        return {"stack.ora": encode_ora(stack, composite=result)} if path.is_file() else {}

    return extra


def encode_ora(
    stack,
    *,
    composite: torch.Tensor | RenderResult | None = None,
    merged_png: bytes | None = None,
    warn: Callable[[str], None] | None = None,
) -> bytes:
    """The OpenRaster file of ``stack`` as bytes (see the module docstring).

    ``composite`` is the exact composite for ``mergedimage.png`` (a ``RenderResult``, or its image (3, H, W));
    rendered if not given. ``merged_png``: that composite already encoded as an 8-bit PNG
    (``lasagna.io.render.encode_composite``), used as is rather than encoded again.
    """
    from lasagna.export.rasters import export_layers, leaves
    from lasagna.io.render import composite_hwc, encode_composite

    result = composite_result(stack, composite)
    layers = export_layers(stack, result.image, target="OpenRaster", warn=warn, groups=True, alpha=result.alpha)
    tree = krita_clip_stacks(layers)
    entries: list[tuple[str, bytes]] = [("stack.xml", _stack_xml(stack.width, stack.height, tree).encode("utf-8"))]
    for layer in leaves(layers):
        # The fewest channels that hold the layer (gray for a multiplier, no alpha where it has none): every
        # OpenRaster reader opens any PNG, and a 12 MP multiplier is then 12 MB to deflate instead of 48.
        data = encode_bands(layer.bands(8, fit=True), layer.width, layer.height)
        entries.append((f"data/{layer.key}.png", data))
    if merged_png is None:
        merged_png = encode_composite(result, "mergedimage.png")
    entries.append(("mergedimage.png", merged_png))
    # A canvas that fits the thumbnail is its own thumbnail (Pillow's ``thumbnail`` never enlarges).
    small = max(stack.width, stack.height) <= THUMBNAIL_MAX
    entries.append(("Thumbnails/thumbnail.png", merged_png if small else _thumbnail(composite_hwc(result))))
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf:
        # The spec: mimetype first, stored (not deflated), no extra field, so that the bytes
        # "image/openraster" sit at offset 38 for magic-number sniffing.
        zf.writestr(zipfile.ZipInfo("mimetype", date_time=_EPOCH), MIMETYPE, compress_type=zipfile.ZIP_STORED)
        for name, data in entries:
            # PNGs are already deflated; storing them saves time and loses nothing.
            kind = zipfile.ZIP_STORED if name.endswith(".png") else zipfile.ZIP_DEFLATED
            zf.writestr(zipfile.ZipInfo(name, date_time=_EPOCH), data, compress_type=kind)
    return out.getvalue()


def export_ora(
    stack,
    path: str | os.PathLike,
    *,
    composite: torch.Tensor | RenderResult | None = None,
    warn: Callable[[str], None] | None = None,
) -> Path:
    """Write ``stack`` as an OpenRaster file at ``path`` (atomically); returns the path."""
    data = encode_ora(stack, composite=composite, warn=warn)
    return write_output(path, data, ExportError)
