"""Rendering glue between stack folders and the compositor, and writing ``composite.png``.

``render_stack`` compiles the stack's document and tensors with ``compose.plan_from_document`` and
renders it; learned layers that have no pixels yet are reported in ``skipped`` as
"not rendered (run `lasagna render`)" rather than being an error. ``write_composite`` writes the
sRGB PNG, 8-bit or (``depth=16``) 16-bit: values clamped to [0, 1] (whatever the document's clamp policy,
quantising needs it) and rounded to nearest, band by band, written atomically. A transparent document's
(``canvas.background`` null) composite is RGBA: straight colour and its alpha; any other's is RGB.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from lasagna.atomic import write_output
from lasagna.compose.plan import plan_from_document
from lasagna.compose.render import RenderResult, render
from lasagna.errors import ImageError
from lasagna.io.png import BitDepth, encode_bands
from lasagna.io.survey import RENDER_CHANNELS, composite_bytes  # noqa: F401  (composite_bytes: re-exported)
from lasagna.limits import check_memory


def render_bytes(width: int, height: int, dtype: torch.dtype = torch.float32) -> int:
    """Bytes a no-grad render of a ``width`` × ``height`` canvas allocates (its output)."""
    return width * height * RENDER_CHANNELS * (torch.finfo(dtype).bits // 8)


def tensor_bytes(tensors) -> int:
    """Bytes held by the storages behind ``tensors`` (each storage once; expanded views cost nothing)."""
    seen: dict[int, int] = {}
    for t in tensors:
        if t is not None:
            storage = t.untyped_storage()
            seen[storage.data_ptr()] = storage.nbytes()
    return sum(seen.values())


def render_stack(stack, dtype: torch.dtype = torch.float32, *, cull: bool = True) -> RenderResult:
    """Composite ``stack`` (a ``lasagna.io.stack.Stack``) into ``RenderResult(image (3, H, W), skipped, evaluated)``.

    Solid layers are built by the plan in ``dtype``, range-mapped like a PNG's values (the document's rule).
    The stack's tensors and the output canvas together must fit the memory budget (``lasagna.limits``)."""
    held = tensor_bytes(t for lt in stack.tensors.values() for t in lt.tensors())
    canvas = render_bytes(stack.width, stack.height, dtype)
    if stack.document.canvas.background is None:  # a transparent document's render carries alpha too
        canvas += canvas // RENDER_CHANNELS
    check_memory(held + canvas, f"rendering {stack.width}x{stack.height}", "render")
    plan = plan_from_document(stack.document, stack.tensors, cull=cull, dtype=dtype)
    result = render(plan, dtype=dtype)
    skipped = dict(result.skipped)
    skipped.update(stack.not_rendered)
    order = {id: i for i, id in enumerate(stack.document.all_ids)}
    skipped = dict(sorted(skipped.items(), key=lambda kv: order.get(kv[0], len(order))))
    return RenderResult(result.image, skipped, list(result.evaluated), result.alpha)


# Rows of the canvas turned into codes at a time: 64 rows of an 8192-wide canvas are 12 MiB of float64.
BAND_ROWS = 64
COMPOSITE_DEPTHS = (8, 16)


def composite_codes(image: torch.Tensor) -> torch.Tensor:
    """(3, H, W) float → (3, H, W) uint8: clamp to [0, 1], then round half to even at 255·v."""
    return (image.detach().to("cpu", torch.float64).clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)


def _code_bands(image: torch.Tensor, alpha: torch.Tensor | None, depth: BitDepth, where: str):
    """(rows, W, 3 or 4) bands of ``image`` (3, H, W) and ``alpha`` (1, H, W) as ``depth``-bit codes, top to
    bottom: clamped to [0, 1], rounded half to even at (2^depth − 1)·v in float64 (exact); a NaN is an error."""
    planes = image if alpha is None else torch.cat([image, alpha])  # (C, H, W): only a transparent render has alpha
    scale, kind = (65535.0, torch.int32) if depth == 16 else (255.0, torch.uint8)
    for y in range(0, image.shape[1], BAND_ROWS):
        band = planes[:, y : y + BAND_ROWS].detach().to("cpu", torch.float64)
        if bool(torch.isnan(band).any()):
            raise ImageError("composite contains NaN; expected finite layer values", where=where)
        codes = (band.clamp(0.0, 1.0) * scale).round().to(kind).permute(1, 2, 0).numpy()
        yield codes.astype("uint16") if depth == 16 else codes


def composite_hwc(result: RenderResult | torch.Tensor, depth: BitDepth = 8) -> np.ndarray:
    """(H, W, 3 or 4) codes of a composite (RGBA for a transparent document's), uint8 or uint16 for ``depth`` 16,
    filled a band at a time (no float copy of the canvas)."""
    image = result.image if isinstance(result, RenderResult) else result
    alpha = result.alpha if isinstance(result, RenderResult) else None
    H, W = image.shape[-2:]
    out = np.empty((H, W, 3 if alpha is None else 4), dtype=np.uint16 if depth == 16 else np.uint8)
    for y, band in zip(range(0, H, BAND_ROWS), _code_bands(image, alpha, depth, "composite")):
        out[y : y + band.shape[0]] = band
    return out


def check_depth(depth: object, where: str = "--depth") -> None:
    """A composite's bit depth must be 8 or 16 (one line otherwise)."""
    if depth not in COMPOSITE_DEPTHS:
        raise ImageError(f"bit depth {depth!r}; expected 8 or 16", where=where)


def encode_composite(
    result: RenderResult | torch.Tensor, where: str = "composite.png", *, depth: BitDepth = 8
) -> bytes:
    """A composite (a ``RenderResult`` or an image (3, H, W)) as sRGB PNG bytes, ``depth`` 8 or 16 bits a sample,
    RGBA when the result has alpha (a transparent document), encoded band by band (``encode_bands``): beside the
    image only its compressed bytes are held, so a canvas of any size costs its float buffer and no more copies."""
    check_depth(depth, where)
    image = result.image if isinstance(result, RenderResult) else result
    alpha = result.alpha if isinstance(result, RenderResult) else None
    if image.ndim != 3 or image.shape[0] != 3:
        raise ImageError(
            f"composite has shape {tuple(image.shape)}; expected (3, H, W) (render one stack, not a batch)",
            where=where,
        )
    bands = _code_bands(image, alpha, depth, where)
    return encode_bands(bands, image.shape[2], image.shape[1], bit_depth=depth, srgb=True)


def write_composite(result: RenderResult | torch.Tensor, path: str | os.PathLike, *, depth: BitDepth = 8) -> Path:
    """Write a composite (a ``RenderResult`` or an image (3, H, W)) as an sRGB PNG of ``depth`` bits (RGBA for a
    transparent document's), atomically."""
    data = encode_composite(result, str(path), depth=depth)
    return write_output(path, data, ImageError)
