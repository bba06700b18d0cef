"""``lasagna import-ora``: read an OpenRaster file into a new stack folder."""

from __future__ import annotations

import argparse

from lasagna.cli.common import max_pixels_argument
from lasagna.errors import PathError

HELP = "read an OpenRaster file into a new stack folder"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("ora", help="OpenRaster file to read")
    p.add_argument("-o", "--output", required=True, metavar="FOLDER", help="stack folder to create")
    p.add_argument("--force", action="store_true", help="overwrite a stack already in FOLDER")
    max_pixels_argument(p)


def run(args: argparse.Namespace) -> int:
    from lasagna.export.ora import import_ora
    from lasagna.io.folder import check_writable

    out = check_writable(args.output, folder=True)
    if (out / "stack.json").exists() and not args.force:
        raise PathError("already holds a stack.json; expected a new folder (or --force to overwrite)", where=str(out))
    stack = import_ora(args.ora, max_pixels=args.max_pixels)
    stack.save(out)
    print(f"wrote {out / 'stack.json'} ({len(stack.ids)} layers, {stack.width}x{stack.height})")
    return 0
