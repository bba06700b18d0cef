"""``within``: run a call that must finish, failing (not hanging the suite) when it loops."""

from __future__ import annotations

import signal
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")


def within(seconds: int, fn: Callable[[], T]) -> T:
    """``fn()``, raising ``TimeoutError`` if it runs longer than ``seconds`` (SIGALRM: main thread, POSIX)."""

    def _stop(*_):
        raise TimeoutError(f"still running after {seconds} s")

    old = signal.signal(signal.SIGALRM, _stop)
    signal.alarm(seconds)
    try:
        return fn()
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
