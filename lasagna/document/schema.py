"""JSON Schemas (draft 2020-12) of ``stack.json`` and ``preset.json``, generated from the models.

The committed files in ``schemas/`` are this module's output (``write_schemas("schemas")``, run by
``make schemas``); a test regenerates them and fails on any drift. The schemas describe *input*:
they accept blend aliases, and express every rule JSON Schema can (types, bounds, patterns, the
range-only-for-multiply/plus rule); cross-field rules such as unique ids or ``lo < hi`` are the
models' alone.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from lasagna.document.models import Document
from lasagna.document.preset import Preset

SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"
SCHEMA_BASE = "https://lasagna.dev/schemas/"

_SCHEMAS: dict[str, tuple[type[BaseModel], str, str]] = {
    "stack.schema.json": (
        Document,
        "Lasagna layer stack",
        "A stack folder's stack.json (format lasagna.stack, version 1).",
    ),
    "preset.schema.json": (
        Preset,
        "Lasagna learned-layer preset",
        "A learned-layer preset, layers/<name>/preset.json (version 1).",
    ),
}


def _schema(model: type[BaseModel], file: str, title: str, description: str) -> dict[str, Any]:
    body = model.model_json_schema(mode="validation")
    body.update(title=title, description=description)
    return {"$schema": SCHEMA_DIALECT, "$id": SCHEMA_BASE + file, **body}


def schemas() -> dict[str, dict[str, Any]]:
    """File name → JSON Schema, for every document format Lasagna reads."""
    return {file: _schema(model, file, title, desc) for file, (model, title, desc) in _SCHEMAS.items()}


def schema_text(schema: dict[str, Any]) -> str:
    """The committed text of a schema: sorted keys, 2-space indent, trailing newline."""
    return json.dumps(schema, indent=2, sort_keys=True, ensure_ascii=False) + "\n"


def write_schemas(out_dir: str | os.PathLike) -> list[Path]:
    """Write every schema into ``out_dir`` atomically; return the files written."""
    from lasagna.atomic import atomic_write_text  # the I/O tier, imported only when writing

    written = []
    for file, schema in schemas().items():
        path = Path(out_dir) / file
        atomic_write_text(path, schema_text(schema))
        written.append(path)
    return written
