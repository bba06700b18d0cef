"""``lasagna import-psd``: read a layered PSD (psd-tools) into a new stack folder.

What the PSD holds that a stack cannot (adjustment layers, effects, clipping, blend modes outside W3C's…)
is rasterised or left out with one ``lasagna: warning:`` line each on stderr (``lasagna.export.psd_import``). The
folder follows ``edit``'s rule (new or empty, or a stack folder replaced as a whole with ``--force``) and
is written all or nothing (``lasagna.io.folder.write_stack_folder``).
"""

from __future__ import annotations

import argparse

from lasagna.cli.common import max_pixels_argument, warn

HELP = "read a layered PSD into a new stack folder"
EXAMPLE = "lasagna import-psd painting.psd -o mystack"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("psd", help="PSD file to read")
    p.add_argument("-o", "--output", required=True, metavar="FOLDER", help="stack folder to create")
    p.add_argument("--force", action="store_true", help="overwrite a stack already in FOLDER")
    p.add_argument(
        "--as-pixels",
        action="store_true",
        help="keep a surface layer's rendered multiplier and hidden normal map as the two pixel layers the file holds "
        "(default: made one surface layer again when its pixels are its map's rendering under the light fitted to them "
        "or named in the map's name)",
    )
    max_pixels_argument(p)


def run(args: argparse.Namespace) -> int:
    from lasagna.export.psd_import import read_psd
    from lasagna.io.folder import check_output_folder, write_stack_folder

    out = check_output_folder(args.output, force=args.force)
    stack = read_psd(args.psd, max_pixels=args.max_pixels, warn=warn, surfaces=not args.as_pixels)
    write_stack_folder(stack, out, force=args.force)
    n = len(stack.document.all_ids)
    print(f"wrote {out / 'stack.json'} ({n} layers, {stack.width}x{stack.height})")
    return 0
