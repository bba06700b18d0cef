"""``lasagna composite``: render a stack's composite PNG."""

from __future__ import annotations

import argparse
from pathlib import Path

from lasagna.cli.common import depth_argument, max_pixels_argument

HELP = "render a stack's composite PNG"
EXAMPLE = "lasagna composite examples/stacks/basic -o out.png -v   # -v lists skipped layers and why"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("stack", help="stack folder or its stack.json")
    p.add_argument("-o", "--output", help="PNG to write (default: STACK/composite.png)")
    p.add_argument("-v", "--verbose", action="store_true", help="list evaluated and skipped layers")
    depth_argument(p, "the PNG (RGBA for a transparent document)")
    max_pixels_argument(p)


def run(args: argparse.Namespace) -> int:
    from lasagna.document import stack_file
    from lasagna.io.folder import check_writable
    from lasagna.io.survey import survey_stack

    out = Path(args.output) if args.output else stack_file(args.stack).parent / "composite.png"
    check_writable(out)
    survey = survey_stack(args.stack, max_pixels=args.max_pixels, composite=True)  # a refusal needs no torch

    from lasagna.io.folder import check_not_input
    from lasagna.io.render import render_stack, write_composite
    from lasagna.io.stack import load_surveyed

    stack = load_surveyed(survey)
    check_not_input([out], stack)
    result = render_stack(stack)
    write_composite(result, out, depth=args.depth)
    total = len(stack.document.all_ids)
    kind = f"{'RGBA' if result.alpha is not None else 'RGB'}, {args.depth}-bit"
    print(f"wrote {out} ({stack.width}x{stack.height} {kind}, {len(result.evaluated)} of {total} layers composed)")
    if args.verbose:
        print(f"composed: {', '.join(result.evaluated) or '(none)'}")
        for id, reason in result.skipped.items():
            print(f"skipped: {id}: {reason}")
    return 0
