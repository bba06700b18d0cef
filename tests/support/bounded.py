"""Time bounds a loaded machine does not trip.

A slow or shared machine (two cores, a training job beside the suite) stretches wall-clock time, not the
work a call does. So a bound on a computation is on its CPU time (``within``, ``cpu_seconds``), and a
wall-clock bound is kept only to stop a hang: ``HANG_SECONDS``, far past what any child process or wait
of the default suite takes there (the slowest, a two-process batch edit, takes about a minute)."""

from __future__ import annotations

import signal
import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")

# Wall-clock seconds after which a child process or a wait counts as hung (a failure, not a slow machine).
HANG_SECONDS = 900


def cpu_seconds() -> float:
    """This process's CPU time (all threads, user + system): what a bound on work is measured in."""
    return time.process_time()


def within(seconds: float, fn: Callable[[], T]) -> T:
    """``fn()``, raising ``TimeoutError`` once it has used more than ``seconds`` of this process's CPU time
    (SIGPROF from ITIMER_PROF: main thread, POSIX) — a loop fails the test instead of hanging the suite."""

    def _stop(*_):
        raise TimeoutError(f"still running after {seconds} CPU seconds")

    old = signal.signal(signal.SIGPROF, _stop)
    signal.setitimer(signal.ITIMER_PROF, seconds)
    try:
        return fn()
    finally:
        signal.setitimer(signal.ITIMER_PROF, 0)
        signal.signal(signal.SIGPROF, old)
