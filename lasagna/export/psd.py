"""Layered PSD export through psd-tools (the optional extra ``lasagna-layers[psd]``).

Each layer of :func:`lasagna.export.rasters.export_layers` becomes an RGBA pixel layer of the file's depth, 8 or
(``depth=16``) 16 bits a channel, made with ``create_pixel_layer_from_array(..., blend_mode=...)`` from the layer's
codes (``PixelLayer.frompil`` ignores blend mode and opacity, and a PIL image holds 8 bits): plus → LINEAR_DODGE
(Photoshop's "Linear Dodge (Add)") and every other mode to its psd-tools name (normal → NORMAL, color-dodge →
COLOR_DODGE, …, luminosity → LUMINOSITY; ``psd_blend_modes``), the colour-dodge half of a multiplier above 1 included.
Opacity is stored as round(255·opacity); hidden layers are hidden. After each plus layer and each dodge pair comes an
opaque white DARKEN layer, min(Cb, 1): the identity in 8/16-bit tools, and the clamp GIMP 2.10's float compositing
otherwise skips (it keeps Cb·y > 1 for the next layer). The file's merged image is our exact composite, not psd-tools'
own flattening, with the composite's alpha for a transparent document (which gets no background layer). Groups are
psd-tools ``Group``s (nested): a pass-through group is PASS_THROUGH, an isolated one has the group's blend mode; both
keep opacity and visibility (``lasagna.export.rasters`` says what stays inexact: group masks, pass-through opacity
below 1). A clipped layer has the record's clipping flag (Photoshop's clipping mask); a clipped group is written
unclipped, as psd-tools and Photoshop read none.

Layer names: the layer record's Pascal string is MacRoman and at most 255 bytes, so, as Photoshop does,
it holds a lossy stand-in (``pascal_name``) and the full name goes in the Unicode layer-name block
(``luni``), which Photoshop, GIMP, Krita and psd-tools read in its place.
"""

from __future__ import annotations

import io
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from lasagna.atomic import write_output
from lasagna.compose.render import RenderResult
from lasagna.errors import ExportError
from lasagna.export.ora import composite_result
from lasagna.export.psd_tools_api import psd_blend_modes, require_psd_tools
from lasagna.export.rasters import ExportGroup, export_layers
from lasagna.io.render import composite_hwc


def _set_merged_image(psd, merged) -> None:
    """Store ``merged`` (H, W, 3 or 4) codes, uint8 or uint16 (RGBA: a transparent document's), as the file's
    composite instead of psd-tools' own.

    psd-tools recomputes the merged image on save when the document was edited; it exposes no public
    setter, so this writes the image-data record and turns the recomputation off for this object.
    Without those internals (another psd-tools version) the file keeps psd-tools' flattening.
    """
    try:
        from psd_tools.api import numpy_io

        values = merged.astype("float32") / float(np.iinfo(merged.dtype).max)
        color = values[:, :, :3]
        alpha = values[:, :, 3:] if values.shape[2] == 4 else np.ones_like(values[:, :, :1])
        if values.shape[2] == 4:  # the merged image has transparency: Photoshop's "Mtrn" ("Mt16") block says so
            from psd_tools.constants import Tag
            from psd_tools.psd.tagged_blocks import TaggedBlocks

            info = psd._record.layer_and_mask_information
            if info.tagged_blocks is None:
                info.tagged_blocks = TaggedBlocks()
            sixteen = merged.dtype == np.uint16
            info.tagged_blocks.set_data(Tag.SAVING_MERGED_TRANSPARENCY16 if sixteen else Tag.SAVING_MERGED_TRANSPARENCY)
        psd._record.image_data.set_data(numpy_io.encode_image_data(psd, color, alpha), psd._record.header)
        psd._update_preview = lambda: None
    except (AttributeError, ImportError, TypeError, ValueError):
        pass


def pascal_name(name: str) -> str:
    """The stand-in for ``name`` in a layer record's Pascal string: each character MacRoman cannot encode
    becomes ``?`` (what psd-tools' own ``name`` setter falls back to, here per character), cut to the 255
    bytes its length byte can count (MacRoman is one byte a character)."""
    return "".join(c if c.encode("mac_roman", "ignore") else "?" for c in name)[:255]


def _create_layer(psd, codes: np.ndarray, name: str, **kwargs):
    """``psd.create_pixel_layer_from_array`` of (h, w, 4) codes (uint8 or uint16) with any ``name``: the Pascal
    string gets ``pascal_name(name)``, the Unicode layer-name block the name itself."""
    from psd_tools.constants import Tag

    layer = psd.create_pixel_layer_from_array(codes, name=pascal_name(name), **kwargs)
    layer._record.tagged_blocks.set_data(Tag.UNICODE_LAYER_NAME, name)  # the ``name`` setter refuses > 255
    return layer


PSD_DEPTHS = (8, 16)


def encode_psd(
    stack,
    *,
    composite: torch.Tensor | RenderResult | None = None,
    warn: Callable[[str], None] | None = None,
    depth: int = 8,
) -> bytes:
    """The layered RGB PSD of ``stack`` as bytes, ``depth`` 8 or 16 bits a channel (``composite``: the merged
    image, a ``RenderResult`` or its image; rendered if None)."""
    if depth not in PSD_DEPTHS:
        raise ExportError(f"bit depth {depth!r}; expected 8 or 16", where="psd")
    PSDImage, BlendMode = require_psd_tools()
    modes = psd_blend_modes(BlendMode)
    result = composite_result(stack, composite)
    if not bool(torch.isfinite(result.image.detach()).all()):
        raise ExportError("composite has NaN or infinite values; expected finite layer values", where="composite")
    background = stack.document.canvas.background
    fill = (0.0, 0.0, 0.0, 0.0) if background is None else tuple(float(c) for c in background) + (1.0,)
    # An RGBA document: layer alpha is stored as each layer's transparency channel (in an RGB document
    # psd-tools would store it as a user layer mask instead).
    psd = PSDImage.new("RGBA", (stack.width, stack.height), color=fill, depth=depth)
    layers = export_layers(stack, result.image, target="PSD", warn=warn, groups=True, alpha=result.alpha)
    clear = background is None  # over transparency a white clamp layer would paint white, as in an isolated group
    _write_items(psd, psd, layers, stack, modes, BlendMode, isolated_in=clear, depth=depth)
    _set_merged_image(psd, composite_hwc(result, depth))  # type: ignore[arg-type]
    buf = io.BytesIO()
    psd.save(buf)
    return buf.getvalue()


def _write_items(psd, parent, items: list, stack, modes, BlendMode, *, isolated_in: bool, depth: int) -> None:
    """Create ``items`` (bottom to top) in ``parent`` (the document or a group): pixel layers, and groups
    as psd-tools ``Group``s — PASS_THROUGH for a pass-through group, else the group's blend (isolated)."""
    from psd_tools.api.layers import Group
    from psd_tools.constants import Tag

    for i, item in enumerate(items):
        if isinstance(item, ExportGroup):
            group = Group.new(parent, name=pascal_name(item.name))
            group._record.tagged_blocks.set_data(Tag.UNICODE_LAYER_NAME, item.name)
            group.blend_mode = modes[item.op] if item.isolated else BlendMode.PASS_THROUGH
            group.opacity = int(round(255 * item.opacity))
            group.visible = item.visible
            inside = isolated_in or item.isolated
            _write_items(psd, group, item.layers, stack, modes, BlendMode, isolated_in=inside, depth=depth)
            continue
        layer = item
        codes = layer.rgba_codes(depth)  # type: ignore[arg-type]
        created = _create_layer(
            psd,
            codes,
            layer.name,
            top=layer.y,
            left=layer.x,
            opacity=int(round(255 * layer.opacity)),
            blend_mode=modes[layer.op],
        )
        created.visible = layer.visible
        created.clipping = layer.clip  # Photoshop's clipping mask: clipped to the nearest unclipped layer below
        if parent is not psd:
            parent.append(created)
        nxt = items[i + 1] if i + 1 < len(items) else None
        last_part = nxt is None or getattr(nxt, "source", None) != layer.source or isinstance(nxt, ExportGroup)
        in_chain = layer.clip or getattr(nxt, "clip", False)  # a layer between would break the clipping run
        if layer.op in ("plus", "linear-dodge", "color-dodge") and last_part and not isolated_in and not in_chain:
            # GIMP 2.10 composites PSD layers in float and keeps a dodge or addition result above 1
            # unclamped, so a layer with alpha above it would blend with that value. An opaque
            # white "darken" layer, min(Cb, 1), clamps it there and is the identity in 8/16-bit tools.
            # (Not inside an isolated group: over its transparent backdrop it would paint white.)
            white = np.full_like(codes, np.iinfo(codes.dtype).max)
            clamp = _create_layer(
                psd,
                white,
                f"{stack.layer(layer.source).name} (clamp to 1)",
                top=layer.y,
                left=layer.x,
                blend_mode=BlendMode.DARKEN,
            )
            clamp.visible = layer.visible
            if parent is not psd:
                parent.append(clamp)


def export_psd(
    stack,
    path: str | os.PathLike,
    *,
    composite: torch.Tensor | RenderResult | None = None,
    warn: Callable[[str], None] | None = None,
    depth: int = 8,
) -> Path:
    """Write ``stack`` as a layered PSD of ``depth`` bits a channel at ``path`` (atomically); returns the path."""
    data = encode_psd(stack, composite=composite, warn=warn, depth=depth)
    return write_output(path, data, ExportError)
