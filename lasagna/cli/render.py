"""``lasagna render``: render a stack's learned layers from their stored generator and settings — those not
rendered yet (no ``source``, or its PNG missing: e.g. a layer added to stack.json by hand, or a PNG deleted to
have it made again), or every one with ``--all``."""

from __future__ import annotations

import argparse
import os

from lasagna.cli.common import device_argument, progress, warn
from lasagna.errors import PathError

HELP = "render a stack's learned layers from their stored generator and settings"
EXAMPLE = (
    "lasagna render out/chelsea-free         # the learned layers not rendered yet",
    "lasagna render out/chelsea-free --all   # every learned layer, from its stored settings",
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("stack", help="stack folder or its stack.json")
    p.add_argument(
        "--all",
        action="store_true",
        help="re-render every learned layer from its stored settings (default: only those not rendered yet: "
        "no source, or its PNG missing)",
    )
    device_argument(p)


def run(args: argparse.Namespace) -> int:
    from lasagna.document import stack_file
    from lasagna.io.survey import survey_stack

    # refused here without loading torch; a learned layer whose PNG is missing is one to render
    survey = survey_stack(args.stack, composite=True, unrendered=True)

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
        learned = [layer.id for _, layer in stack.document.walk() if layer.kind == "learned"]
        surfaces = [layer.id for _, layer in stack.document.walk() if layer.kind == "surface"]
        if learned:
            why = f"every learned layer ({', '.join(learned)}) has its pixels; --all re-renders them (stored settings)"
        elif surfaces:  # what `lasagna edit` makes by default: nothing here for render to make
            why = f"the stack has no learned layer (its surface layers, {', '.join(surfaces)}, are lit when composited)"
        else:
            why = "the stack has no learned layer"
        print(f"nothing to render: {why}; wrote {folder / 'composite.png'}")
        return 0
    print(f"rendered {', '.join(ids)}; wrote their PNGs, {folder / 'stack.json'} and {folder / 'composite.png'}")
    return 0
