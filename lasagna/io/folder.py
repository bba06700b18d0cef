"""Output places and stack-folder transactions: refuse what cannot be written before any work, and write a
stack folder all or nothing.

``check_writable`` is the one writability check (a file to write, or a folder to write into);
``check_output_folder`` adds a stack folder's rules (new or empty, or replaced as a whole with
``force``). ``write_stack_folder`` writes everything into a temporary sibling folder and renames it
into place (``swap_in``, which checks the rule again under a lock, so two writers racing for one folder
cannot both win): a failure leaves no half-written stack and the target as it was. ``stage_stack_folder``
is its first half, for a writer of many folders that makes them durable together before renaming them
(``lasagna.batch``); its ``SharedFiles`` writes a large file many of those folders carry byte for byte (a
generator's weights) once and hard-links it into each. ``check_not_input`` refuses an output that is one
of the input stack's own files.
"""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lasagna.atomic import (
    atomic_write_all,
    atomic_write_bytes,
    folder_lock,
    make_temp_folder,
    private_folder,
    sweep_stale,
    temp_path,
    umask_mode,
)
from lasagna.document import STACK_FILE, stack_file
from lasagna.errors import ConflictError, LasagnaError, PathError
from lasagna.io.survey import entry_inside, resolve_inside

if TYPE_CHECKING:
    from lasagna.io.stack import Stack


def _check_place(path: Path, where: str) -> None:
    """Refuse ``path`` unless its nearest existing ancestor (itself included) is a writable folder."""
    probe = path
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        raise PathError(f"{probe} is not a writable folder; expected a writable location", where)


def check_writable(path: str | os.PathLike, *, folder: bool = False) -> Path:
    """Refuse an output path that cannot be written, before anything is written: a file path (``folder``
    false) must not be a folder and must lie in an existing writable folder; a folder to write into must not be a
    file and must be writable (or creatable)."""
    path = Path(path)
    if not folder and path.is_dir():
        raise PathError("is a folder; expected a file path to write", str(path))
    if folder and path.exists() and not path.is_dir():
        raise PathError("exists and is not a folder; expected a folder to write into", str(path))
    if not folder and not path.parent.exists():  # a mistyped folder is refused, not created
        raise PathError(f"folder {path.parent} does not exist; expected a file in an existing folder", str(path))
    _check_place(path if folder else path.parent, str(path))
    return path


def input_files(stack: Stack) -> dict[Path, str]:
    """The files ``stack`` was read from (resolved path → what it is): its stack.json and every file the
    document names (layer sources, masks, generator checkpoints). Empty for a stack not from a folder."""
    if stack.folder is None:
        return {}
    folder = Path(stack.folder)
    found = {(folder / STACK_FILE).resolve(): "the input document"}
    for loc, layer in stack.document.walk():
        generator = getattr(layer, "generator", None)
        refs = [
            ("source", getattr(layer, "source", None)),
            ("mask", getattr(layer, "mask", None)),
            ("generator.checkpoint", generator.checkpoint if generator is not None else None),
        ]
        for field, rel in refs:
            if rel:
                found[(folder / rel).resolve()] = f"{loc}.{field} of the input"
    return found


def check_not_input(outputs, stack: Stack) -> None:
    """Refuse writing any of ``outputs`` onto ``stack``'s own files (``input_files``): the input would be
    overwritten by what was rendered from it. The stack's composite.png is no input and may be rewritten."""
    inputs = input_files(stack)
    for out in outputs:
        out = Path(out)
        what = inputs.get(out.resolve())
        if what is None and out.exists():
            what = next((w for p, w in inputs.items() if p.exists() and os.path.samefile(p, out)), None)
        if what is not None:
            raise PathError(f"is {what}; expected an output path that is not one of the stack's files", str(out))


def check_output_folder(out: str | os.PathLike, *, force: bool = False) -> Path:
    """Refuse an output stack folder that cannot be (re)written, before any work: a file, a symbolic link (the
    new folder is renamed into place, which would replace the link rather than fill the folder it points to),
    a non-empty folder (unless ``force`` and it holds a stack.json: then it is replaced as a whole), an
    unwritable place (the folder is renamed into its parent, so the parent must be writable)."""
    out = Path(out)
    if out.is_symlink():
        raise PathError(
            f"is a symbolic link (to {os.readlink(out)}); expected a real folder or a new name "
            "(give the link's target instead)",
            str(out),
        )
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


# Files at least this large that many stack folders of one batch carry byte for byte (a generator's 2 MB
# weights) are written once and hard-linked into each: writing 2 MB per 64² stack folder was a fifth of an
# amortised batch edit's time (``benchmarks/batch.py``). Smaller files cost less to write than to hash.
SHARE_MIN_BYTES = 64 * 1024


class SharedFiles:
    """A batch's store of large identical files, hard-linked into the stack folders it stages.

    The store is a hidden temporary folder in ``folder`` (the batch's OUTDIR: the same file system as the
    stack folders, so a link is possible; swept like any temporary when its process dies) holding each
    distinct content once, named by its SHA-256. ``place`` links it to a destination; ``close`` removes the
    store, and the stack folders keep their links: each stays a whole, self-contained folder (copy or move
    it anywhere), its large files sharing disk blocks with its batch siblings'. Lasagna never writes into a
    file in place (every write is a new file renamed over the old), so a later ``lasagna render`` of one
    folder cannot change another's. Where the file system refuses hard links (FAT, some network mounts)
    ``place`` declines and the caller writes the bytes as before.
    """

    def __init__(self, folder: str | os.PathLike) -> None:
        self.folder = Path(folder)
        self.enabled = True
        self._store: Path | None = None
        self._digests: dict[int, tuple[bytes, str]] = {}  # id(data) → (data kept alive, its SHA-256)
        self._files: dict[str, Path] = {}  # SHA-256 → the store's file

    def place(self, data: bytes, dst: Path) -> bool:
        """Hard-link a stored copy of ``data`` as the new file ``dst``; False (nothing done) for small
        data, or where links fail, and the caller writes ``data`` itself."""
        if not self.enabled or len(data) < SHARE_MIN_BYTES:
            return False
        known = self._digests.get(id(data))
        if known is None or known[0] is not data:
            known = (data, hashlib.sha256(data).hexdigest())
            self._digests[id(data)] = known
        digest = known[1]
        try:
            src = self._files.get(digest)
            if src is None:
                if self._store is None:
                    self._store = make_temp_folder(self.folder / "shared")
                src = self._store / digest
                atomic_write_bytes(src, data)
                self._files[digest] = src
            dst.parent.mkdir(parents=True, exist_ok=True)
            os.link(src, dst)
        except OSError:
            self.enabled = False  # the file system takes no links (or the store cannot be written): write copies
            return False
        return True

    def close(self) -> None:
        """Remove the store (the linked stack folders keep their files)."""
        if self._store is not None:
            shutil.rmtree(self._store, ignore_errors=True)
        self._store = None
        self._files.clear()
        self._digests.clear()


def write_stack_folder(
    stack: Stack,
    out: str | os.PathLike,
    *,
    files: dict[str, bytes] | None = None,
    force: bool = False,
    result=None,
    composite_png: bytes | None = None,
) -> Path:
    """Write ``stack`` as the folder ``out``: stack.json, layers/, masks/, composite.png and ``files``
    (relative path → bytes: generators/, stack.ora, …), all or nothing.

    ``result`` is the stack's ``RenderResult`` when the caller has it (it is rendered otherwise). With
    ``force`` an existing stack folder is replaced (renamed aside, the new one renamed in, the old one
    removed). ``stack.folder`` becomes ``out``.
    """
    out = Path(out)
    old_folder = stack.folder
    tmp = stage_stack_folder(stack, out, files=files, force=force, result=result, composite_png=composite_png)
    try:
        swap_in(tmp, out, force=force)
    except BaseException:
        stack.folder = old_folder
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    stack.folder = out
    return out


def stage_stack_folder(
    stack: Stack,
    out: str | os.PathLike,
    *,
    files: dict[str, bytes] | None = None,
    force: bool = False,
    result=None,
    composite_png: bytes | None = None,
    shared: SharedFiles | None = None,
) -> Path:
    """``write_stack_folder`` up to the rename: the whole stack folder written into a fresh temporary sibling
    of ``out``, which is returned (``swap_in`` renames it into place; on failure nothing is left).
    ``stack.folder`` is left as it was. ``composite_png`` is composite.png's bytes when the caller encoded
    them already (``lasagna.io.render.encode_composite``); ``shared`` links large ``files`` from a batch's
    store instead of writing them (``SharedFiles``)."""
    out = check_output_folder(out, force=force)
    out.parent.mkdir(parents=True, exist_ok=True)
    sweep_stale(out.parent)
    tmp = make_temp_folder(out)
    old_folder = stack.folder
    try:
        from lasagna.io.render import write_composite  # torch: imported only when a stack is written
        from lasagna.io.stack import save_stack

        with private_folder(tmp):  # renamed into place whole or removed whole: no per-file temporaries
            save_stack(stack, tmp)
            for rel, data in (files or {}).items():
                dst = resolve_inside(tmp, rel, rel)
                if shared is None or not shared.place(data, dst):
                    atomic_write_bytes(dst, data)
            if composite_png is not None:
                atomic_write_bytes(tmp / "composite.png", composite_png)
            else:
                write_composite(result if result is not None else stack.render(), tmp / "composite.png")
        os.chmod(tmp, umask_mode(0o777))  # made 0700 (as mkdtemp does); a folder made by mkdir would not be
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        stack.folder = old_folder
    return tmp


def swap_in(tmp: Path, out: Path, *, force: bool = False) -> None:
    """Rename the finished folder ``tmp`` to ``out``, race-free between Lasagna processes.

    ``check_output_folder``'s rule is checked again under ``folder_lock`` on the parent, held until the
    rename: two writers aiming at one new folder both pass the early check, and without the lock the second
    would replace the first's stack as if forced. The loser gets the rule's ``PathError`` and its own
    folder is removed by the caller; nothing of the winner's is touched. An empty ``out`` is replaced by
    the rename itself (POSIX renames onto an empty folder); a forced stack is renamed aside first, and put
    back if the second rename fails.
    """
    with folder_lock(out.parent):
        check_output_folder(out, force=force)
        if not out.exists() or not any(out.iterdir()):
            try:
                os.rename(tmp, out)
            except OSError as exc:
                if exc.errno in (errno.ENOTEMPTY, errno.EEXIST):  # filled by a writer that took no lock
                    raise PathError("is not empty; expected a new or empty folder", str(out)) from None
                raise
            return
        aside = temp_path(out, "old")
        os.rename(out, aside)
        try:
            os.rename(tmp, out)
        except BaseException:
            os.rename(aside, out)
            raise
    shutil.rmtree(aside, ignore_errors=True)


# ---- saving an open stack in place (the editor) -----------------------------------------------------


def stack_sha256(folder: str | os.PathLike) -> str | None:
    """SHA-256 of ``folder``'s stack.json as it is on disk (None if there is none): the version a saver
    compares with the one it read, so that a second writer is told instead of overwritten."""
    path = Path(folder) / STACK_FILE
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except FileNotFoundError:
        return None


def _fresh_name(folder: Path, rel: str, taken: set[str]) -> str:
    """``rel`` if nothing is there and no document names it, else ``stem.N.ext`` (``N`` = 2, 3, …) that is free."""
    if rel not in taken and not (folder / rel).exists():
        return rel
    p = Path(rel)
    base = p.stem
    while base.rsplit(".", 1)[-1].isdigit() and "." in base:  # layers/a.3.png saved again: a.4, not a.3.2
        base = base.rsplit(".", 1)[0]
    n = 2
    while True:
        candidate = (p.parent / f"{base}.{n}{p.suffix}").as_posix()
        if candidate not in taken and not (folder / candidate).exists():
            return candidate
        n += 1


def save_in_place(
    stack: Stack,
    *,
    unchanged: Mapping[str, object],
    files: Mapping[str, bytes] | None = None,
    expect_sha256: str | None,
    extra: Callable[[Stack, Any], dict[str, bytes]] | None = None,
) -> tuple[str, dict[str, object]]:
    """Save ``stack`` into its own folder so that a kill at any instant leaves the old or the new stack whole.

    stack.json is the commit point and the only file replaced: every layer PNG (or mask) whose pixels
    changed is written under a new name (``layers/<id>.2.png``, …; the document's ``source`` follows it),
    new generator files likewise, all of them before stack.json is renamed into place. Files the old
    stack.json named and the new one does not are removed after the commit; composite.png (and whatever
    ``extra(stack, result)`` returns, e.g. stack.ora) are rewritten after it too, being derived.

    ``unchanged`` maps layer ids to the ``LayerTensors`` object their PNG on disk holds (identity): those
    are not encoded again. ``files`` are further files by relative path (generator copies); one already on
    disk with the same bytes is kept. ``expect_sha256`` is the stack.json the caller read (``stack_sha256``;
    None for a folder without one): a different one on disk is a ``ConflictError`` and nothing is written.
    Returns the new stack.json's SHA-256 and the new ``unchanged`` map. ``stack.document`` is updated.
    """
    from lasagna.io.render import encode_composite
    from lasagna.io.stack import encode_group_mask, encode_layer

    if stack.folder is None:
        raise PathError("the stack was not loaded from a folder; expected one to save into", "save")
    folder = Path(stack.folder)
    old_doc = _document_on_disk(folder)
    old_refs = _referenced(old_doc) if old_doc is not None else set()
    doc = stack.document
    taken = set(_referenced(doc)) | old_refs
    writes: list[tuple[Path, bytes]] = []
    renamed: dict[str, str] = {}  # generator checkpoint folder → its fresh name
    for rel, data in (files or {}).items():
        target = resolve_inside(folder, rel, rel)
        if target.is_file() and target.read_bytes() == data:
            continue
        parent = Path(rel).parent.as_posix()
        if target.exists() and parent not in renamed:
            renamed[parent] = _fresh_name(folder, parent, taken)
            taken.add(renamed[parent])
        out_rel = f"{renamed.get(parent, parent)}/{Path(rel).name}"
        writes.append((entry_inside(folder, out_rel, rel), data))

    def fresh(rel: str) -> str:
        name = _fresh_name(folder, rel, taken - {rel} if rel not in old_refs else taken)
        taken.add(name)
        return name

    changed: dict[str, dict[str, Any]] = {}  # layer id → fields that name new files
    now_unchanged: dict[str, object] = {}
    for loc, layer in doc.walk():  # groups' layers and masks too
        changes: dict[str, Any] = {}
        generator = getattr(layer, "generator", None)
        if generator is not None:
            parent = Path(generator.checkpoint).parent.as_posix()
            if parent in renamed:
                ckpt = f"{renamed[parent]}/{Path(generator.checkpoint).name}"
                changes["generator"] = {**generator.model_dump(mode="json"), "checkpoint": ckpt}
        tensors = stack.tensors.get(layer.id)
        if tensors is not None and layer.kind in ("group", "adjustment", "gradient"):
            if layer.mask is not None and not (unchanged.get(layer.id) is tensors and (folder / layer.mask).is_file()):
                data = encode_group_mask(stack, layer.id, loc)
                if not _holds(folder, layer.mask, data):
                    changes["mask"] = fresh(layer.mask)
                    writes.append((entry_inside(folder, changes["mask"], f"{loc}.mask"), data))
            now_unchanged[layer.id] = tensors
        elif tensors is not None and layer.kind != "solid":
            same = unchanged.get(layer.id) is tensors and (folder / layer.source).is_file()
            if not same:
                data, mask_data = encode_layer(stack, layer.id)
                same = _holds(folder, layer.source, data) and (
                    mask_data is None or _holds(folder, layer.mask, mask_data)
                )
            if not same:
                source = fresh(layer.source)
                writes.append((entry_inside(folder, source, f"{loc}.source"), data))
                if source != layer.source:
                    changes["source"] = source
                if mask_data is not None:
                    mask = fresh(layer.mask)
                    writes.append((entry_inside(folder, mask, f"{loc}.mask"), mask_data))
                    if mask != layer.mask:
                        changes["mask"] = mask
            now_unchanged[layer.id] = tensors
        if changes:
            changed[layer.id] = changes
    for id, changes in changed.items():
        doc = doc.replace_layer(id, **changes)
    stack.document = doc
    text = stack.document.to_json().encode("utf-8")
    result = stack.render()
    derived = [(folder / "composite.png", encode_composite(result, str(folder / "composite.png")))]
    if extra is not None:
        derived += [(resolve_inside(folder, rel, rel), data) for rel, data in extra(stack, result).items()]
    with folder_lock(folder):
        found = stack_sha256(folder)
        if found != expect_sha256:
            raise ConflictError(
                "stack.json changed on disk since this stack was read (another editor or program saved it); "
                "expected the version that was read: reload to see the other changes",
                str(folder / STACK_FILE),
            )
        if writes:
            atomic_write_all(writes)
        atomic_write_bytes(stack_file(folder), text)  # the commit
        for path, data in derived:
            atomic_write_bytes(path, data)
        now_refs = _referenced(stack.document)
        kept = {(folder / rel).resolve() for rel in now_refs}
        for rel in old_refs - now_refs:
            _remove_superseded(folder, rel, kept)
    return hashlib.sha256(text).hexdigest(), now_unchanged


def _holds(folder: Path, rel: str | None, data: bytes) -> bool:
    """Whether the file ``rel`` in ``folder`` holds exactly ``data`` (same size first: most differ there)."""
    if rel is None:
        return False
    path = folder / rel
    try:
        return path.is_file() and path.stat().st_size == len(data) and path.read_bytes() == data
    except OSError:
        return False


def _document_on_disk(folder: Path):
    from lasagna.document import Document

    path = folder / STACK_FILE
    if not path.is_file():
        return None
    try:
        return Document.from_json(path.read_text(encoding="utf-8"), where=str(path))
    except (LasagnaError, UnicodeDecodeError):
        return None  # an unreadable document names nothing we may remove


def _referenced(doc) -> set[str]:
    """Relative paths of the files ``doc`` names: sources, masks, generator checkpoints and their configs."""
    out: set[str] = set()
    for _, layer in doc.walk():  # groups' layers and masks too
        for rel in (getattr(layer, "source", None), getattr(layer, "mask", None)):
            if rel:
                out.add(Path(rel).as_posix())
        generator = getattr(layer, "generator", None)
        if generator is not None:
            out.add(Path(generator.checkpoint).as_posix())
            out.add((Path(generator.checkpoint).parent / "config.json").as_posix())
    return out


def _remove_superseded(folder: Path, rel: str, kept: set[Path]) -> None:
    """Remove a file the previous stack.json named and the new one does not, if it lies in one of the
    folders the stack's own files live in (layers/, masks/, generators/) — never anything else.

    What is removed is the folder's entry ``rel`` itself (``os.unlink``; a symlink there is unlinked, its
    target never touched), and a file is kept while a name the new document uses (``kept``, resolved)
    leads to it: another layer's symlink to it."""
    parts = Path(rel).parts
    if len(parts) < 2 or parts[0] not in ("layers", "masks", "generators") or ".." in parts:
        return
    try:
        entry = entry_inside(folder, rel, rel)
    except PathError:
        return
    if not entry.is_symlink() and (not entry.is_file() or entry.resolve() in kept):
        return
    try:
        os.unlink(entry)
    except OSError:
        return
    if parts[0] == "generators":
        try:
            entry.parent.rmdir()  # only when empty
        except OSError:
            pass
