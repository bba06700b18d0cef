"""``lasagna demo``: relight, colourise and light the bundled examples (``lasagna.demo``); falls back to
compositing and exporting the example stack when no learned layer can run."""

from __future__ import annotations

import argparse

from lasagna.cli.common import warn
from lasagna.errors import LasagnaError

HELP = "relight, colourise and light the bundled examples; writes stacks and one sheet to look at"
EXAMPLE = "lasagna demo -o out/demo"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", default="out/demo", metavar="DIR", help="output folder (default out/demo)")
    p.add_argument(
        "--steps",
        type=int,
        default=None,
        metavar="N",
        help="per-image steps for a preset whose default is a per-image layer (default: the preset's)",
    )


def run(args: argparse.Namespace) -> int:
    from lasagna.demo import run_demo
    from lasagna.io.folder import check_writable

    out = check_writable(args.output, folder=True)
    if args.steps is not None and args.steps < 1:
        raise LasagnaError(f"expected a positive integer, got {args.steps}", where="--steps")
    run_demo(out, steps=args.steps, say=print, warn=warn)
    return 0
