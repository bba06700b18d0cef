"""The small Python API: load, build, render, save and export layer stacks.

    import lasagna
    stack = lasagna.load("examples/stacks/basic")          # a Stack: document + layer tensors
    result = lasagna.render(stack)                         # RenderResult(image (3, H, W), skipped, evaluated)
    lasagna.save(stack, "out/copy", composite=True)        # stack.json, layers/*.png, composite.png

    lasagna.to_pil(result).save("view.png")                # 8-bit sRGB as composite.png; to_numpy: (H, W, 3)

    stack = lasagna.from_image(albedo)                     # a tensor (C, h, w), numpy array (h, w, C) or PIL image
    stack.add_layer("shade", shading, blend="multiply", range=(0, 2))
    stack.add_solid("tint", (1.0, 0.5, 0.0, 0.25), blend="normal")
    lasagna.export_ora(stack, "out/stack.ora")

    result = lasagna.edit("photo.png", "shading", "left")  # EditResult: stack, layer, composite, settings
    result.save("out/relit")                               # the stack folder `lasagna edit` writes
    report = lasagna.edit_many(["photos/", "more/*.jpg"], "shading", "left", "out/")   # out/<stem>/ each; resumable
    lit = lasagna.edit("photo.png", "relight", "left", source_light="top")   # told its source light: a surface
    lit.stack.set_light(lit.layer_id, "left", source_light="az=120,el=45")   # the source moved: no learning
    lasagna.reread_surface(lit.stack, lit.layer_id)        # the surface read again told the moved light
    (lasagna.editing: edit, render_learned, reread_surface; lasagna.batch: edit_many)

Tensors and float arrays are layer values y (a [0, 2] multiplier is given in [0, 2]); PIL images and
integer arrays are stored codes, mapped by the layer's range like a PNG in a stack folder. Tensors are
channels first (C, h, w); numpy arrays may be either, (h, w, C) as PIL and imageio give them (an array
whose last axis has 1 to 4 entries and whose first has more is read as (h, w, C)). Everything
here is a thin name for a function of ``lasagna.io`` / ``lasagna.export``; see them for details.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from lasagna.batch import BatchReport, edit_many
from lasagna.compose.render import RenderResult
from lasagna.editing import EditResult, edit, render_learned, reread_surface
from lasagna.errors import ImageError
from lasagna.export.ora import export_ora
from lasagna.export.ora_import import import_ora
from lasagna.export.png import export_layer_pngs
from lasagna.io.render import composite_codes, render_stack, write_composite
from lasagna.io.stack import Stack, load_stack, save_stack, stack_from_tensors

__all__ = [
    "Stack",
    "RenderResult",
    "load",
    "render",
    "save",
    "from_image",
    "from_tensors",
    "export_ora",
    "export_psd",
    "import_ora",
    "export_layer_pngs",
    "write_composite",
    "EditResult",
    "edit",
    "render_learned",
    "reread_surface",
    "BatchReport",
    "edit_many",
    "to_pil",
    "to_numpy",
]


def load(path: str | os.PathLike, **limits: Any) -> Stack:
    """Load a stack folder (or its stack.json); ``limits``: ``max_pixels``, ``max_total_pixels``."""
    return load_stack(path, **limits)


def render(stack: Stack | str | os.PathLike, *, dtype: torch.dtype = torch.float32, cull: bool = True) -> RenderResult:
    """Composite a stack (or the stack folder at a path): ``RenderResult(image (3, H, W), skipped, evaluated)``.

    Differentiable: layer tensors that require grad receive gradients through ``result.image``.
    """
    if not isinstance(stack, Stack):
        stack = load_stack(stack)
    return render_stack(stack, dtype=dtype, cull=cull)


def save(stack: Stack, folder: str | os.PathLike | None = None, *, clip: bool = False, composite: bool = False) -> Path:
    """Write the stack folder (stack.json, layer PNGs; ``composite.png`` too if ``composite``).

    Values outside a layer's range are an error unless ``clip``. Returns the stack.json written.
    """
    written = save_stack(stack, folder, clip=clip)
    if composite:
        write_composite(render_stack(stack), written.parent / "composite.png")
    return written


def from_image(image, **kwargs: Any) -> Stack:
    """A new stack whose canvas is ``image``'s size and whose bottom layer is ``image`` (see ``Stack.from_image``)."""
    return Stack.from_image(image, **kwargs)


def from_tensors(layers, **kwargs: Any) -> Stack:
    """A new stack from ``(id, image)`` pairs or layer dicts, bottom first (see ``stack_from_tensors``)."""
    return stack_from_tensors(layers, **kwargs)


def export_psd(stack: Stack, path: str | os.PathLike, **kwargs: Any) -> Path:
    """Write a layered PSD (needs ``pip install 'lasagna-layers[psd]'``)."""
    from lasagna.export.psd import export_psd as _export_psd

    return _export_psd(stack, path, **kwargs)


def to_numpy(image):
    """The composite as (H, W, 3) uint8 sRGB codes — (H, W, 4) for a transparent document's, with its alpha —
    clamped and rounded exactly as ``composite.png`` is (``lasagna.io.render.composite_codes``). ``image``: a
    ``RenderResult``, an ``EditResult``, a ``Stack`` or stack folder (rendered), or a (3, H, W) / (1, H, W)
    tensor of values in [0, 1]."""
    if isinstance(image, (Stack, str, os.PathLike)):
        image = render(image)
    if isinstance(image, EditResult):
        image = image.composite if image.stack.document.canvas.background is not None else image._render()
    alpha = None
    if isinstance(image, RenderResult):
        image, alpha = image.image, image.alpha
    if not isinstance(image, torch.Tensor) or image.ndim != 3 or image.shape[0] not in (1, 3):
        got = tuple(image.shape) if isinstance(image, torch.Tensor) else type(image).__name__
        raise ImageError(
            f"got {got}; expected a RenderResult, EditResult, Stack or (3, H, W) tensor (no batch)", where="to_pil"
        )
    if bool(torch.isnan(image.detach()).any()):
        raise ImageError("the image contains NaN; expected finite values", where="to_pil")
    planes = image.expand(3, *image.shape[-2:])
    if alpha is not None and alpha.ndim == 3:
        planes = torch.cat([planes, alpha])
    return composite_codes(planes).permute(1, 2, 0).contiguous().numpy()


def to_pil(image):
    """The composite as an 8-bit RGB PIL image, RGBA for a transparent document's (``to_numpy``'s codes)."""
    from PIL import Image

    codes = to_numpy(image)
    return Image.fromarray(codes, "RGBA" if codes.shape[2] == 4 else "RGB")
