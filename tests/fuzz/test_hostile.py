"""Fuzzing the CLI with hostile input (#16): stack folders, PNG files and .ora archives, valid and then
mutated (tests/fuzz/hostile.py), each run by the real ``lasagna.cli.main`` in a forked child under a
memory ceiling and a time limit. Every command must end with status 0 or 2, at most one error line
on stderr (besides one-line warnings), never an internal error or a traceback, and never hang.

The default suite runs a few derandomised examples of each; the ``slow`` variants run
``LASAGNA_FUZZ_EXAMPLES`` (default 3500) of each, as ``benchmarks/hostile.py`` does."""

from __future__ import annotations

import os
import warnings

import pytest
from hypothesis import HealthCheck, given, settings

from tests.fuzz import hostile

DEFAULT_EXAMPLES = 25
SLOW_EXAMPLES = int(os.environ.get("LASAGNA_FUZZ_EXAMPLES", "3500"))


@pytest.fixture(scope="module")
def env(tiny) -> dict[str, str]:
    """The child's environment: the tiny catalogue first (``lasagna edit`` runs in milliseconds), the
    default memory budget."""
    return {"LASAGNA_LAYERS": str(tiny)}


@pytest.fixture(scope="module")
def oras() -> list[dict[str, bytes]]:
    return hostile.base_oras()


def _fuzz(strategy, env: dict[str, str], examples: int, derandomize: bool) -> None:
    @settings(
        max_examples=examples,
        derandomize=derandomize,
        deadline=None,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )
    @given(strategy)
    def case(c):
        files, commands = c
        hostile.check(hostile.run_case(files, commands, env))

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # zipfile's "Duplicate name", meant here
        case()


KINDS = ["stack", "png", "ora"]


def _strategy(kind: str, oras):
    return {"stack": hostile.stack_cases(), "png": hostile.png_cases(), "ora": hostile.ora_cases(oras)}[kind]


@pytest.mark.parametrize("kind", KINDS)
def test_fuzz(kind, env, oras):
    _fuzz(_strategy(kind, oras), env, DEFAULT_EXAMPLES, derandomize=True)


@pytest.mark.slow
@pytest.mark.parametrize("kind", KINDS)
def test_fuzz_long(kind, env, oras):
    _fuzz(_strategy(kind, oras), env, SLOW_EXAMPLES, derandomize=False)


def test_a_case_forked_while_the_parents_openmp_pool_runs_does_not_deadlock(tmp_path):
    """The harness forks: a child of a process whose OpenMP pool is running (torch on two threads before the fork)
    would deadlock in its first parallel region (libgomp is not fork-safe) — it must compute on one thread and
    answer. Found when ``-m slow`` ran at OMP_NUM_THREADS=2: fuzz_long[png] hung after the fused kernels' tests."""
    import torch

    from lasagna.io.stack import Stack

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        x = torch.rand(1500, 1500)
        assert float((x @ x).sum()) > 0  # the parent's pool is up
        Stack.from_image(torch.rand(3, 384, 384)).save(tmp_path / "s")
        files = {
            p.relative_to(tmp_path / "s").as_posix(): p.read_bytes() for p in (tmp_path / "s").rglob("*") if p.is_file()
        }
        results = hostile.run_case(files, [["composite", "{d}", "-o", "{d}/c.png"]], env={"OMP_NUM_THREADS": "2"})
    finally:
        torch.set_num_threads(before)
    assert results[0][1] == 0, results


def test_the_worker_reports_what_breaks_the_contract():
    """The harness itself: a hang, an internal error and a two-line stderr are caught (else the fuzz
    tests above could pass by checking nothing)."""
    ok = hostile.run_case({}, [["validate", "{d}/missing"]])
    assert ok[0][1] == 2 and "lasagna" in ok[0][3]
    hostile.check(ok)
    for bad in [
        [(["x"], 1, "", "lasagna: error: x\n")],
        [(["x"], 2, "", "lasagna: error: internal error (KeyError: 'a')\n")],
        [(["x"], 2, "", "lasagna: error: a\nsecond line\n")],
        [(["x"], 2, "", "lasagna: warning: w\n")],
        [(["x"], 2, "", "")],
    ]:
        with pytest.raises(AssertionError):
            hostile.check(bad)


def test_the_worker_enforces_memory_and_time(monkeypatch):
    import time

    import lasagna.cli.validate as validate_command

    def spin(args):
        while True:
            pass

    # The child is a fork: what is patched here is what it runs.
    monkeypatch.setattr(validate_command, "run", lambda args: bytearray(4 * 2**30) and 0)
    [(_, code, _, err)] = hostile.run_case({}, [["validate", "{d}"]])
    assert code == 2 and "out of memory (MemoryError" in err  # the ceiling held: 4 GiB was refused
    monkeypatch.setattr(hostile, "CASE_CPU_SECONDS", 1)
    monkeypatch.setattr(validate_command, "run", spin)  # a loop: stopped by its CPU time, however loaded
    with pytest.raises(AssertionError, match="within 1 CPU seconds \\(a hang\\)"):
        hostile.run_case({}, [["validate", "{d}"]])
    monkeypatch.setattr(hostile, "HANG_SECONDS", 1)
    monkeypatch.setattr(validate_command, "run", lambda args: time.sleep(600))  # a wait that spends no CPU
    with pytest.raises(AssertionError, match="within 1 s \\(a hang\\)"):
        hostile.run_case({}, [["validate", "{d}"]])
