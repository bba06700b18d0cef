"""Loading and saving ``stack.json``: one-line errors on the way in, atomic writes on the way out.

Only the document is read here; the PNGs a document names are the I/O tier's (``lasagna.io``).
"""

from __future__ import annotations

import os
from pathlib import Path

from lasagna.atomic import atomic_write_text
from lasagna.document.models import Document
from lasagna.document.validation import format_validation_error, read_json_text
from lasagna.errors import DocumentError

__all__ = ["STACK_FILE", "stack_file", "load_document", "save_document", "format_validation_error"]

STACK_FILE = "stack.json"


def stack_file(path: str | os.PathLike) -> Path:
    """``path`` if it names a ``.json`` file, else ``path/stack.json`` (a stack folder)."""
    p = Path(path)
    return p if p.suffix.lower() == ".json" and not p.is_dir() else p / STACK_FILE


def load_document(path: str | os.PathLike) -> Document:
    """Read and validate a stack folder's ``stack.json`` (``path`` is the folder or the file).

    Every problem is a one-line ``DocumentError`` naming the file and, for a broken rule, the JSON
    path of the first error (``…/stack.json: layers[2].blend: unknown blend 'mutiply'; …``).
    """
    file = stack_file(path)
    if not file.exists():
        raise DocumentError(
            f"not found; expected a stack folder containing {STACK_FILE}, or the file itself", str(file)
        )
    text = read_json_text(file, f"a {STACK_FILE}")
    return Document.from_json(text, str(file))


def save_document(doc: Document, path: str | os.PathLike) -> Path:
    """Write ``doc`` to ``path`` (a stack folder, created if needed, or a ``.json`` file) atomically.

    Returns the file written. The text is ``doc.to_json()``: full, canonical and stable.
    """
    file = stack_file(path)
    atomic_write_text(file, doc.to_json())
    return file
