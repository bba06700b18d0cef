"""Atomic writes (the ground floor every tier may import): write temporaries beside the targets, then rename.

One file (``atomic_path``, ``atomic_write_bytes``) or several at once (``atomic_write_all``: every
destination checked, every temporary written, then all renamed; a failure leaves every existing output
as it was). A crash, a full disk or an exception half-way leaves the user's existing files untouched.

Every temporary (file or folder) is named here, by ``temp_path``:
``.{name}.lasagna-{pid}-{random}.{kind}{suffix}`` — hidden, recognisable, carrying its owner's process id,
and at most ``NAME_MAX`` bytes (the kept part of ``name`` is shortened; the suffix stays, so libraries
that choose a format by extension still do). A process killed with SIGKILL cannot clean up after itself;
``sweep_stale`` removes the temporaries of owners that no longer run, and every writer calls it before
writing into a folder, so litter lasts only until the next write there.

``open_regular`` is how every reader opens a user's input: a regular file, or one line saying what it is
instead (a FIFO would block the reader forever; a device never ends).

``copy_tree`` copies a user's folder without following a link, within a cap on bytes and files.

``folder_lock`` serialises check-then-rename sequences between processes (``lasagna.io.folder``'s swap).

Every temporary file is fsync'd before it is renamed, except inside ``unsynced()``: a writer of many
outputs (``lasagna.batch``) stages them there and makes them durable together with one ``sync_filesystem``
before renaming any into place — one flush instead of one per file (seven per stack folder).

Inside a ``private_folder`` (a fresh temporary folder its writer renames into place whole, or removes whole:
``lasagna.io.folder.stage_stack_folder``) the folder is the unit of atomicity, so the files written into it
go straight to their names, without a temporary and a rename each.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import os
import re
import shutil
import stat
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import BinaryIO

from lasagna.errors import LasagnaError, PathError
from lasagna.limits import MAX_COPY_BYTES, MAX_COPY_FILES, format_size

# The longest file name most file systems take (ext4, APFS, NTFS: 255 bytes). A temporary longer than its
# target would make a legal output name fail, so temporaries are cut to this.
NAME_MAX = 255
# A suffix longer than this is no file-format extension ("a.<200 characters>"); it is not kept whole.
_MAX_SUFFIX = 16
_TEMP = re.compile(
    r"^\.(?P<kept>.*)\.lasagna-(?P<pid>[0-9]+)-(?P<random>[0-9a-f]{8})\.(?P<kind>tmp|old)(?P<suffix>\.[^.]*)?$", re.S
)


def file_kind(mode: int) -> str:
    """What a ``st_mode`` is, in words: ``a named pipe (FIFO)``, ``a character device``, ``a folder``, …"""
    for test, what in (
        (stat.S_ISREG, "a regular file"),
        (stat.S_ISDIR, "a folder"),
        (stat.S_ISLNK, "a symbolic link"),
        (stat.S_ISFIFO, "a named pipe (FIFO)"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return what
    return "not a file"


def _not_regular(mode: int, where: str, expected: str) -> PathError:
    return PathError(f"is not a regular file ({file_kind(mode)}); expected {expected}", where)


def open_regular(
    path: str | os.PathLike,
    where: str | None = None,
    *,
    follow_symlinks: bool = True,
    expected: str = "a regular file",
) -> BinaryIO:
    """Open a user's input for reading in binary, only if it is a regular file.

    A FIFO, device or socket is refused (``PathError``, one line: ``X: is not a regular file (a named pipe
    (FIFO)); expected …``) without blocking: its type is checked with ``stat`` before the open (opening some
    devices has effects of its own), and the file is opened ``O_NONBLOCK`` and checked again with ``fstat``
    (the name may have been swapped in between); only then is the descriptor made blocking again. A folder
    raises ``IsADirectoryError`` and other failures their ``OSError``, as ``open`` does, for the caller to
    word. ``follow_symlinks=False`` refuses a symbolic link too (``O_NOFOLLOW``)."""
    where = str(path) if where is None else where
    flags = os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0)
    if not follow_symlinks:
        flags |= getattr(os, "O_NOFOLLOW", 0)

    def check(mode: int) -> None:
        if stat.S_ISDIR(mode):
            raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), os.fspath(path))
        if not stat.S_ISREG(mode):
            raise _not_regular(mode, where, expected)

    check(os.stat(path, follow_symlinks=follow_symlinks).st_mode)
    fd = os.open(path, flags)
    try:
        check(os.fstat(fd).st_mode)
        os.set_blocking(fd, True)
        fh = os.fdopen(fd, "rb")
        fh.raw.name = os.fspath(path)  # type: ignore[attr-defined]  # as open() names it (tifffile reads it)
        return fh
    except BaseException:
        os.close(fd)
        raise


def copy_tree(
    src: str | os.PathLike,
    dst: str | os.PathLike,
    *,
    max_bytes: int = MAX_COPY_BYTES,
    max_files: int = MAX_COPY_FILES,
) -> int:
    """Copy the folder ``src`` into the existing folder ``dst``: its folders and regular files only, never
    following a link inside it; returns the bytes copied.

    A symbolic link (to the folder itself, to ``/dev/zero``, anywhere) or a FIFO, device or socket inside
    ``src`` is refused (``PathError``, one line naming it), and so is a tree of more than ``max_files`` files
    or ``max_bytes`` bytes, counted while copying (a file growing meanwhile is cut off at the cap). The caller
    copies into a temporary folder it removes on failure (``lasagna.catalogue.add_prior``)."""
    root, out = Path(src), Path(dst)
    total, files = 0, 0
    todo: list[Path] = [Path()]
    while todo:
        rel = todo.pop()
        with os.scandir(root / rel) as it:
            entries = sorted(it, key=lambda e: e.name)
        for entry in entries:
            path, child = root / rel / entry.name, rel / entry.name
            mode = entry.stat(follow_symlinks=False).st_mode
            if stat.S_ISDIR(mode):
                (out / child).mkdir()
                todo.append(child)
                continue
            if not stat.S_ISREG(mode):
                raise PathError(
                    f"is {file_kind(mode)}; expected only folders and regular files (links are not followed)",
                    str(path),
                )
            files += 1
            if files > max_files:
                raise PathError(f"holds more than {max_files} files; expected a smaller folder", str(root))
            with open_regular(path, follow_symlinks=False) as fh, open(out / child, "xb") as copy:
                while chunk := fh.read(min(1 << 20, max_bytes - total + 1)):
                    total += len(chunk)
                    if total > max_bytes:
                        raise PathError(
                            f"holds more than {format_size(max_bytes)}; expected a smaller folder", str(root)
                        )
                    copy.write(chunk)
    return total


def umask_mode(mode: int) -> int:
    """``mode`` less the process's umask: the permissions ``open``/``mkdir`` would give a new file/folder."""
    umask = os.umask(0)
    os.umask(umask)
    return mode & ~umask


def _cut(text: str, limit: int) -> str:
    """The longest prefix of ``text`` whose UTF-8 encoding has at most ``limit`` bytes."""
    data = text.encode("utf-8", "surrogateescape")[: max(0, limit)]
    return data.decode("utf-8", "ignore")


def temp_path(target: str | os.PathLike, kind: str = "tmp", suffix: str | None = None) -> Path:
    """A fresh temporary name beside ``target``: ``.{name}.lasagna-{pid}-{random}.{kind}{suffix}``.

    ``kind`` is ``tmp`` (being written) or ``old`` (an existing output moved aside, see ``sweep_stale``);
    ``suffix`` defaults to the target's for a ``tmp`` file. Nothing is created."""
    target = Path(target)
    if suffix is None:
        suffix = target.suffix if kind == "tmp" else ""
    if len(suffix.encode("utf-8", "surrogateescape")) > _MAX_SUFFIX:
        suffix = ""
    tail = f".lasagna-{os.getpid()}-{os.urandom(4).hex()}.{kind}{suffix}"
    room = NAME_MAX - 1 - len(tail.encode("utf-8", "surrogateescape"))
    return target.parent / f".{_cut(target.name, room)}{tail}"


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs (one we may not signal runs too: someone else's live writer)."""
    if pid == os.getpid() or os.name != "posix":  # on Windows os.kill(pid, 0) would end the process
        return True
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):  # no such process (or no such pid at all)
        return False
    except PermissionError:
        return True
    return True


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError, IsADirectoryError, PermissionError):
            path.unlink()


def sweep_stale(folder: str | os.PathLike) -> list[Path]:
    """Remove the temporaries in ``folder`` whose owner process is gone (killed, crashed); returns them.

    A ``tmp`` is half-written: removed. An ``old`` is an output moved aside by a swap (``lasagna.io.folder``):
    when its target exists the swap completed and it is removed; when the target is missing the owner died
    between the two renames, so it is renamed back — the user's previous output is never deleted. (A name
    cut to ``NAME_MAX`` does not say its target, so such an ``old`` whose target is missing is left alone.)
    Temporaries of live processes, this one included, are never touched; a pid reused since is taken as
    alive (the litter stays, nothing is lost).
    """
    folder = Path(folder)
    removed: list[Path] = []
    try:
        entries = list(os.scandir(folder))
    except (FileNotFoundError, NotADirectoryError, PermissionError):
        return removed
    for entry in entries:
        m = _TEMP.match(entry.name)
        if m is None or _alive(int(m["pid"])):
            continue
        path = folder / entry.name
        if m["kind"] == "old":
            target = folder / m["kept"]
            if not target.exists() and not target.is_symlink():
                if len(entry.name.encode("utf-8", "surrogateescape")) < NAME_MAX:
                    with contextlib.suppress(OSError):
                        os.rename(path, target)
                continue
        _remove(path)
        removed.append(path)
    return removed


# The private staging folder of this context (``private_folder``), as an absolute path; None outside one.
_PRIVATE: contextvars.ContextVar[str | None] = contextvars.ContextVar("lasagna_atomic_private", default=None)


@contextlib.contextmanager
def private_folder(folder: str | os.PathLike) -> Iterator[None]:
    """Within, files written inside ``folder`` go straight to their names (no temporary, no rename).

    Only for a fresh temporary folder that nothing else reads and whose writer renames it into place as a
    whole or removes it as a whole: a failure half-way then leaves nothing, whatever state its files are in.
    Writes elsewhere stay atomic file by file."""
    token = _PRIVATE.set(os.path.abspath(folder))
    try:
        yield
    finally:
        _PRIVATE.reset(token)


def _in_private(target: Path) -> bool:
    root = _PRIVATE.get()
    return root is not None and os.path.abspath(target).startswith(root + os.sep)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path in ``path``'s folder; on success it replaces ``path`` atomically.

    The temporary keeps the target's suffix (``.png``, ``.ora``; or ``suffix``) so libraries that choose
    a format by extension still do. On an exception (Ctrl-C and SIGTERM included) the temporary file is
    removed and ``path`` is left as it was. Inside a ``private_folder`` the path itself is yielded.
    """
    target = Path(path)
    if _in_private(target):
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            yield target
        except BaseException:
            with contextlib.suppress(FileNotFoundError, IsADirectoryError):
                target.unlink()
            raise
        return
    target.parent.mkdir(parents=True, exist_ok=True)
    sweep_stale(target.parent)
    tmp = _create(target, suffix)
    try:
        yield tmp
        os.chmod(tmp, umask_mode(0o666))  # created 0600 (as mkstemp does); give what a plain open() would
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def _create(target: Path, suffix: str | None = None) -> Path:
    """Create an empty temporary file for ``target`` (exclusively, mode 0600) and return its path."""
    while True:
        tmp = temp_path(target, "tmp", suffix)
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
        except FileExistsError:
            continue
        return tmp


def make_temp_folder(target: str | os.PathLike, kind: str = "tmp") -> Path:
    """Create an empty temporary folder beside ``target`` (mode 0700, as ``mkdtemp``) and return it."""
    target = Path(target)
    while True:
        tmp = temp_path(target, kind, suffix="")
        try:
            os.mkdir(tmp, 0o700)
        except FileExistsError:
            continue
        return tmp


# False inside ``unsynced()``: temporaries are written without fsync; the caller syncs before renaming.
_FSYNC: contextvars.ContextVar[bool] = contextvars.ContextVar("lasagna_atomic_fsync", default=True)


@contextlib.contextmanager
def unsynced() -> Iterator[None]:
    """Write temporaries without fsync within: only for outputs that stay inside a temporary folder until the
    caller has called ``sync_filesystem`` on it (a power cut must not find a renamed output half on disk)."""
    token = _FSYNC.set(False)
    try:
        yield
    finally:
        _FSYNC.reset(token)


def sync_filesystem(folder: str | os.PathLike) -> None:
    """Flush everything written to the file system holding ``folder`` (``syncfs``; ``sync`` where there is none)."""
    try:
        import ctypes

        syncfs = ctypes.CDLL(None, use_errno=True).syncfs
    except (OSError, AttributeError):  # not Linux
        os.sync()
        return
    fd = os.open(folder, os.O_RDONLY)
    try:
        if syncfs(fd) != 0:
            os.sync()
    finally:
        os.close(fd)


def _write(path: Path, data: bytes) -> None:
    with open(path, "wb") as fh:
        fh.write(data)
        if _FSYNC.get():
            fh.flush()
            os.fsync(fh.fileno())


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (fsync before the rename, so a power cut is safe too)."""
    with atomic_path(path) as tmp:
        _write(tmp, data)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))


def _cannot_write(exc: OSError, target: Path, error: type[LasagnaError] = PathError) -> LasagnaError:
    return error(f"cannot write ({exc.strerror or exc}); expected a writable location", str(target))


def write_output(path: str | os.PathLike, data: bytes, error: type[LasagnaError] = PathError) -> Path:
    """Write an output file the user named (an export, a composite, a PNG) atomically; a failure to write is
    one line of ``error`` naming the file: "cannot write (why); expected a writable location"."""
    try:
        atomic_write_bytes(path, data)
    except OSError as exc:
        raise _cannot_write(exc, Path(path), error) from None
    return Path(path)


def atomic_write_all(files: Sequence[tuple[str | os.PathLike, bytes]]) -> list[Path]:
    """Write several files all or nothing; returns their paths.

    Every destination is checked first (not a folder, no two the same), then every temporary is written,
    then all are renamed into place. A failure before the renames removes every temporary (and the
    folders this call made) and leaves every existing output untouched; a rename failing half-way puts
    back the outputs already replaced (each existing output is hard-linked aside before it is replaced).
    Errors are ``PathError``s naming the user's path, never a temporary's.
    """
    targets = [Path(p) for p, _ in files]
    seen: set[str] = set()
    for t in targets:
        key = os.path.abspath(t)
        if key in seen:
            raise PathError("is written twice; expected each output once", str(t))
        seen.add(key)
        if t.is_dir():
            raise PathError("is a folder; expected a file path to write", str(t))
    if all(_in_private(t) for t in targets):  # the folder is the unit of atomicity: straight to the names
        for t, (_, data) in zip(targets, files):
            try:
                t.parent.mkdir(parents=True, exist_ok=True)
                _write(t, data)
            except OSError as exc:
                raise _cannot_write(exc, t) from None
        return targets
    made: list[Path] = []  # folders this call created, deepest last
    temps: list[Path] = []
    asides: list[tuple[Path, Path]] = []  # (backup, target) of outputs already replaced
    try:
        for t in targets:
            missing = [p for p in [t.parent, *t.parent.parents] if not p.exists()]
            for folder in reversed(missing):
                try:
                    folder.mkdir()
                except OSError as exc:
                    raise _cannot_write(exc, t) from None
                made.append(folder)
        for folder in {t.parent for t in targets}:
            sweep_stale(folder)
        for t, (_, data) in zip(targets, files):
            try:
                tmp = _create(t)
                temps.append(tmp)
                _write(tmp, data)
                os.chmod(tmp, umask_mode(0o666))
            except OSError as exc:
                raise _cannot_write(exc, t) from None
        for t, tmp in zip(targets, temps):
            try:
                backup = None
                if t.is_symlink() or t.is_file():  # a link is put back as the link, never as its target
                    backup = temp_path(t, "old")
                    try:
                        os.link(t, backup, follow_symlinks=False)
                    except OSError:  # no hard links here (FAT, some network shares): copy instead
                        shutil.copy2(t, backup, follow_symlinks=False)
                os.replace(tmp, t)
            except OSError as exc:
                if backup is not None:
                    with contextlib.suppress(FileNotFoundError):
                        backup.unlink()
                raise _cannot_write(exc, t) from None
            if backup is not None:
                asides.append((backup, t))
    except BaseException:
        for backup, t in reversed(asides):
            with contextlib.suppress(OSError):
                os.replace(backup, t)
        for tmp in temps:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
        for folder in reversed(made):
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise
    for backup, _ in asides:
        with contextlib.suppress(FileNotFoundError):
            backup.unlink()
    return targets


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike) -> Iterator[None]:
    """Hold an exclusive advisory lock (``flock``) on ``folder`` itself: no lock file to leave behind.

    Only Lasagna's own writers take it; it makes a check-then-rename atomic between them. Without
    ``fcntl`` (Windows) nothing is locked.
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock
