"""Output places and stack-folder transactions: refuse what cannot be written before any work, and write a
stack folder all or nothing.

``check_writable`` is the one writability check (a file to write, or a folder to write into);
``check_output_folder`` adds a stack folder's rules (new or empty, or replaced as a whole with
``force``). ``write_stack_folder`` writes everything into a temporary sibling folder and renames it
into place (``swap_in``): a failure leaves no half-written stack and the target as it was.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from lasagna.atomic import atomic_write_bytes, umask_mode
from lasagna.errors import PathError
from lasagna.io.render import write_composite
from lasagna.io.stack import Stack, resolve_inside, save_stack


def _check_place(path: Path, where: str) -> None:
    """Refuse ``path`` unless its nearest existing ancestor (itself included) is a writable folder."""
    probe = path
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        raise PathError(f"{probe} is not a writable folder; expected a writable location", where)


def check_writable(path: str | os.PathLike, *, folder: bool = False) -> Path:
    """Refuse an output path that cannot be written, before anything is written: a file path (``folder``
    false) must not be a folder and must lie in a writable place; a folder to write into must not be a
    file and must be writable (or creatable)."""
    path = Path(path)
    if not folder and path.is_dir():
        raise PathError("is a folder; expected a file path to write", str(path))
    if folder and path.exists() and not path.is_dir():
        raise PathError("exists and is not a folder; expected a folder to write into", str(path))
    _check_place(path if folder else path.parent, str(path))
    return path


def check_output_folder(out: str | os.PathLike, *, force: bool = False) -> Path:
    """Refuse an output stack folder that cannot be (re)written, before any work: a file, a non-empty folder
    (unless ``force`` and it holds a stack.json: then it is replaced as a whole), an unwritable place (the
    folder is renamed into its parent, so the parent must be writable)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise PathError("exists and is not a folder; expected a folder to write the stack into", str(out))
    if out.is_dir() and any(out.iterdir()):
        if not force:
            raise PathError(
                "is not empty; expected a new or empty folder (or --force to replace a stack folder)", str(out)
            )
        if not (out / "stack.json").is_file():
            raise PathError("is not empty and holds no stack.json; --force replaces only a stack folder", str(out))
    _check_place(out.parent, str(out))
    return out


def write_stack_folder(
    stack: Stack, out: str | os.PathLike, *, files: dict[str, bytes] | None = None, force: bool = False, result=None
) -> Path:
    """Write ``stack`` as the folder ``out``: stack.json, layers/, masks/, composite.png and ``files``
    (relative path → bytes: generators/, stack.ora, …), all or nothing.

    ``result`` is the stack's ``RenderResult`` when the caller has it (it is rendered otherwise). With
    ``force`` an existing stack folder is replaced (renamed aside, the new one renamed in, the old one
    removed). ``stack.folder`` becomes ``out``.
    """
    out = check_output_folder(out, force=force)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    old_folder = stack.folder
    try:
        save_stack(stack, tmp)
        for rel, data in (files or {}).items():
            atomic_write_bytes(resolve_inside(tmp, rel, rel), data)
        write_composite(result if result is not None else stack.render(), tmp / "composite.png")
        os.chmod(tmp, umask_mode(0o777))  # mkdtemp makes 0700; a folder made by mkdir would not be
        swap_in(tmp, out)
    except BaseException:
        stack.folder = old_folder
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    stack.folder = out
    return out


def swap_in(tmp: Path, out: Path) -> None:
    """Rename ``tmp`` to ``out``; an existing ``out`` (empty, or a stack when forced) is replaced."""
    if not out.exists():
        os.rename(tmp, out)
        return
    if not any(out.iterdir()):
        out.rmdir()
        os.rename(tmp, out)
        return
    aside = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".old", dir=out.parent))
    aside.rmdir()
    os.rename(out, aside)
    try:
        os.rename(tmp, out)
    except BaseException:
        os.rename(aside, out)
        raise
    shutil.rmtree(aside, ignore_errors=True)
