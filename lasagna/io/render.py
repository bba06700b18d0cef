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

from lasagna.compose.plan import plan_from_document
from lasagna.compose.render import RenderResult, render
from lasagna.errors import ImageError
from lasagna.io.png import write_png


def render_stack(stack, dtype: torch.dtype = torch.float32, *, cull: bool = True) -> RenderResult:
    """Composite ``stack`` (a ``lasagna.io.stack.Stack``) into ``RenderResult(image (3, H, W), skipped, evaluated)``.

    Solid layers are built by the plan in ``dtype``, range-mapped like a PNG's values (the document's rule)."""
    plan = plan_from_document(stack.document, stack.tensors, cull=cull, dtype=dtype)
    result = render(plan, dtype=dtype)
    skipped = dict(result.skipped)
    skipped.update(stack.not_rendered)
    order = {id: i for i, id in enumerate(stack.ids)}
    skipped = dict(sorted(skipped.items(), key=lambda kv: order.get(kv[0], len(order))))
    return RenderResult(result.image, skipped, list(result.evaluated))


def composite_codes(image: torch.Tensor) -> torch.Tensor:
    """(3, H, W) float → (3, H, W) uint8: clamp to [0, 1], then round half to even at 255·v."""
    return (image.detach().to("cpu", torch.float64).clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)


def write_composite(result: RenderResult | torch.Tensor, path: str | os.PathLike) -> Path:
    """Write a composite (a ``RenderResult`` or an image (3, H, W)) as an 8-bit sRGB PNG, atomically."""
    image = result.image if isinstance(result, RenderResult) else result
    if image.ndim != 3 or image.shape[0] != 3:
        raise ImageError(
            f"composite has shape {tuple(image.shape)}; expected (3, H, W) (render one stack, not a batch)",
            where=str(path),
        )
    codes = composite_codes(image)
    if bool(torch.isnan(image.detach()).any()):
        raise ImageError("composite contains NaN; expected finite layer values", where=str(path))
    write_png(path, codes.double() / 255.0)
    return Path(path)
