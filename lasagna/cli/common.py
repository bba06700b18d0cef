"""What the command modules share: the program's name, warnings on stderr, the progress switch, the thread
policy and the arguments several commands take (``--threads``, ``--max-pixels``, the distillation overrides)."""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import threading
import time
from collections.abc import Iterator, Mapping

PROG = "lasagna"


def warn(message: str) -> None:
    """A warning line on stderr: ``lasagna: warning: …``."""
    print(f"{PROG}: warning: {message}", file=sys.stderr)


def one_line(text: str) -> str:
    return " ".join(text.split())


_forced_progress = False


def set_progress(forced: bool) -> None:
    """``--progress``: report progress even when stderr is not a terminal (a log file, a CI job)."""
    global _forced_progress
    _forced_progress = bool(forced)


def progress() -> bool:
    """Progress reports for a person watching (stderr is a terminal), or where ``--progress`` asked for them."""
    return _forced_progress or sys.stderr.isatty()


# A phase that ends sooner says nothing: only waits a person would notice get a line.
PHASE_QUIET_SECONDS = 1.0


@contextlib.contextmanager
def phase(what: str, *, bar: bool = False) -> Iterator[None]:
    """Report a phase of a command on stderr when ``progress()``: once it has run ``PHASE_QUIET_SECONDS``, one line
    ``lasagna: WHAT… done in N s`` (its start shown at that second, its end appended). ``bar``: the phase draws a
    progress bar of its own below the line, so the start ends its line and the end is a line of its own."""
    if not progress():
        yield
        return
    start = time.monotonic()
    shown = threading.Event()

    def show() -> None:
        shown.set()
        print(f"{PROG}: {what}…", end="\n" if bar else "", file=sys.stderr, flush=True)

    timer = threading.Timer(0.0 if bar else PHASE_QUIET_SECONDS, show)
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
        timer.join()  # a start being printed is finished before the end is
        if shown.is_set():
            seconds = time.monotonic() - start
            print(f"{PROG}: {what} done in {seconds:.1f} s" if bar else f" done in {seconds:.1f} s", file=sys.stderr)


def progress_argument(p: argparse.ArgumentParser) -> None:
    """``--progress``: progress lines and bars even when stderr is not a terminal."""
    p.add_argument(
        "--progress",
        action="store_true",
        help="report progress on stderr even when it is not a terminal (default: only on a terminal)",
    )


# The commands that compute with torch, and so take ``--threads``: the others read, write or list.
COMPUTING = frozenset(
    {"composite", "export", "edit", "render", "serve", "demo", "world"}
    | {"train-prior", "train-corrective", "train-layer", "train-surface"}
)


def thread_count(requested: int | None = None, environ: Mapping[str, str] | None = None) -> int:
    """Torch's intra-op threads for this process: ``requested`` (``--threads``) when given, else the cores this
    process may run on (``os.sched_getaffinity``), capped by ``OMP_NUM_THREADS`` when that is set.

    Torch's own default is every core of the machine, whatever the process's affinity, and each busy thread
    beyond the free cores is time-sliced against the others: with two busy processes on 2 vCPUs a 512² edit
    took 57.9 s at torch's default and 4.9 s on one thread (issue 27). How many cores other processes keep busy
    is not knowable here, so the default is the affinity count and ``--threads`` / ``OMP_NUM_THREADS`` lower it.
    """
    if requested is not None:
        return requested
    env = os.environ if environ is None else environ
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    omp = env.get("OMP_NUM_THREADS", "").strip()
    if omp.isdigit() and int(omp) >= 1:
        cores = min(cores, int(omp))
    return max(1, cores)


def positive_int(text: str) -> int:
    """An argument's type: an integer of at least 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def threads_argument(p: argparse.ArgumentParser) -> None:
    """``--threads``: torch's intra-op threads (``thread_count``)."""
    p.add_argument(
        "--threads",
        type=positive_int,
        metavar="N",
        help="CPU threads for torch (default: the cores this process may use, at most $OMP_NUM_THREADS; "
        "lower it when other work is running)",
    )


def set_threads(requested: int | None) -> int:
    """Set torch's intra-op threads by the policy of ``thread_count``; returns the number set.

    Before torch is imported this only sets ``OMP_NUM_THREADS`` (and ``MKL_NUM_THREADS``), which torch and its
    OpenMP runtime read when they load — the same thread count, and a command that refuses its input before any
    tensor work (a memory estimate, a bad file) never pays torch's import (~1.5 s on this project's boxes)."""
    import sys

    n = thread_count(requested)
    torch = sys.modules.get("torch")
    if torch is None:
        os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = str(n)
    elif torch.get_num_threads() != n:
        torch.set_num_threads(n)
    return n


def max_pixels_argument(p: argparse.ArgumentParser) -> None:
    from lasagna.io.png import DEFAULT_MAX_PIXELS

    p.add_argument(
        "--max-pixels",
        type=int,
        default=DEFAULT_MAX_PIXELS,
        metavar="N",
        help=f"refuse any PNG with more than N pixels before decoding it (default {DEFAULT_MAX_PIXELS})",
    )


def depth_argument(p: argparse.ArgumentParser, what: str) -> None:
    """``--depth 8|16``: the bits a channel of ``what`` (a composite PNG, a PSD)."""
    p.add_argument(
        "--depth",
        type=int,
        choices=(8, 16),
        default=8,
        help=f"bits a channel of {what} (default 8; 16 keeps 16-bit inputs and smooth gradients)",
    )


def loss_argument(p: argparse.ArgumentParser, help: str) -> None:
    """``--loss`` with the registered loss names (``lasagna.document.preset.LOSS_NAMES``) as its choices."""
    from lasagna.document.preset import LOSS_NAMES

    p.add_argument("--loss", choices=LOSS_NAMES, help=help)


def distill_arguments(p: argparse.ArgumentParser) -> None:
    """The per-image run's overrides of a preset's ``distill`` defaults (``edit``)."""
    loss_argument(p, "score-distillation loss (default: the preset's)")
    p.add_argument(
        "--guidance", type=float, metavar="W", help="guidance weight ω in ε_u + ω(ε_c − ε_u) (default: the preset's)"
    )
    p.add_argument("--seed", type=int, metavar="S", help="seed of the per-image run (default: the preset's)")
    p.add_argument("--lr", type=float, help="Adam learning rate of the per-image run (default: the preset's)")
    device_argument(p)


def torch_device(text: str) -> str:
    """``--device``'s type: a device torch can name *and* this machine has (checked at parse time, so a
    bogus name or CUDA on a CPU-only machine is one line, not a failure after loading everything)."""
    if text == "cpu":
        return text  # always there; and parsing the default must not import torch
    from lasagna.errors import LasagnaError
    from lasagna.learned import check_device

    try:
        return check_device(text)
    except LasagnaError as err:
        raise argparse.ArgumentTypeError(err.message) from None


def device_argument(p: argparse.ArgumentParser, default: str | None = "cpu", help: str = "torch device (default cpu)"):
    """``--device``, checked against this machine (``torch_device``)."""
    p.add_argument("--device", type=torch_device, default=default, help=help)


def memory_budget_argument(p: argparse.ArgumentParser) -> None:
    """``--memory-budget``: every command's ceiling on what it may allocate (``lasagna.limits``)."""
    p.add_argument(
        "--memory-budget",
        metavar="SIZE",
        help="refuse work estimated to need more memory than SIZE, e.g. 12G (default $LASAGNA_MEMORY_BUDGET, else 8G)",
    )


def example_epilog(example: str | tuple[str, ...]) -> str:
    """A help text's closing lines: ``example:`` and each command line of ``example`` indented below it."""
    lines = (example,) if isinstance(example, str) else example
    return "example:\n" + "\n".join(f"  {line}" for line in lines)


def add_command(subparsers, name: str, command, *, arguments: bool = True) -> argparse.ArgumentParser:
    """Register the command module ``command`` (``HELP``, ``EXAMPLE``, ``add_arguments``, ``run``) as ``name``;
    with ``arguments`` false only its name and help are listed (its arguments may import its tier). ``--help``
    ends with the example (its lines kept as written)."""
    p = subparsers.add_parser(
        name,
        help=command.HELP,
        description=command.HELP,
        epilog=example_epilog(command.EXAMPLE),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    if arguments:
        command.add_arguments(p)
        memory_budget_argument(p)
        if name in COMPUTING:
            threads_argument(p)
            progress_argument(p)
    p.set_defaults(run=command.run)
    return p
