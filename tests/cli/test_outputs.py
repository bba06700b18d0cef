"""Every command's outputs all or nothing: several outputs written together or not at all, outputs that
would overwrite the input refused, long legal names, symlinked and non-stack output folders, SIGTERM
(exit 143, nothing left behind) and SIGKILL (the litter swept by the next run), racing writers."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lasagna.cli import main
from tests.support.bounded import HANG_SECONDS
from tests.support.tinylayers import ROOT

BASIC = ROOT / "examples" / "stacks" / "basic"
PHOTO = ROOT / "examples" / "photos" / "coffee.png"

# A child process running the CLI with one write made to wait (after its temporary is written, before
# anything is renamed), so a test can signal it at that moment deterministically.
SLOW_CLI = """
import os, sys, time
from pathlib import Path
import lasagna.atomic as atomic
import lasagna.io.folder as folder
from lasagna.cli import main

def wait_here():
    Path(os.environ["LASAGNA_TEST_READY"]).write_text("ready")
    time.sleep(120)

real_write, real_swap = atomic._write, folder.swap_in
def slow_write(path, data):
    real_write(path, data)
    wait_here()
def slow_swap(tmp, out, **kw):
    wait_here()
    return real_swap(tmp, out, **kw)
atomic._write, folder.swap_in = slow_write, slow_swap
sys.exit(main(sys.argv[1:]))
"""


def run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def one_error_line(code: int, err: str) -> bool:
    return code == 2 and len(err.strip().splitlines()) == 1 and err.startswith("lasagna: error: ")


def litter(*folders: Path) -> list[str]:
    return [p.name for folder in folders if folder.is_dir() for p in folder.iterdir() if ".lasagna-" in p.name]


def start_slow(tmp_path: Path, *argv, env: dict | None = None) -> tuple[subprocess.Popen, Path]:
    """The CLI in a child process, stopped inside its write; returns (process, the ready marker)."""
    ready = tmp_path / "ready"
    environ = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", LASAGNA_TEST_READY=str(ready))
    environ.update(env or {})
    proc = subprocess.Popen(
        [sys.executable, "-c", SLOW_CLI, *map(str, argv)],
        env=environ,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 120
    while not ready.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            out, err = proc.communicate()
            pytest.fail(f"the child never reached its write (exit {proc.returncode}): {err}")
        time.sleep(0.05)
    return proc, ready


# ---- several outputs, all or nothing --------------------------------------------------------------------


def test_export_writes_every_output_or_none(tmp_path, capsys):
    keep = tmp_path / "keep.ora"
    keep.write_bytes(b"the user's file")
    (tmp_path / "L" / "shade.png").mkdir(parents=True)  # one of --layers' files cannot be written
    code, out, err = run(
        capsys, "export", BASIC, "--ora", keep, "--psd", tmp_path / "new.psd", "--layers", tmp_path / "L"
    )
    assert one_error_line(code, err), err
    assert f"{tmp_path / 'L' / 'shade.png'}: is a folder; expected a file path to write" in err
    assert out == "" and keep.read_bytes() == b"the user's file" and not (tmp_path / "new.psd").exists()
    assert sorted(p.name for p in (tmp_path / "L").iterdir()) == ["shade.png"]
    assert litter(tmp_path, tmp_path / "L") == []


def test_export_write_error_names_the_users_path(tmp_path, capsys, monkeypatch):
    import lasagna.atomic as atomic

    keep = tmp_path / "keep.ora"
    keep.write_bytes(b"the user's file")
    real = atomic._write

    def full_disk(path, data):
        if path.name.startswith(".b.psd."):
            raise OSError(28, "No space left on device", str(path))
        real(path, data)

    monkeypatch.setattr(atomic, "_write", full_disk)
    code, out, err = run(capsys, "export", BASIC, "--ora", keep, "--psd", tmp_path / "b.psd")
    assert one_error_line(code, err)
    assert err.startswith(f"lasagna: error: {tmp_path / 'b.psd'}: cannot write (No space left on device)")
    assert keep.read_bytes() == b"the user's file" and litter(tmp_path) == []


# ---- outputs onto the input, long names ------------------------------------------------------------------


@pytest.mark.parametrize("name", ["stack.json", "layers/base.png", "layers/../stack.json"])
def test_composite_refuses_to_overwrite_the_input(tmp_path, capsys, name):
    stack = tmp_path / "s"
    shutil.copytree(BASIC, stack)
    before = {p: p.read_bytes() for p in stack.rglob("*") if p.is_file()}
    code, _, err = run(capsys, "composite", stack, "-o", stack / name)
    assert one_error_line(code, err) and "; expected an output path that is not one of the stack's files" in err
    assert {p: p.read_bytes() for p in stack.rglob("*") if p.is_file()} == before
    assert run(capsys, "composite", stack, "-o", stack / "composite.png")[0] == 0  # its own composite: fine


def test_export_refuses_to_overwrite_the_input(tmp_path, capsys):
    stack = tmp_path / "s"
    shutil.copytree(BASIC, stack)
    before = (stack / "layers" / "shade.png").read_bytes()
    code, _, err = run(capsys, "export", stack, "--layers", stack / "layers")
    assert one_error_line(code, err) and "layers[0].source of the input" in err
    assert (stack / "layers" / "shade.png").read_bytes() == before


def test_a_long_legal_output_name(tmp_path, capsys):
    out = tmp_path / ("c" * 244 + ".png")  # 248 characters: legal, and its temporary must be too
    code, _, err = run(capsys, "composite", BASIC, "-o", out)
    assert code == 0, err
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and litter(tmp_path) == []


# ---- output folders ------------------------------------------------------------------------------------


def test_edit_refuses_a_symlinked_output_before_any_work(tmp_path, capsys, monkeypatch, tiny):
    import lasagna.editing

    monkeypatch.setenv("LASAGNA_LAYERS", str(tiny))
    monkeypatch.setattr(lasagna.editing, "edit", lambda *a, **k: pytest.fail("the edit ran before the check"))
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "real")
    code, _, err = run(capsys, "edit", PHOTO, "--condition", "left", "-o", tmp_path / "link")
    assert one_error_line(code, err) and "link: is a symbolic link" in err
    assert not any((tmp_path / "real").iterdir())


def test_import_ora_follows_the_stack_folder_rule(tmp_path, capsys):
    assert run(capsys, "export", BASIC, "--ora", tmp_path / "b.ora")[0] == 0
    other = tmp_path / "notes"
    other.mkdir()
    (other / "todo.txt").write_text("mine")
    code, _, err = run(capsys, "import-ora", tmp_path / "b.ora", "-o", other)
    assert one_error_line(code, err) and "is not empty; expected a new or empty folder" in err
    code, _, err = run(capsys, "import-ora", tmp_path / "b.ora", "-o", other, "--force")
    assert one_error_line(code, err) and "holds no stack.json" in err
    assert sorted(p.name for p in other.iterdir()) == ["todo.txt"]
    out = tmp_path / "back"
    assert run(capsys, "import-ora", tmp_path / "b.ora", "-o", out)[0] == 0
    assert sorted(p.name for p in out.iterdir()) == ["composite.png", "layers", "stack.json"]
    (out / "extra.txt").write_text("replaced with the folder")
    assert run(capsys, "import-ora", tmp_path / "b.ora", "-o", out, "--force")[0] == 0
    assert not (out / "extra.txt").exists() and litter(tmp_path) == []


# ---- signals -------------------------------------------------------------------------------------------


def test_sigterm_during_export_exits_143_and_leaves_nothing(tmp_path):
    keep = tmp_path / "keep.ora"
    keep.write_bytes(b"the user's file")
    proc, _ = start_slow(tmp_path, "export", BASIC, "--ora", keep, "--layers", tmp_path / "L")
    assert litter(tmp_path), "the child was stopped before writing its temporary"
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=HANG_SECONDS)
    assert proc.returncode == 143, err
    assert "Traceback" not in err and out == ""
    assert keep.read_bytes() == b"the user's file" and not (tmp_path / "L").exists() and litter(tmp_path) == []


def test_sigkill_litter_is_swept_by_the_next_export(tmp_path, capsys):
    keep = tmp_path / "keep.ora"
    keep.write_bytes(b"the user's file")
    proc, _ = start_slow(tmp_path, "export", BASIC, "--ora", keep)
    proc.kill()
    proc.communicate(timeout=HANG_SECONDS)
    left = litter(tmp_path)
    assert len(left) == 1 and f".lasagna-{proc.pid}-" in left[0] and keep.read_bytes() == b"the user's file"
    assert run(capsys, "export", BASIC, "--ora", keep)[0] == 0
    assert litter(tmp_path) == [] and keep.read_bytes()[:2] == b"PK"


@pytest.mark.parametrize("how", ["SIGTERM", "SIGKILL"])
def test_killed_edit(tmp_path, capsys, monkeypatch, tiny, how):
    out = tmp_path / "out"
    proc, _ = start_slow(tmp_path, "edit", PHOTO, "--condition", "left", "-o", out, env={"LASAGNA_LAYERS": str(tiny)})
    assert any(name.endswith(".tmp") for name in litter(tmp_path))  # the finished folder, not renamed in yet
    proc.send_signal(getattr(signal, how))
    _, err = proc.communicate(timeout=HANG_SECONDS)
    assert not out.exists()
    if how == "SIGTERM":
        assert proc.returncode == 143 and "Traceback" not in err and litter(tmp_path) == []
        return
    assert proc.returncode == -signal.SIGKILL and litter(tmp_path)
    monkeypatch.setenv("LASAGNA_LAYERS", str(tiny))
    assert run(capsys, "edit", PHOTO, "--condition", "left", "-o", out)[0] == 0
    assert litter(tmp_path) == [] and (out / "stack.json").is_file()


def test_sigterm_handler_is_restored(capsys):
    before = signal.getsignal(signal.SIGTERM)
    assert run(capsys, "layers")[0] == 0
    assert signal.getsignal(signal.SIGTERM) is before


def test_racing_imports_into_one_folder(tmp_path, capsys):
    """Two processes writing one new folder at once: exactly one succeeds, the other says why (exit 2)."""
    assert run(capsys, "export", BASIC, "--ora", tmp_path / "b.ora")[0] == 0
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    for attempt in range(2):
        out = tmp_path / f"out{attempt}"
        argv = [sys.executable, "-m", "lasagna.cli", "import-ora", str(tmp_path / "b.ora"), "-o", str(out)]
        procs = [subprocess.Popen(argv, env=env, stderr=subprocess.PIPE, text=True) for _ in range(2)]
        results = sorted((p.wait(timeout=HANG_SECONDS), p.stderr.read()) for p in procs)
        assert [code for code, _ in results] == [0, 2], results
        assert one_error_line(2, results[1][1]) and f"{out}: is not empty" in results[1][1]
        assert (out / "stack.json").is_file() and litter(tmp_path) == []
