"""Shared documents for the document-tier tests: one valid stack and helpers to break it."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
DELETE = object()  # patch value meaning "remove this key"


def valid_stack() -> dict[str, Any]:
    """The example of docs/ARCHITECTURE.md (all three kinds), as parsed JSON."""
    return {
        "format": "lasagna.stack",
        "version": 1,
        "canvas": {"width": 64, "height": 48, "background": [0.0, 0.0, 0.0]},
        "blend_space": "srgb",
        "clamp": "layer",
        "layers": [
            {"id": "base", "name": "Albedo", "kind": "pixels", "source": "layers/base.png"},
            {
                "id": "shade",
                "name": "Shading",
                "kind": "pixels",
                "source": "layers/shade.png",
                "blend": "multiply",
                "range": [0.0, 2.0],
                "opacity": 1.0,
                "visible": True,
                "offset": {"x": 0, "y": 0},
                "mask": None,
            },
            {
                "id": "tint",
                "kind": "solid",
                "color": [1.0, 0.5, 0.0, 0.25],
                "blend": "normal",
                "size": {"width": 16, "height": 16},
                "offset": {"x": 8, "y": 8},
            },
            {
                "id": "relit",
                "kind": "learned",
                "preset": "shading",
                "condition": {"label": "left"},
                "conditioned_on": "base",
                "blend": "multiply",
                "range": [0.0, 2.0],
                "source": "layers/relit.png",
                "generator": {"checkpoint": "layers/shading/generator.safetensors"},
                "settings": {},
            },
        ],
        "metadata": {},
    }


def patched(doc: dict[str, Any], path: str, value: Any) -> dict[str, Any]:
    """A deep copy of ``doc`` with the dotted ``path`` ("layers.1.blend") set to ``value`` (or deleted)."""
    out = copy.deepcopy(doc)
    *parents, last = [int(p) if p.lstrip("-").isdigit() else p for p in path.split(".")]
    node: Any = out
    for part in parents:
        node = node[part]
    if value is DELETE:
        del node[last]
    else:
        node[last] = copy.deepcopy(value)
    return out


def load_json(path: Path) -> Any:
    return json.loads(path.read_text(encoding="utf-8"))
