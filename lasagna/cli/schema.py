"""``lasagna schema``: print one JSON Schema (stack or preset), or write them all into a folder."""

from __future__ import annotations

import argparse
import sys

HELP = "print or write the JSON Schemas"
EXAMPLE = (
    "lasagna schema preset            # print the preset schema",
    "lasagna schema --out schemas     # write every schema",
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "name", nargs="?", choices=["stack", "preset"], default="stack", help="which schema to print (default: stack)"
    )
    p.add_argument("--out", metavar="DIR", help="write every schema into DIR instead of printing one")


def run(args: argparse.Namespace) -> int:
    from lasagna.document import schemas, write_schemas
    from lasagna.document.schema import schema_text

    if args.out:
        from lasagna.io.folder import check_writable

        check_writable(args.out, folder=True)
        for path in write_schemas(args.out):
            print(f"wrote {path}")
        return 0
    sys.stdout.write(schema_text(schemas()[f"{args.name}.schema.json"]))
    return 0
