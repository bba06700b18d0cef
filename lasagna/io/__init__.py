"""The I/O tier: PNG read/write (8/16-bit, size limits), atomic files, stack folders, rendering glue.

    atomic.py   atomic_path, atomic_write_bytes, atomic_write_text
    png.py      read_png, decode_png, write_png, encode_png, read_png_header (bomb-safe)
    stack.py    Stack, load_stack, save_stack, stack_from_tensors
    render.py   render_stack, write_composite

Names are imported lazily: the document tier writes through ``lasagna.atomic`` and must not pull
in torch (which ``stack`` and ``render`` need) by importing this package.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "atomic_path": "atomic",
    "atomic_write_bytes": "atomic",
    "atomic_write_text": "atomic",
    "DEFAULT_MAX_PIXELS": "png",
    "PngHeader": "png",
    "PngImage": "png",
    "read_png": "png",
    "decode_png": "png",
    "write_png": "png",
    "encode_png": "png",
    "read_png_header": "png",
    "Stack": "stack",
    "load_stack": "stack",
    "save_stack": "stack",
    "stack_from_tensors": "stack",
    "render_stack": "render",
    "write_composite": "render",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'lasagna.io' has no attribute {name!r}")
    return getattr(importlib.import_module(f"lasagna.io.{module}"), name)
