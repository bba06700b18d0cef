"""The CLI's hostile-input edges (#16): ``--device`` checked at parse time, ``--memory-budget`` on every
command, and failures the budget did not foresee (out of memory, recursion) as one line, exit 2."""

from __future__ import annotations

import pytest
import torch

import lasagna.cli.validate as validate_command
from lasagna.cli import COMMANDS, main
from tests.support.stackcraft import write_stack


def run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _one_line_error(code: int, err: str, *parts: str) -> None:
    assert code == 2, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err and "internal error" not in err, err
    for part in parts:
        assert part in err, (part, err)


def _solid(folder, side: int):
    return write_stack(
        folder,
        {
            "format": "lasagna.stack",
            "version": 1,
            "canvas": {"width": side, "height": side},
            "layers": [{"id": "fill", "kind": "solid", "color": [0.1, 0.2, 0.3]}],
        },
    )


@pytest.mark.parametrize("device, message", [("bogus", "is not a torch device"), ("gpu:7", "is not a torch device")])
def test_bogus_device_is_one_line(tmp_path, capsys, device, message):
    _one_line_error(*run(capsys, "render", tmp_path, "--device", device)[::2], "argument --device", message)


@pytest.mark.parametrize("device", ["cuda", "cuda:0", "cuda:3"])
def test_cuda_on_a_machine_without_it_is_one_line(tmp_path, capsys, monkeypatch, device):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    code, _, err = run(capsys, "render", tmp_path, "--device", device)
    _one_line_error(code, err, "this machine has no CUDA device; expected cpu")


def test_cpu_device_is_accepted_at_parse_time(tmp_path, capsys):
    code, _, err = run(capsys, "render", tmp_path / "missing", "--device", "cpu")
    _one_line_error(code, err)
    assert "--device" not in err  # the refusal is about the missing stack, not the device


@pytest.mark.parametrize("budget", ["1x", "-5G", "0", "lots"])
def test_bad_memory_budget_is_one_line(tmp_path, capsys, budget):
    _solid(tmp_path, 4)
    code, _, err = run(capsys, "composite", tmp_path, f"--memory-budget={budget}")
    _one_line_error(code, err, "memory budget", repr(budget))
    assert not (tmp_path / "composite.png").exists()


def test_every_command_takes_memory_budget(capsys):
    for name in COMMANDS:
        code, out, _ = run(capsys, name, "--help")
        assert code == 0 and "--memory-budget" in out, name


def test_memory_budget_refuses_a_2048_composite(tmp_path, capsys):
    # A 2048² canvas is estimated at ~60 MB (float32 RGB plus codes; lasagna.io.render.composite_bytes),
    # measured ~110 MB over the imports' baseline in a child process: 50M refuses it, 200M lets it run.
    _solid(tmp_path, 2048)
    code, _, err = run(capsys, "composite", tmp_path, "--memory-budget", "50M")
    _one_line_error(code, err, "rendering its 2048x2048 canvas", "needs ~60.0 MB", "over the memory budget of 50.0 MB")
    assert not (tmp_path / "composite.png").exists()
    code, _, err = run(capsys, "composite", tmp_path, "--memory-budget", "200M")
    assert code == 0, err


def test_environment_budget_and_the_option_over_it(tmp_path, capsys, monkeypatch):
    _solid(tmp_path, 2048)
    monkeypatch.setenv("LASAGNA_MEMORY_BUDGET", "50M")
    _one_line_error(*run(capsys, "composite", tmp_path)[::2], "over the memory budget of 50.0 MB")
    assert run(capsys, "composite", tmp_path, "--memory-budget", "1G")[0] == 0


@pytest.mark.parametrize(
    "exc, parts",
    [
        (
            RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried to allocate 12 bytes"),
            ["validate: out of memory (RuntimeError: DefaultCPUAllocator", "see --memory-budget"],
        ),
        (MemoryError(), ["validate: out of memory (MemoryError"]),
        (RecursionError("maximum recursion depth exceeded"), ["validate: input nested too deeply"]),
    ],
)
def test_unforeseen_failures_are_one_line(tmp_path, capsys, monkeypatch, exc, parts):
    def fail(args):
        raise exc

    monkeypatch.setattr(validate_command, "run", fail)
    _one_line_error(*run(capsys, "validate", tmp_path)[::2], *parts)


def test_other_runtime_errors_are_still_internal_errors(tmp_path, capsys, monkeypatch):
    def fail(args):
        raise RuntimeError("expected scalar type Float")

    monkeypatch.delenv("LASAGNA_DEBUG", raising=False)
    monkeypatch.setattr(validate_command, "run", fail)
    code, _, err = run(capsys, "validate", tmp_path)
    assert code == 2 and "internal error (RuntimeError: expected scalar type Float)" in err
