"""Layered PSD export through psd-tools (the optional extra ``lasagna-layers[psd]``).

Each layer of :func:`lasagna.export.rasters.export_layers` becomes an 8-bit RGBA pixel layer made
with ``create_pixel_layer(..., blend_mode=...)`` (``PixelLayer.frompil`` ignores blend mode and
opacity, so it is not used): plus → LINEAR_DODGE (Photoshop's "Linear Dodge (Add)") and every other
mode to its psd-tools name (normal → NORMAL, color-dodge → COLOR_DODGE, …, luminosity → LUMINOSITY;
``psd_blend_modes``), the colour-dodge half of a multiplier above 1 included. Opacity is stored as
round(255·opacity); hidden layers are hidden. After each plus layer and each dodge pair comes an
opaque white DARKEN layer, min(Cb, 1): the identity in 8/16-bit tools, and the clamp GIMP 2.10's
float compositing otherwise skips (it keeps Cb·y > 1 for the next layer). The file's merged image is
our exact composite, not psd-tools' own flattening. Groups are psd-tools ``Group``s (nested): a pass-through
group is PASS_THROUGH, an isolated one has the group's blend mode; both keep opacity and visibility
(``lasagna.export.rasters`` says what stays inexact: group masks, pass-through opacity below 1). A clipped layer
has the record's clipping flag (Photoshop's clipping mask); a clipped group is written unclipped, as psd-tools
and Photoshop read none.

Layer names: the layer record's Pascal string is MacRoman and at most 255 bytes, so, as Photoshop does,
it holds a lossy stand-in (``pascal_name``) and the full name goes in the Unicode layer-name block
(``luni``), which Photoshop, GIMP, Krita and psd-tools read in its place.
"""

from __future__ import annotations

import io
import os
from collections.abc import Callable
from pathlib import Path

import torch
from PIL import Image

from lasagna.atomic import write_output
from lasagna.document.blend import BLEND_MODES
from lasagna.errors import ExportError
from lasagna.export.ora import composite_uint8
from lasagna.export.rasters import ExportGroup, export_layers
from lasagna.version import install_hint

INSTALL_HINT = install_hint("psd")


def require_psd_tools():
    """(PSDImage, BlendMode) of psd-tools; an ``ExportError`` saying how to install it when it is missing."""
    try:
        from psd_tools import PSDImage
        from psd_tools.constants import BlendMode
    except ImportError:
        raise ExportError(
            f"PSD export needs psd-tools, which is not installed; expected it: {INSTALL_HINT}", where="psd"
        ) from None
    return PSDImage, BlendMode


def _set_merged_image(psd, merged) -> None:
    """Store ``merged`` (H, W, 3) uint8 as the file's composite instead of psd-tools' own.

    psd-tools recomputes the merged image on save when the document was edited; it exposes no public
    setter, so this writes the image-data record and turns the recomputation off for this object.
    Without those internals (another psd-tools version) the file keeps psd-tools' flattening.
    """
    try:
        from psd_tools.api import numpy_io

        color = merged.astype("float32") / 255.0
        alpha = color[:, :, :1] * 0.0 + 1.0
        psd._record.image_data.set_data(numpy_io.encode_image_data(psd, color, alpha), psd._record.header)
        psd._update_preview = lambda: None
    except (AttributeError, ImportError, TypeError, ValueError):
        pass


def pascal_name(name: str) -> str:
    """The stand-in for ``name`` in a layer record's Pascal string: each character MacRoman cannot encode
    becomes ``?`` (what psd-tools' own ``name`` setter falls back to, here per character), cut to the 255
    bytes its length byte can count (MacRoman is one byte a character)."""
    return "".join(c if c.encode("mac_roman", "ignore") else "?" for c in name)[:255]


def _create_layer(psd, image, name: str, **kwargs):
    """``psd.create_pixel_layer`` with any ``name``: the Pascal string gets ``pascal_name(name)``, the
    Unicode layer-name block the name itself."""
    from psd_tools.constants import Tag

    layer = psd.create_pixel_layer(image, name=pascal_name(name), **kwargs)
    layer._record.tagged_blocks.set_data(Tag.UNICODE_LAYER_NAME, name)  # the ``name`` setter refuses > 255
    return layer


def psd_blend_modes(BlendMode) -> dict[str, object]:
    """psd-tools' ``BlendMode`` of every blend: its own name in upper case (``color-dodge`` → ``COLOR_DODGE``,
    ``linear-dodge`` → ``LINEAR_DODGE``), and plus too is LINEAR_DODGE ("Linear Dodge (Add)"): its partial alpha
    is baked into its values on export (``lasagna.export.rasters``), on which the two agree. Read back,
    LINEAR_DODGE is ``linear-dodge`` (the last of the two in this table)."""
    return {m: BlendMode.LINEAR_DODGE if m == "plus" else BlendMode[m.upper().replace("-", "_")] for m in BLEND_MODES}


def encode_psd(stack, *, composite: torch.Tensor | None = None, warn: Callable[[str], None] | None = None) -> bytes:
    """The layered 8-bit RGB PSD of ``stack`` as bytes (``composite``: the merged image, rendered if None)."""
    PSDImage, BlendMode = require_psd_tools()
    modes = psd_blend_modes(BlendMode)
    if composite is None:
        from lasagna.io.render import render_stack

        composite = render_stack(stack).image
    merged = composite_uint8(composite)
    background = tuple(float(c) for c in stack.document.canvas.background)
    # An RGBA document: layer alpha is stored as each layer's transparency channel (in an RGB document
    # psd-tools would store it as a user layer mask instead).
    psd = PSDImage.new("RGBA", (stack.width, stack.height), color=background + (1.0,))
    layers = export_layers(stack, composite.detach().cpu().double().numpy(), target="PSD", warn=warn, groups=True)
    _write_items(psd, psd, layers, stack, modes, BlendMode, isolated_in=False)
    _set_merged_image(psd, merged)
    buf = io.BytesIO()
    psd.save(buf)
    return buf.getvalue()


def _write_items(psd, parent, items: list, stack, modes, BlendMode, *, isolated_in: bool) -> None:
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
            _write_items(psd, group, item.layers, stack, modes, BlendMode, isolated_in=isolated_in or item.isolated)
            continue
        layer = item
        pil = Image.fromarray(layer.rgba_uint8())
        created = _create_layer(
            psd,
            pil,
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
            white = Image.new("RGBA", pil.size, (255, 255, 255, 255))
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
    stack, path: str | os.PathLike, *, composite: torch.Tensor | None = None, warn: Callable[[str], None] | None = None
) -> Path:
    """Write ``stack`` as a layered PSD at ``path`` (atomically); returns the path."""
    data = encode_psd(stack, composite=composite, warn=warn)
    return write_output(path, data, ExportError)
