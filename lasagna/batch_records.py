"""A batch's inputs, output names and records (``lasagna.batch.edit_many`` runs them).

**Inputs** (``collect_inputs``): a file, a stack folder (a folder holding stack.json, or its stack.json:
the layer goes on top of it, as ``edit`` does), a folder that is not a stack folder (its image files and
the stack folders directly inside it), or a glob pattern (``glob.glob(recursive=True)``: ``**`` crosses
folders; its matches filtered to image files and stack folders). A folder or pattern that finds nothing
is refused before any work. Path inputs are sorted and de-duplicated; in-memory images (tensors, arrays,
PIL images, ``Stack``) keep their order and come after them.

**Names and records**: ``out_dir/<name>/`` per input. Each stack folder records, in its stack.json's
metadata (``BATCH_KEY``), the source it was made from — its path relative to its **batch root** (the folder
given, a pattern's fixed leading folder, a file's own folder), size and SHA-256 (``source_record``) — and
what was asked (preset, condition and the settings that change the layer: ``request_record``). Names are
matched to sources, never to sort positions (``assign_names``): an existing folder is claimed by the input
whose path it records, so one input keeps its folder across runs whatever is added beside it; the other
inputs take their stem (a stack folder's name), made unique in input order without regard to case
(``a.png``, ``a.jpg`` → ``a``, ``a-2``) and skipping every name already in ``out_dir`` (a folder of another
source, or one without a record, is never touched). In-memory images are ``image-1``, ``image-2``, … A
complete output's record decides (``compare_record``) whether it is skipped (same source bytes, same
request), redone in place (its source changed) or refused (asked with other settings, or no record).
"""

from __future__ import annotations

import glob
import hashlib
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from lasagna.atomic import open_regular
from lasagna.document import STACK_FILE
from lasagna.errors import LasagnaError, PathError
from lasagna.request import EditRequest

# The image files a folder or a glob contributes (``lasagna.io.image`` reads these; nothing else is opened).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".webp", ".bmp", ".tif", ".tiff")

# The stack.json metadata key of a batch output's record: its source and what was asked (module docstring).
BATCH_KEY = "lasagna.batch"


# ---- inputs and names -------------------------------------------------------------------------------


def _is_image(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES


def _is_stack(path: Path) -> bool:
    return path.is_dir() and (path / STACK_FILE).is_file()


def _found(paths, where: str, what: str) -> list[Path]:
    found = [p for p in paths if _is_image(p) or _is_stack(p)]
    if not found:
        raise PathError(f"{what} no image file or stack folder; expected at least one", where)
    return found


def collect_inputs(items: Sequence[Any] | Any) -> list[Any]:
    """The inputs ``items`` name (module docstring): paths sorted and de-duplicated, then in-memory images."""
    return collect_with_roots(items)[0]


def _pattern_root(pattern: str) -> Path:
    """A glob pattern's fixed leading folder: ``photos/**/*.png`` → ``photos``."""
    parts = Path(pattern).parts
    fixed = parts[: next(i for i, part in enumerate(parts) if glob.has_magic(part))]
    return Path(*fixed) if fixed else Path(".")


def collect_with_roots(items: Sequence[Any] | Any) -> tuple[list[Any], list[Path | None]]:
    """``collect_inputs``'s list, and each path input's batch root (module docstring; None for an image)."""
    if isinstance(items, (str, os.PathLike)) or not isinstance(items, Sequence):
        items = [items]
    paths: dict[str, tuple[Path, Path]] = {}
    images: list[Any] = []
    for item in items:
        if not isinstance(item, (str, os.PathLike)):
            images.append(item)
            continue
        text = os.fspath(item)
        p = Path(text)
        if p.exists() or os.path.lexists(p):
            listed = p.is_dir() and not _is_stack(p)
            found = _found(sorted(p.iterdir()), text, "holds") if listed else [p]
            root = p if listed else _folder_of(p).parent
        elif glob.has_magic(text):
            found = _found((Path(m) for m in sorted(glob.glob(text, recursive=True))), text, "matches")
            root = _pattern_root(text)
        else:
            found, root = [p], p.parent  # reported as missing, with the others written
        for f in found:
            paths.setdefault(os.path.normpath(os.path.abspath(f)), (f, root))
    keys = sorted(paths)
    return [paths[k][0] for k in keys] + images, [paths[k][1] for k in keys] + [None] * len(images)


def _folder_of(p: Path) -> Path:
    """A stack input's folder (``p`` itself for a folder or an image file's path)."""
    return p.parent if p.name == STACK_FILE else p


def _relative(item: Path, root: Path) -> str:
    """``item``'s path relative to its batch root, with '/' (what a record keeps)."""
    return Path(os.path.relpath(os.path.abspath(_folder_of(item)), os.path.abspath(root))).as_posix()


def source_record(item: Path, root: Path) -> dict[str, Any]:
    """What a batch output records of its source: path relative to the batch root, size and SHA-256 of the
    image file (of a stack folder's stack.json). Read through ``open_regular``: a FIFO is one line."""
    p = Path(item)
    file = p / STACK_FILE if p.is_dir() else p
    digest, size = hashlib.sha256(), 0
    with open_regular(file, str(p), expected="an image file or a stack folder") as fh:
        while chunk := fh.read(1 << 20):
            digest.update(chunk)
            size += len(chunk)
    return {"path": _relative(p, root), "size": size, "sha256": digest.hexdigest()}


def read_record(folder: Path) -> dict[str, Any] | None:
    """The batch record in ``folder``'s stack.json (``BATCH_KEY``), or None (none, or not readable)."""
    from lasagna.document.validation import parse_json, read_json_text

    try:
        doc = parse_json(read_json_text(folder / STACK_FILE, "stack.json"), str(folder / STACK_FILE))
    except (LasagnaError, OSError, RecursionError):
        return None
    meta = doc.get("metadata") if isinstance(doc, dict) else None
    record = meta.get(BATCH_KEY) if isinstance(meta, dict) else None
    return record if isinstance(record, dict) else None


def _recorded_path(record: dict[str, Any] | None) -> str | None:
    source = record.get("source") if record else None
    path = source.get("path") if isinstance(source, dict) else None
    return path if isinstance(path, str) else None


def assign_names(inputs: Sequence[Any], roots: Sequence[Path | None], out_dir: Path) -> list[str]:
    """One folder name per input, stable across runs (module docstring): each existing folder of ``out_dir``
    is claimed by the input whose path (relative to its root) it records — among several inputs of that
    path, the one whose bytes it records, else the first — then the others get ``output_names``' names,
    skipping every name already in ``out_dir`` (but empty folders)."""
    rels = {i: _relative(Path(x), r) for i, (x, r) in enumerate(zip(inputs, roots)) if r is not None}
    by_rel: dict[str, list[int]] = {}
    for i, rel in rels.items():
        by_rel.setdefault(rel, []).append(i)
    claimed: dict[int, str] = {}
    taken: set[str] = set()
    unsourced: dict[str, str] = {}  # casefolded name → folder made from an in-memory image (its record says so)
    entries = sorted(os.scandir(out_dir), key=lambda e: e.name) if out_dir.is_dir() else []
    for entry in entries:
        if entry.name.startswith("."):
            continue  # temporaries (swept) and hidden files are no one's output
        folder = Path(entry.path)
        if not (entry.is_dir(follow_symlinks=False) and not any(folder.iterdir())):
            taken.add(entry.name.casefold())  # a name in use: never given to another source
        record = read_record(folder) if entry.is_dir(follow_symlinks=False) else None
        if record is not None and record.get("source") is None:
            unsourced[entry.name.casefold()] = entry.name
        candidates = [i for i in by_rel.get(_recorded_path(record) or "", []) if i not in claimed]
        if len(candidates) > 1:  # one relative path under several roots: the bytes decide
            want = record["source"] if record else None
            same = [i for i in candidates if _same_source(inputs[i], roots[i], want)]
            candidates = same or candidates
        if candidates:
            claimed[candidates[0]] = entry.name
    positional = output_names(inputs)  # an in-memory image has only its position: image-<k>
    for i, root in enumerate(roots):
        if root is None and positional[i].casefold() in unsourced:
            claimed[i] = unsourced[positional[i].casefold()]
    return output_names(inputs, claimed=claimed, taken=taken)


def _same_source(item: Any, root: Path | None, want: Any) -> bool:
    try:
        return root is not None and source_record(Path(item), root) == want
    except (LasagnaError, OSError):
        return False


def output_names(
    inputs: Sequence[Any], *, claimed: dict[int, str] | None = None, taken: set[str] | None = None
) -> list[str]:
    """One folder name per input: a file's stem, a stack folder's name (a stack.json's folder's), else
    ``image-<k>``; made unique in order, case-insensitively, by ``-2``, ``-3``, … ``claimed``: inputs whose
    name is already decided (index → name); ``taken``: casefolded names no other input may get."""
    claimed = claimed or {}
    names: list[str] = []
    taken = set(taken or ()) | {name.casefold() for name in claimed.values()}
    width = len(str(len(inputs)))
    for k, item in enumerate(inputs):
        if k in claimed:
            names.append(claimed[k])
            continue
        if isinstance(item, (str, os.PathLike)):
            p = Path(item)
            stem = p.parent.resolve().name if p.name == STACK_FILE else (p.resolve().name if p.is_dir() else p.stem)
        else:
            stem = f"image-{k + 1:0{width}d}"
        stem = stem or "image"
        name, n = stem, 2
        while name.casefold() in taken:
            name, n = f"{stem}-{n}", n + 1
        taken.add(name.casefold())
        names.append(name)
    return names


# ---- records ------------------------------------------------------------------------------------------


def request_record(request: EditRequest) -> dict[str, Any]:
    """What was asked, as an output records it: the preset, the condition and the settings that change the
    layer (those given), as JSON values."""
    r = request
    asked = {"preset": r.preset, "condition": r.condition, "on": r.on, "id": r.id, "generator": r.generator}
    asked.update(optimize=r.asked_steps, loss=r.loss, guidance=r.guidance, seed=r.seed, lr=r.lr)
    return json.loads(json.dumps({k: v for k, v in asked.items() if v is not None}))


def source_or_none(item: Any, root: Path | None) -> dict[str, Any] | None:
    """``source_record`` of a path input; None for an in-memory image, or a path that cannot be read as a file
    (missing, a folder without stack.json: ``plan_edit`` says why, in its words). A FIFO, a device: refused."""
    if root is None:
        return None
    try:
        return source_record(Path(item), root)
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
        return None


def compare_record(old: dict[str, Any] | None, new: dict[str, Any], out: Path) -> str | None:
    """Whether a complete output may be skipped (None), is to be redone (the reason, for ``Outcome.note``: its
    source changed), or is refused (a ``LasagnaError``: made with other settings, or not by a batch)."""
    if old is None:
        raise PathError(
            "holds a stack folder without a batch record (written by hand or by an older lasagna); expected a "
            "folder this batch wrote (--force to replace it, or another OUTDIR)",
            str(out),
        )
    before = old.get("request") if isinstance(old.get("request"), dict) else {}
    differ = [k for k in sorted(set(before) | set(new["request"])) if before.get(k) != new["request"].get(k)]
    if differ:

        def shown(value: Any) -> str:
            return "(default)" if value is None else repr(value)

        now = new["request"]
        was = ", ".join(f"{k} {shown(before.get(k))} (asked now: {shown(now.get(k))})" for k in differ)
        raise PathError(
            f"was made with {was}; expected the same request to resume (--force redoes it, or another OUTDIR)",
            str(out),
        )
    if old.get("source") != new["source"] and new["source"] is not None:
        return "redone: its source changed since this output was made"
    return None


def with_record(result, record: dict[str, Any]):
    """``result`` with ``record`` in its stack.json's metadata (``BATCH_KEY``)."""
    doc = result.stack.document
    result.stack.document = doc.replace(metadata={**dict(doc.metadata), BATCH_KEY: record})
    return result


__all__ = [
    "BATCH_KEY",
    "IMAGE_SUFFIXES",
    "assign_names",
    "collect_inputs",
    "collect_with_roots",
    "compare_record",
    "output_names",
    "read_record",
    "request_record",
    "source_or_none",
    "source_record",
    "with_record",
]
