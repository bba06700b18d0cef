"""The I/O tier: files on disk — PNGs, stack folders and their all-or-nothing writes, network checkpoints.

    png.py         read_png, decode_png, write_png, encode_png, read_png_header (bomb-safe)
    stack.py       Stack, load_stack, save_stack, stack_from_tensors
    render.py      render_stack, write_composite (the glue to the compositor)
    folder.py      check_writable (the one writability check), check_output_folder, write_stack_folder,
                   check_not_input (no output onto the input stack's own files)
    checkpoint.py  networks (model.safetensors + config.json, ``Pretrained``) and training checkpoints

Atomic writes, temporary names and the sweep of a killed writer's temporaries are the ground floor's
(``lasagna.atomic``), so that the document tier uses them too. The tier keeps the name ``io``; the
document's JSON files are ``lasagna.document.files``. Names are imported lazily: ``import lasagna.io``
alone loads nothing.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
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
    "check_writable": "folder",
    "check_output_folder": "folder",
    "write_stack_folder": "folder",
    "check_not_input": "folder",
    "Pretrained": "checkpoint",
    "save_tensors": "checkpoint",
    "load_tensors": "checkpoint",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'lasagna.io' has no attribute {name!r}")
    return getattr(importlib.import_module(f"lasagna.io.{module}"), name)
