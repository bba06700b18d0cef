"""``lasagna world``: write scenes of a split as ground-truth stack folders (``lasagna.world``).

lasagna world -o DIR --split NAME --count N --seed S [--resolution R] [--task shading|color|light|relight]
              [--start I] [--shadows] [--ambient A]
"""

from __future__ import annotations

import argparse
import sys

from lasagna.cli.common import add_command
from lasagna.errors import LasagnaError

HELP = "write procedural scenes with ground truth as layer-stack folders"
EXAMPLE = "lasagna world -o out/world --split heldout --count 8 --seed 0"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Add the ``world`` options to ``p``."""
    from lasagna.document.condition import AMBIENT
    from lasagna.world.names import SPLIT_NAMES, TASKS

    p.add_argument("-o", "--output", required=True, metavar="DIR", help="folder to write the stack folders into")
    p.add_argument("--split", required=True, choices=SPLIT_NAMES, help="which named split to draw scenes from")
    p.add_argument("--count", required=True, type=int, metavar="N", help="number of scenes")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="seed of the split's scenes (default 0)")
    p.add_argument("--start", type=int, default=0, metavar="I", help="index of the first scene (default 0)")
    p.add_argument("--resolution", type=int, default=64, metavar="R", help="image side in pixels (default 64)")
    p.add_argument(
        "--task",
        choices=TASKS,
        default="shading",
        help="shading: albedo + multiply shading; color: gray + normal colour layer; "
        "light: image + plus glow of a warm, cool or white fill light, its label in the stack's "
        "metadata as condition; relight: the image lit from a random direction A + multiply ratio "
        "S_B/S_A in [0, 4] to the scene's named light B, the condition (default shading)",
    )
    p.add_argument("--shadows", action="store_true", help="cast shadows (off by default)")
    p.add_argument(
        "--ambient",
        type=float,
        default=AMBIENT,
        metavar="A",
        help=f"ambient term a of a + (1 - a) max(0, n.l) (default {AMBIENT})",
    )


def add_world_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``world`` on an ``argparse`` subparsers object (``args.run`` is ``run``): how the world's
    own tests (``tests/world``) build this command without the rest of the CLI."""
    return add_command(subparsers, "world", sys.modules[__name__])


def run(args: argparse.Namespace) -> int:
    """Write the stacks; prints one summary line; returns the exit status 0 (errors raise LasagnaError)."""
    # The integers first: a mistyped number is refused before the renderer (and torch) is imported.
    if args.count < 1:
        raise LasagnaError(f"expected a positive integer, got {args.count}", where="--count")
    for name in ("seed", "start"):
        if getattr(args, name) < 0:
            raise LasagnaError(f"expected a non-negative integer, got {getattr(args, name)}", where=f"--{name}")
    from lasagna.io.folder import check_writable
    from lasagna.world.export import MANIFEST, write_world_stacks
    from lasagna.world.scene import check_resolution

    out = check_writable(args.output, folder=True)
    check_resolution(args.resolution)
    folders = write_world_stacks(
        out,
        args.split,
        args.count,
        args.seed,
        args.resolution,
        args.task,
        start=args.start,
        shadows=args.shadows,
        ambient=args.ambient,
        progress=args.count >= 64,
    )
    print(
        f"wrote {len(folders)} {args.task} stacks ({args.split}, seed {args.seed}, "
        f"{args.resolution}x{args.resolution}) and {out / MANIFEST}"
    )
    return 0
