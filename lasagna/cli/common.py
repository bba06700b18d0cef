"""What the command modules share: the program's name, warnings on stderr, the progress switch and the
arguments several commands take (``--max-pixels``, the distillation overrides)."""

from __future__ import annotations

import argparse
import sys

PROG = "lasagna"


def warn(message: str) -> None:
    """A warning line on stderr: ``lasagna: warning: …``."""
    print(f"{PROG}: warning: {message}", file=sys.stderr)


def one_line(text: str) -> str:
    return " ".join(text.split())


def progress() -> bool:
    """Progress bars only for a person watching (stderr is a terminal)."""
    return sys.stderr.isatty()


def max_pixels_argument(p: argparse.ArgumentParser) -> None:
    from lasagna.io.png import DEFAULT_MAX_PIXELS

    p.add_argument(
        "--max-pixels",
        type=int,
        default=DEFAULT_MAX_PIXELS,
        metavar="N",
        help=f"refuse any PNG with more than N pixels before decoding it (default {DEFAULT_MAX_PIXELS})",
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


def add_command(subparsers, name: str, command, *, arguments: bool = True) -> argparse.ArgumentParser:
    """Register the command module ``command`` (``HELP``, ``add_arguments``, ``run``) as ``name``; with
    ``arguments`` false only its name and help are listed (its arguments may import its tier)."""
    p = subparsers.add_parser(name, help=command.HELP, description=command.HELP)
    if arguments:
        command.add_arguments(p)
        memory_budget_argument(p)
    p.set_defaults(run=command.run)
    return p
