"""``lasagna serve``: the layer editor in the browser (needs ``pip install 'lasagna-layers[serve]'``).

``open_target(path)`` turns what the user named into a stack folder (an image gets a new stack folder
beside it), ``EditSession`` (``session``) is the open stack, ``create_app`` (``app``) its HTTP face,
and ``serve`` runs it on uvicorn until Ctrl-C. The page (``static/``) is plain HTML, CSS and JavaScript
shipped in the package: it works offline and needs no build step.
"""

from __future__ import annotations

import os
import secrets
import socket
from collections.abc import Callable
from pathlib import Path

from lasagna.errors import PathError
from lasagna.io.image import DEFAULT_EDIT_MAX_PIXELS

LOOPBACK = ("127.0.0.1", "localhost", "::1")
LAYERED = (".ora", ".psd")
"""Layered files ``lasagna serve`` opens by importing them (`lasagna.export`), as ``import-ora`` / ``import-psd``
would: their layers, groups and modes, a surface layer made one again."""
STACK_SUFFIX = ".stack"
"""An image ``photo.jpg`` opened by ``lasagna serve`` becomes the stack folder ``photo.stack/`` beside it."""


def _target(p: Path) -> tuple[Path, bool]:
    """(the stack folder ``p`` names, whether it is still to be made from the image ``p``): a stack folder (or its
    stack.json) is itself; an image file's (or an OpenRaster or PSD file's) folder is ``<stem>.stack/`` beside it."""
    if p.is_dir() or p.suffix.lower() == ".json":
        folder = p if p.is_dir() else p.parent
        if not (folder / "stack.json").is_file():
            raise PathError("holds no stack.json; expected a stack folder or an image file", str(folder))
        return folder, False
    if not p.is_file():
        raise PathError(
            "does not exist; expected a stack folder, an image file (PNG, JPEG, …) or a layered file (ORA, PSD)", str(p)
        )
    folder = p.with_name(p.stem + STACK_SUFFIX)
    return folder, not (folder / "stack.json").is_file()


def survey_target(path: str | os.PathLike, *, max_pixels: int = DEFAULT_EDIT_MAX_PIXELS) -> None:
    """``open_target``'s and the session's refusals, read-only and without torch (``lasagna serve`` runs it before
    the editor's imports): no stack and no image there, a stack that would not load (its document, sizes against
    ``max_pixels`` and memory, as the session's ``load_stack`` surveys them), an image that would not decode (its
    header)."""
    from lasagna.io.image import probe_image_file
    from lasagna.io.survey import survey_stack

    folder, make = _target(Path(path))
    if make and Path(path).suffix.lower() in LAYERED:
        _probe_layered(Path(path))
    elif make:
        probe_image_file(path, max_pixels=max_pixels)
    else:
        survey_stack(folder, max_pixels=max_pixels)


def _probe_layered(p: Path) -> None:
    """An OpenRaster file is a zip archive, a PSD starts "8BPS": one line for a file that is neither (its layers are
    read, and refused in one line, by the import itself)."""
    import zipfile

    if p.suffix.lower() == ".ora" and not zipfile.is_zipfile(p):
        raise PathError("is not a zip archive; expected an OpenRaster file", str(p))
    if p.suffix.lower() == ".psd":
        with open(p, "rb") as f:
            if f.read(4) != b"8BPS":
                raise PathError("does not start with 8BPS; expected a Photoshop file", str(p))


def open_target(
    path: str | os.PathLike,
    *,
    max_pixels: int = DEFAULT_EDIT_MAX_PIXELS,
    warn: Callable[[str], None] | None = None,
) -> tuple[Path, bool]:
    """The stack folder for ``path`` and whether it was made now: a stack folder (or its stack.json) is
    itself; an image file gets ``<stem>.stack/`` beside it, made with the image as its base layer — an OpenRaster
    or PSD file (``LAYERED``) with its layers, imported (``warn``: one line per thing the import could not keep) —
    or opened again if an earlier ``serve`` made it."""
    p = Path(path)
    folder, make = _target(p)
    if not make:
        return folder, False
    from lasagna.io.folder import write_stack_folder

    if p.suffix.lower() == ".ora":
        from lasagna.export.ora_import import import_ora

        stack = import_ora(p, max_pixels=max_pixels, warn=warn)
    elif p.suffix.lower() == ".psd":
        from lasagna.export.psd_import import read_psd

        stack = read_psd(p, max_pixels=max_pixels, warn=warn)
    else:
        from lasagna.editing import read_image

        stack = read_image(p, max_pixels)
    write_stack_folder(stack, folder)
    return folder, True


def free_port(host: str) -> int:
    """A port the OS says is free on ``host`` (bound and released: a tiny race, as every such helper has)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def allowed_hosts(host: str, port: int) -> list[str]:
    """Host header values naming this server: the bound address and, on loopback, every loopback name."""
    names = {host, *LOOPBACK} if host in LOOPBACK or host == "0.0.0.0" else {host}
    return sorted(f"[{n}]:{port}" if ":" in n else f"{n}:{port}" for n in names)


def new_token() -> str:
    """The access token: 24 random bytes, URL-safe (as Jupyter's)."""
    return secrets.token_urlsafe(24)


__all__ = ["STACK_SUFFIX", "allowed_hosts", "free_port", "new_token", "open_target"]
