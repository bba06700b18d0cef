"""``lasagna render``: render a stack's learned layers from their stored generator and settings."""

from __future__ import annotations

import argparse
import os

from lasagna.cli.common import device_argument, progress, warn
from lasagna.errors import PathError

HELP = "render a stack's learned layers from their stored generator and settings"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("stack", help="stack folder or its stack.json")
    p.add_argument("--all", action="store_true", help="re-render every learned layer, not only those without pixels")
    device_argument(p)


def run(args: argparse.Namespace) -> int:
    from lasagna.document import stack_file
    from lasagna.io.survey import survey_stack

    survey = survey_stack(args.stack, composite=True)  # refused here without loading torch

    from lasagna.editing import render_learned
    from lasagna.io.stack import load_surveyed

    stack = load_surveyed(survey)
    folder = stack_file(args.stack).parent
    if not os.access(folder, os.W_OK | os.X_OK):
        raise PathError("is not writable; expected a stack folder render can write into", str(folder))
    stack, ids = render_learned(stack, all=args.all, device=args.device, progress=progress(), warn=warn)
    if not ids:
        from lasagna.io.render import write_composite

        write_composite(stack.render(), folder / "composite.png")
        print(f"no learned layer to render (use --all to re-render); wrote {folder / 'composite.png'}")
        return 0
    print(f"rendered {', '.join(ids)}; wrote their PNGs, {folder / 'stack.json'} and {folder / 'composite.png'}")
    return 0
