"""Rendering glue between stack folders and the compositor, and writing ``composite.png``.

``render_stack`` compiles the stack's document and tensors with ``compose.plan_from_document`` and
renders it; learned layers that have no pixels yet are reported in ``skipped`` as
"not rendered (run `lasagna render`)" rather than being an error. ``write_composite`` writes the
8-bit sRGB PNG: values clamped to [0, 1] (whatever the document's clamp policy, quantising needs
it) and rounded to nearest, written atomically.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from lasagna.atomic import write_output
from lasagna.compose.plan import plan_from_document
from lasagna.compose.render import RenderResult, render
from lasagna.errors import ImageError
from lasagna.io.png import encode_rgb8_bands
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
    check_memory(
        held + render_bytes(stack.width, stack.height, dtype), f"rendering {stack.width}x{stack.height}", "render"
    )
    plan = plan_from_document(stack.document, stack.tensors, cull=cull, dtype=dtype)
    result = render(plan, dtype=dtype)
    skipped = dict(result.skipped)
    skipped.update(stack.not_rendered)
    order = {id: i for i, id in enumerate(stack.document.all_ids)}
    skipped = dict(sorted(skipped.items(), key=lambda kv: order.get(kv[0], len(order))))
    return RenderResult(result.image, skipped, list(result.evaluated))


# Rows of the canvas turned into codes at a time: 64 rows of an 8192-wide canvas are 12 MiB of float64.
BAND_ROWS = 64


def composite_codes(image: torch.Tensor) -> torch.Tensor:
    """(3, H, W) float → (3, H, W) uint8: clamp to [0, 1], then round half to even at 255·v."""
    return (image.detach().to("cpu", torch.float64).clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)


def _code_bands(image: torch.Tensor, where: str):
    """(rows, W, 3) uint8 bands of ``image`` (3, H, W), top to bottom (``composite_codes`` a band at a
    time, in float64 so the rounding is exact); a NaN anywhere is an error."""
    for y in range(0, image.shape[1], BAND_ROWS):
        band = image[:, y : y + BAND_ROWS].detach().to("cpu", torch.float64)
        if bool(torch.isnan(band).any()):
            raise ImageError("composite contains NaN; expected finite layer values", where=where)
        yield composite_codes(band).permute(1, 2, 0).numpy()


def encode_composite(result: RenderResult | torch.Tensor, where: str = "composite.png") -> bytes:
    """A composite (a ``RenderResult`` or an image (3, H, W)) as 8-bit sRGB PNG bytes, encoded band by band
    (``encode_rgb8_bands``): beside the image only its compressed bytes are held, so a canvas of any size
    costs its float buffer and not three more copies."""
    image = result.image if isinstance(result, RenderResult) else result
    if image.ndim != 3 or image.shape[0] != 3:
        raise ImageError(
            f"composite has shape {tuple(image.shape)}; expected (3, H, W) (render one stack, not a batch)",
            where=where,
        )
    return encode_rgb8_bands(_code_bands(image, where), image.shape[2], image.shape[1])


def write_composite(result: RenderResult | torch.Tensor, path: str | os.PathLike) -> Path:
    """Write a composite (a ``RenderResult`` or an image (3, H, W)) as an 8-bit sRGB PNG, atomically."""
    data = encode_composite(result, str(path))
    return write_output(path, data, ImageError)
