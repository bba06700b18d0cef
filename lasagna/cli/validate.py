"""``lasagna validate``: check a stack's document and every PNG it names ("ok: N layers")."""

from __future__ import annotations

import argparse

from lasagna.cli.common import max_pixels_argument

HELP = "check a stack's document and every PNG it names"
EXAMPLE = 'lasagna validate examples/stacks/basic   # "ok: 5 layers", or one line saying what is wrong'


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("stack", help="stack folder or its stack.json")
    max_pixels_argument(p)


def run(args: argparse.Namespace) -> int:
    from lasagna.document.models import LearnedLayer
    from lasagna.io.survey import verify_stack

    doc = verify_stack(args.stack, max_pixels=args.max_pixels)  # every PNG checked, none decoded
    waiting = sum(1 for layer in doc.layers if isinstance(layer, LearnedLayer) and layer.source is None)
    extra = f"; {waiting} learned layer(s) not rendered" if waiting else ""
    print(
        f"ok: {len(doc.all_ids)} layers ({doc.canvas.width}x{doc.canvas.height}, blend_space={doc.blend_space}){extra}"
    )
    return 0
