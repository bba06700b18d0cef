"""The CLI's thread policy (``lasagna.cli.common.thread_count``) and ``--threads`` on every computing command."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
import torch

from lasagna.cli import COMMANDS, build_parser, main
from lasagna.cli.common import COMPUTING, thread_count

BASIC = Path(__file__).resolve().parents[2] / "examples" / "stacks" / "basic"
AFFINITY = len(os.sched_getaffinity(0))


@pytest.fixture
def keep_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def test_default_is_the_affinity_count():
    assert thread_count(None, {}) == AFFINITY


def test_omp_num_threads_caps_the_default():
    assert thread_count(None, {"OMP_NUM_THREADS": "1"}) == 1
    assert thread_count(None, {"OMP_NUM_THREADS": str(AFFINITY + 8)}) == AFFINITY  # a cap, never a raise
    assert thread_count(None, {"OMP_NUM_THREADS": "junk"}) == AFFINITY  # not a number: torch ignores it too


def test_requested_wins():
    assert thread_count(3, {"OMP_NUM_THREADS": "1"}) == 3


def test_every_computing_command_takes_threads():
    assert COMPUTING <= set(COMMANDS)
    for name in COMMANDS:
        p = build_parser([name])
        sub = next(a for a in p._subparsers._group_actions).choices[name]
        flags = {o for a in sub._actions for o in a.option_strings}
        assert ("--threads" in flags) == (name in COMPUTING), name


def test_threads_is_set_before_the_command(tmp_path, capsys, keep_threads):
    folder = shutil.copytree(BASIC, tmp_path / "basic")
    torch.set_num_threads(AFFINITY)
    assert main(["composite", str(folder), "--threads", "1"]) == 0
    assert torch.get_num_threads() == 1


def test_default_follows_omp_num_threads(tmp_path, capsys, keep_threads, monkeypatch):
    folder = shutil.copytree(BASIC, tmp_path / "basic")
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    torch.set_num_threads(AFFINITY + 1)
    assert main(["composite", str(folder)]) == 0
    assert torch.get_num_threads() == 1


def test_a_fresh_process_gets_its_threads_without_torch_before_the_command(tmp_path):
    """In a fresh process torch is not imported until the command needs it: ``--threads`` reaches it through
    ``OMP_NUM_THREADS`` (torch reads it at import), and a refusal before any tensor work (a broken stack.json, an
    edit of a file that is no image, of an unknown preset or label, a re-light of a stack without a surface layer, a
    normal map that is no PNG, a broken PSD, an editor of a broken stack, a training command's unknown task, a world
    of an unknown split or task or no scenes) never
    imports torch (~1.5 s:
    `benchmarks/hostile.py`'s bombs' time bound)."""
    import importlib.util
    import subprocess
    import sys

    code = (
        "import sys, lasagna.cli as c\n"
        "rc = c.main(sys.argv[1:])\n"
        "t = sys.modules.get('torch')\n"
        "print(rc, None if t is None else t.get_num_threads())\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}

    def composite(folder: Path) -> list[str]:
        argv = [sys.executable, "-c", code, "composite", str(folder), "--threads", "1"]
        done = subprocess.run(argv, env=env, capture_output=True, text=True)
        return done.stdout.splitlines()[-1].split()  # after the command's own output

    assert composite(shutil.copytree(BASIC, tmp_path / "basic")) == ["0", "1"]
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "stack.json").write_text("{")
    assert composite(bad) == ["2", "None"]
    eps = tmp_path / "l.eps"
    eps.write_bytes(b"%!PS-Adobe-3.0 EPSF-3.0\n")  # an edit of what is no image is refused before any tensor
    argv = [sys.executable, "-c", code, "edit", str(eps), "--condition", "left", "-o", str(tmp_path / "o")]
    done = subprocess.run(argv, env=env, capture_output=True, text=True)
    assert done.stdout.split() == ["2", "None"] and "cannot decode" in done.stderr
    argv = [sys.executable, "-c", code, "light", str(tmp_path / "basic"), "--light", "left"]  # no surface layer
    done = subprocess.run(argv, env=env, capture_output=True, text=True)
    assert done.stdout.split() == ["2", "None"] and "no surface layer" in done.stderr
    (tmp_path / "map.png").write_bytes(b"not a png")
    argv = [sys.executable, "-c", code, "add-surface", str(tmp_path / "basic"), str(tmp_path / "map.png")]
    done = subprocess.run(argv, env=env, capture_output=True, text=True)
    assert done.stdout.split() == ["2", "None"] and "not a PNG" in done.stderr
    photo = Path(__file__).resolve().parents[2] / "examples" / "photos" / "chelsea.png"
    argv = [sys.executable, "-c", code, "edit", str(photo), "--layer", "nosuch", "-o", str(tmp_path / "o")]
    done = subprocess.run(argv, env=env, capture_output=True, text=True)
    assert done.stdout.split() == ["2", "None"] and "no preset named 'nosuch'" in done.stderr
    argv = [sys.executable, "-c", code, "edit", str(photo), "--condition", "sideways", "-o", str(tmp_path / "o")]
    done = subprocess.run(argv, env=env, capture_output=True, text=True)
    assert done.stdout.split() == ["2", "None"] and "got 'sideways'" in done.stderr
    for argv, needle in (  # the training commands' typing mistakes: their task table is read torch-free
        (["train-prior", "--task", "nope", "--out", str(tmp_path / "t")], "invalid choice: 'nope'"),
        (["train-corrective", "--prior", "x", "--task", "nope", "--out", str(tmp_path / "t")], "invalid choice"),
        # the world's typing mistakes: its split and task names are read torch-free (lasagna.world.names)
        (["world", "-o", str(tmp_path / "t"), "--split", "nope", "--count", "1"], "invalid choice: 'nope'"),
        (["world", "-o", str(tmp_path / "t"), "--split", "far", "--count", "1", "--task", "x"], "invalid choice"),
        (["world", "-o", str(tmp_path / "t"), "--split", "far", "--count", "0"], "--count: expected a positive"),
    ):
        done = subprocess.run([sys.executable, "-c", code, *argv], env=env, capture_output=True, text=True)
        assert done.stdout.split() == ["2", "None"] and needle in done.stderr and not (tmp_path / "t").exists()
    if importlib.util.find_spec("uvicorn") is not None:
        for target in (bad, photo.with_name("missing.png")):  # a broken stack, no file: before the editor loads
            done = subprocess.run(
                [sys.executable, "-c", code, "serve", str(target)], env=env, capture_output=True, text=True
            )
            assert done.stdout.split() == ["2", "None"] and done.stderr.count("\n") == 1
    if importlib.util.find_spec("psd_tools") is not None:
        (tmp_path / "broken.psd").write_bytes(b"8BPS")
        argv = [sys.executable, "-c", code, "import-psd", str(tmp_path / "broken.psd"), "-o", str(tmp_path / "p")]
        done = subprocess.run(argv, env=env, capture_output=True, text=True)
        assert done.stdout.split() == ["2", "None"] and "psd-tools cannot read it" in done.stderr


@pytest.mark.parametrize("bad", ["0", "-2", "two"])
def test_threads_must_be_positive(capsys, bad):
    assert main(["composite", str(BASIC), "--threads", bad]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--threads" in err and "expected a positive integer" in err
