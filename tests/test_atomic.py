"""Atomic writes: temporary names (recognisable, owner's pid, within NAME_MAX, suffix kept), the sweep of a
dead owner's temporaries (a ``tmp`` removed, an ``old`` put back or removed), and ``atomic_write_all``
(every output or none, errors naming the user's path)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from lasagna import atomic
from lasagna.atomic import (
    NAME_MAX,
    atomic_write_all,
    atomic_write_bytes,
    make_temp_folder,
    sweep_stale,
    temp_path,
    write_output,
)
from lasagna.errors import ExportError, ImageError, PathError


@pytest.fixture(scope="module")
def dead_pid() -> int:
    """The pid of a process that has exited (and been reaped)."""
    child = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    return int(child.stdout)


def stale(folder, name: str, pid: int, kind: str = "tmp", suffix: str = "", *, is_folder: bool = False):
    """A temporary as ``temp_path`` names it, but owned by ``pid``."""
    path = folder / f".{name}.lasagna-{pid}-0123abcd.{kind}{suffix}"
    if is_folder:
        path.mkdir()
        (path / "inside.png").write_bytes(b"x" * 10)
    else:
        path.write_bytes(b"half-written")
    return path


def temporaries(folder) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if ".lasagna-" in p.name)


class TestTempPath:
    def test_names_the_owner_and_keeps_the_suffix(self, tmp_path):
        tmp = temp_path(tmp_path / "out.png")
        assert tmp.parent == tmp_path and tmp.name.startswith(".out.png.lasagna-")
        assert f"-{os.getpid()}-" in tmp.name and tmp.name.endswith(".tmp.png")
        assert atomic._TEMP.match(tmp.name)["kept"] == "out.png"
        assert temp_path(tmp_path / "out.png") != tmp  # random part

    @pytest.mark.parametrize("name", ["a" * 244 + ".png", "名" * 83 + ".png", "😀" * 62 + ".psd", "a" * 255])
    def test_stays_within_name_max(self, tmp_path, name):
        assert len(name.encode()) <= NAME_MAX
        tmp = temp_path(tmp_path / name)
        assert len(tmp.name.encode()) <= NAME_MAX
        assert tmp.name.endswith(".tmp" + (os.path.splitext(name)[1]))
        tmp.name.encode("utf-8")  # cut on a character boundary, never inside one

    def test_a_legal_long_name_can_be_written(self, tmp_path):
        target = tmp_path / ("b" * 248 + ".png")
        atomic_write_bytes(target, b"data")
        assert target.read_bytes() == b"data" and temporaries(tmp_path) == []

    def test_temp_folder(self, tmp_path):
        folder = make_temp_folder(tmp_path / "out")
        assert folder.is_dir() and folder.name.endswith(".tmp") and (folder.stat().st_mode & 0o777) == 0o700


class TestSweepStale:
    def test_removes_a_dead_owners_temporaries(self, tmp_path, dead_pid):
        a = stale(tmp_path, "x.ora", dead_pid, suffix=".ora")
        b = stale(tmp_path, "out", dead_pid, is_folder=True)
        assert sorted(sweep_stale(tmp_path)) == sorted([a, b])
        assert temporaries(tmp_path) == []

    def test_keeps_live_owners_temporaries(self, tmp_path):
        mine = stale(tmp_path, "x.png", os.getpid(), suffix=".png")
        parent = stale(tmp_path, "y.png", os.getppid(), suffix=".png")  # alive (our parent)
        init = stale(tmp_path, "z.png", 1, suffix=".png")  # alive; signalling it is not permitted unless root
        assert sweep_stale(tmp_path) == []
        assert mine.exists() and parent.exists() and init.exists()

    def test_ignores_other_files(self, tmp_path, dead_pid):
        names = [".x.png.12345.png", "x.lasagna-1-0123abcd.tmp", f".x.lasagna-{dead_pid}-0123abcd.bak", "plain.png"]
        for name in names:
            (tmp_path / name).write_bytes(b"keep")
        sweep_stale(tmp_path)
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted(names)

    def test_an_old_folder_whose_target_is_missing_is_put_back(self, tmp_path, dead_pid):
        # The owner died between renaming the user's stack aside and renaming the new one in.
        aside = stale(tmp_path, "out", dead_pid, kind="old", is_folder=True)
        new = stale(tmp_path, "out", dead_pid, is_folder=True)
        sweep_stale(tmp_path)
        assert (tmp_path / "out" / "inside.png").is_file() and not aside.exists() and not new.exists()

    def test_an_old_whose_target_exists_is_removed(self, tmp_path, dead_pid):
        (tmp_path / "out").mkdir()
        aside = stale(tmp_path, "out", dead_pid, kind="old", is_folder=True)
        sweep_stale(tmp_path)
        assert not aside.exists() and (tmp_path / "out").is_dir() and not any((tmp_path / "out").iterdir())

    def test_atomic_write_sweeps_first(self, tmp_path, dead_pid):
        stale(tmp_path, "x.png", dead_pid, suffix=".png")
        atomic_write_bytes(tmp_path / "x.png", b"new")
        assert temporaries(tmp_path) == [] and (tmp_path / "x.png").read_bytes() == b"new"


class TestAtomicWriteAll:
    def test_writes_every_file_and_makes_folders(self, tmp_path):
        files = [(tmp_path / "a.ora", b"A"), (tmp_path / "L" / "masks" / "m.png", b"M"), (tmp_path / "L" / "j", b"J")]
        assert atomic_write_all(files) == [p for p, _ in files]
        assert [p.read_bytes() for p, _ in files] == [b"A", b"M", b"J"]
        assert temporaries(tmp_path) == temporaries(tmp_path / "L") == []

    def test_a_folder_in_the_way_writes_nothing(self, tmp_path):
        (tmp_path / "keep.ora").write_bytes(b"old")
        (tmp_path / "L" / "shade.png").mkdir(parents=True)
        with pytest.raises(PathError, match=r"L/shade\.png: is a folder"):
            atomic_write_all([(tmp_path / "keep.ora", b"new"), (tmp_path / "L" / "shade.png", b"x")])
        assert (tmp_path / "keep.ora").read_bytes() == b"old" and temporaries(tmp_path) == []

    def test_the_same_output_twice_is_refused(self, tmp_path):
        with pytest.raises(PathError, match="written twice"):
            atomic_write_all([(tmp_path / "a", b"1"), (tmp_path / "." / "a", b"2")])
        assert not (tmp_path / "a").exists()

    def test_a_failed_write_removes_every_temporary_and_made_folder(self, tmp_path, monkeypatch):
        (tmp_path / "keep.ora").write_bytes(b"old")
        real = atomic._write

        def full_disk(path, data):
            if data == b"second":
                raise OSError(28, "No space left on device", str(path))
            real(path, data)

        monkeypatch.setattr(atomic, "_write", full_disk)
        with pytest.raises(PathError) as info:
            atomic_write_all([(tmp_path / "keep.ora", b"first"), (tmp_path / "new" / "x.png", b"second")])
        assert str(info.value).startswith(f"{tmp_path / 'new' / 'x.png'}: cannot write (No space left on device)")
        assert (tmp_path / "keep.ora").read_bytes() == b"old"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.ora"]

    def test_a_failed_rename_puts_back_what_was_replaced(self, tmp_path, monkeypatch):
        a, b = tmp_path / "a.ora", tmp_path / "b.psd"
        a.write_bytes(b"old a")
        b.write_bytes(b"old b")
        real = os.replace

        def failing(src, dst):
            if str(dst) == str(b):
                raise OSError(5, "Input/output error", str(src))
            real(src, dst)

        monkeypatch.setattr(atomic.os, "replace", failing)
        with pytest.raises(PathError, match=r"b\.psd: cannot write"):
            atomic_write_all([(a, b"new a"), (b, b"new b")])
        monkeypatch.undo()
        assert a.read_bytes() == b"old a" and b.read_bytes() == b"old b"
        assert temporaries(tmp_path) == []


def test_unsynced_skips_fsync_only_within(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(atomic.os, "fsync", lambda fd: calls.append(fd))
    with atomic.unsynced():
        atomic_write_bytes(tmp_path / "a", b"1")
    assert calls == [] and (tmp_path / "a").read_bytes() == b"1"
    atomic_write_bytes(tmp_path / "b", b"2")
    assert len(calls) == 1
    atomic.sync_filesystem(tmp_path)  # syncfs (or sync): returns once flushed


def test_private_folder_writes_straight_to_names_inside_only(tmp_path, monkeypatch):
    """Inside a private staging folder no temporary is made (``_create`` would be called for one); a write
    outside it, in the same context, is still a temporary and a rename; a failure removes the half file."""
    private, outside = tmp_path / ".stage.tmp", tmp_path / "out"
    made = []
    real_create = atomic._create
    monkeypatch.setattr(atomic, "_create", lambda t, s=None: made.append(t) or real_create(t, s))
    with atomic.private_folder(private):
        atomic_write_bytes(private / "layers" / "a.png", b"a")
        atomic_write_all([(private / "stack.json", b"{}"), (private / "deep" / "b", b"b")])
        assert made == []
        atomic_write_bytes(outside / "c", b"c")
        assert made == [outside / "c"]
        with pytest.raises(RuntimeError), atomic.atomic_path(private / "half.png") as p:
            assert p == private / "half.png"
            p.write_bytes(b"half")
            raise RuntimeError("interrupted")
    assert sorted(q.relative_to(private).as_posix() for q in private.rglob("*") if q.is_file()) == [
        "deep/b",
        "layers/a.png",
        "stack.json",
    ]
    assert (private / "deep" / "b").read_bytes() == b"b" and (outside / "c").read_bytes() == b"c"
    with pytest.raises(PathError, match="written twice"), atomic.private_folder(private):
        atomic_write_all([(private / "x", b"1"), (private / "x", b"2")])
    made.clear()
    atomic_write_bytes(private / "after", b"1")  # the context is over: atomic again
    assert made == [private / "after"]


def test_copy_tree_copies_files_and_folders_within_its_caps(tmp_path):
    """Issue #28 (9): folders and regular files only, counted against the caps while copying."""
    from lasagna.atomic import copy_tree
    from lasagna.errors import PathError

    src = tmp_path / "src"
    (src / "sub").mkdir(parents=True)
    (src / "a.bin").write_bytes(b"a" * 10)
    (src / "sub" / "b.bin").write_bytes(b"b" * 20)
    (tmp_path / "ok").mkdir()
    assert copy_tree(src, tmp_path / "ok") == 30
    assert (tmp_path / "ok" / "sub" / "b.bin").read_bytes() == b"b" * 20
    (tmp_path / "few").mkdir()
    with pytest.raises(PathError, match=r"src: holds more than 1 files; expected a smaller folder"):
        copy_tree(src, tmp_path / "few", max_files=1)
    (tmp_path / "small").mkdir()
    with pytest.raises(PathError, match=r"src: holds more than 29 B"):
        copy_tree(src, tmp_path / "small", max_bytes=29)
    (src / "sub" / "loop").symlink_to(src)
    (tmp_path / "links").mkdir()
    with pytest.raises(PathError, match=r"loop: is a symbolic link; expected only folders and regular files"):
        copy_tree(src, tmp_path / "links")


@pytest.mark.parametrize("error", [PathError, ImageError, ExportError])
def test_write_output_is_one_line_of_the_callers_error(tmp_path, error):
    (tmp_path / "a-file").write_bytes(b"")
    target = tmp_path / "a-file" / "out.png"  # its folder is a file
    with pytest.raises(error) as info:
        write_output(target, b"x", error)
    assert str(info.value).startswith(f"{target}: cannot write (") and "expected a writable location" in str(info.value)
    assert write_output(tmp_path / "ok.png", b"x", error) == tmp_path / "ok.png"
    assert (tmp_path / "ok.png").read_bytes() == b"x"
