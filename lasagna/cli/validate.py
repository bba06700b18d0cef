"""``lasagna validate``: check a stack's document and every PNG it names ("ok: N layers")."""

from __future__ import annotations

import argparse

from lasagna.cli.common import max_pixels_argument

HELP = "check a stack's document and every PNG it names"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("stack", help="stack folder or its stack.json")
    max_pixels_argument(p)


def run(args: argparse.Namespace) -> int:
    from lasagna.io.stack import load_stack

    stack = load_stack(args.stack, max_pixels=args.max_pixels)
    doc = stack.document
    extra = f"; {len(stack.not_rendered)} learned layer(s) not rendered" if stack.not_rendered else ""
    print(
        f"ok: {len(doc.layers)} layers ({doc.canvas.width}x{doc.canvas.height}, blend_space={doc.blend_space}){extra}"
    )
    return 0
