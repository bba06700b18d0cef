"""lasagna.limits: sizes as written and printed, the memory budget's precedence (scope > environment >
default), the refusal's one line, and which failures count as out of memory."""

from __future__ import annotations

import pytest

from lasagna.errors import LasagnaError
from lasagna.limits import (
    DEFAULT_MEMORY_BUDGET,
    MEMORY_BUDGET_ENV,
    BudgetError,
    check_memory,
    format_size,
    is_out_of_memory,
    memory_budget,
    memory_budget_scope,
    parse_size,
)


@pytest.fixture(autouse=True)
def _no_env_budget(monkeypatch):
    monkeypatch.delenv(MEMORY_BUDGET_ENV, raising=False)


@pytest.mark.parametrize(
    "text, expected",
    [
        ("8G", 8 * 2**30),
        ("512M", 512 * 2**20),
        ("3.5GB", int(3.5 * 2**30)),
        ("1GiB", 2**30),
        ("1gib", 2**30),
        ("1048576", 1048576),
        (" 12 K ", 12 * 2**10),
        ("2T", 2 * 2**40),
    ],
)
def test_parse_size(text, expected):
    assert parse_size(text) == expected


@pytest.mark.parametrize("text", ["", "1x", "G", "-1G", "1.2.3M", "1e9", "0", "0.0001", "8 GG", "nan"])
def test_parse_size_refuses_in_one_line(text):
    with pytest.raises(LasagnaError) as info:
        parse_size(text, where="--memory-budget")
    message = str(info.value)
    assert "\n" not in message and "--memory-budget" in message and "expected" in message


def test_format_size():
    assert format_size(0) == "0 B"
    assert format_size(1023) == "1023 B"
    assert format_size(2**10) == "1.0 KB"
    assert format_size(100 * 2**20) == "100.0 MB"
    assert format_size(int(12.9 * 2**30)) == "12.9 GB"
    assert format_size(3 * 2**40) == "3.0 TB"


def test_format_parse_round_trip():
    for n in (2**10, 5 * 2**20, 7 * 2**30):
        assert parse_size(format_size(n).replace(" ", "")) == n


def test_budget_precedence(monkeypatch):
    assert memory_budget() == DEFAULT_MEMORY_BUDGET == 8 * 2**30
    monkeypatch.setenv(MEMORY_BUDGET_ENV, "2G")
    assert memory_budget() == 2 * 2**30
    with memory_budget_scope("100M") as value:
        assert value == memory_budget() == 100 * 2**20
        with memory_budget_scope(4096):
            assert memory_budget() == 4096
        with memory_budget_scope(None) as same:
            assert same == memory_budget() == 100 * 2**20
        assert memory_budget() == 100 * 2**20
    assert memory_budget() == 2 * 2**30
    monkeypatch.setenv(MEMORY_BUDGET_ENV, "lots")
    with pytest.raises(LasagnaError, match=MEMORY_BUDGET_ENV):
        memory_budget()


def test_scope_is_reset_after_an_error():
    with pytest.raises(ZeroDivisionError), memory_budget_scope("1M"):
        1 / 0
    assert memory_budget() == DEFAULT_MEMORY_BUDGET


def test_check_memory():
    with memory_budget_scope("1M"):
        check_memory(2**20, "exactly the budget", "here")  # at the budget: allowed
        with pytest.raises(BudgetError) as info:
            check_memory(3 * 2**20, "decoding a 1x1 image", "x.png")
    message = str(info.value)
    assert "\n" not in message
    for part in ("x.png", "decoding a 1x1 image", "~3.0 MB", "1.0 MB", "--memory-budget", MEMORY_BUDGET_ENV):
        assert part in message, part


class OutOfMemoryError(RuntimeError):
    """A stand-in with torch.OutOfMemoryError's name (the check goes by name, not by import)."""


@pytest.mark.parametrize(
    "exc, expected",
    [
        (MemoryError(), True),
        (RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried to allocate 12 bytes"), True),
        (RuntimeError("CUDA out of memory. Tried to allocate 2.00 GiB"), True),
        (OutOfMemoryError("whatever"), True),
        (RuntimeError("expected scalar type Float but found Double"), False),
        (ValueError("bad value"), False),
        (RecursionError("maximum recursion depth exceeded"), False),
    ],
)
def test_is_out_of_memory(exc, expected):
    assert is_out_of_memory(exc) is expected
