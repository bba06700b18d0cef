"""The ``lasagna`` console script: one small function per subcommand, gathered in ``COMMANDS``.

    lasagna composite STACK [-o out.png] [-v]     render STACK/composite.png (or out.png)
    lasagna export STACK [--ora F] [--psd F] [--layers DIR]
    lasagna validate STACK                        check the document and every PNG: "ok: N layers"
    lasagna schema [stack|preset] [--out DIR]     print (or write) the JSON Schemas
    lasagna import-ora IN.ora -o FOLDER           an OpenRaster file as a stack folder
    lasagna edit IMAGE --layer P --condition L -o OUT   add a learned layer; writes a stack folder
    lasagna render STACK [--all]                  render learned layers from their stored settings
    lasagna layers                                list the learned-layer catalogue
    lasagna train-layer --preset P [--out DIR]    train a preset's amortised generator
    lasagna demo -o DIR                           relight, colourise and light the bundled examples
    lasagna world -o DIR --split S --count N      procedural scenes as stack folders (lasagna.world)

STACK is a stack folder or its stack.json. Any bad input ends with one line on stderr,
``lasagna: error: <where>: <what>; expected <…>``, exit status 2, no traceback, and no output file
touched: every output is rendered/encoded in memory and written atomically at the end. Set
``LASAGNA_DEBUG=1`` to see the traceback of an unexpected error. Ctrl-C exits with 130.

Adding a subcommand is adding one ``Command`` to ``COMMANDS``; ``_lazy`` names a function of another
module without importing it at startup (``world``, ``train-*`` and the learned-layer commands of
``lasagna.cli_learned`` are wired that way).
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

from pydantic import ValidationError

from lasagna import __version__
from lasagna.errors import LasagnaError, PathError

PROG = "lasagna"


def _warn(message: str) -> None:
    print(f"{PROG}: warning: {message}", file=sys.stderr)


def _max_pixels_arg(p: argparse.ArgumentParser) -> None:
    from lasagna.io.png import DEFAULT_MAX_PIXELS

    p.add_argument("--max-pixels", type=int, default=DEFAULT_MAX_PIXELS, metavar="N",
                   help=f"refuse any PNG with more than N pixels before decoding it (default {DEFAULT_MAX_PIXELS})")


def _load(args):
    from lasagna.io.stack import load_stack

    return load_stack(args.stack, max_pixels=args.max_pixels)


def _check_writable(path: Path, *, folder: bool = False) -> None:
    """Refuse an output path that cannot be written, before anything is written."""
    if not folder and path.is_dir():
        raise PathError("is a folder; expected a file path to write", where=str(path))
    if folder and path.exists() and not path.is_dir():
        raise PathError("exists and is not a folder; expected a folder to write into", where=str(path))
    parent = path if folder else path.parent
    probe = parent
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        raise PathError(f"{probe} is not a writable folder; expected a writable location", where=str(path))


# ---- subcommands ----------------------------------------------------------------------------------


def _composite_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("stack", help="stack folder or its stack.json")
    p.add_argument("-o", "--output", help="PNG to write (default: STACK/composite.png)")
    p.add_argument("-v", "--verbose", action="store_true", help="list evaluated and skipped layers")
    _max_pixels_arg(p)


def cmd_composite(args) -> int:
    from lasagna.document import stack_file
    from lasagna.io.render import render_stack, write_composite

    out = Path(args.output) if args.output else stack_file(args.stack).parent / "composite.png"
    _check_writable(out)
    stack = _load(args)
    result = render_stack(stack)
    write_composite(result, out)
    print(f"wrote {out} ({stack.width}x{stack.height}, {len(result.evaluated)} of {len(stack.ids)} layers composed)")
    if args.verbose:
        print(f"composed: {', '.join(result.evaluated) or '(none)'}")
        for id, reason in result.skipped.items():
            print(f"skipped: {id}: {reason}")
    return 0


def _export_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("stack", help="stack folder or its stack.json")
    p.add_argument("--ora", help="OpenRaster file to write")
    p.add_argument("--psd", help="layered PSD file to write (needs the psd extra)")
    p.add_argument("--layers", metavar="DIR", help="folder for one raw-value PNG per layer")
    _max_pixels_arg(p)


def cmd_export(args) -> int:
    from lasagna.export.png import layer_pngs
    from lasagna.io.atomic import atomic_write_bytes, atomic_write_text
    from lasagna.io.render import render_stack

    if not (args.ora or args.psd or args.layers):
        raise LasagnaError("nothing to export; expected at least one of --ora, --psd, --layers", where="export")
    for path in (args.ora, args.psd):
        if path:
            _check_writable(Path(path))
    if args.layers:
        _check_writable(Path(args.layers), folder=True)
    if args.psd:
        from lasagna.export.psd import _psd_tools

        _psd_tools()  # fail before any work if psd-tools is missing
    stack = _load(args)
    composite = render_stack(stack).image
    # Encode everything in memory first; write only once every output is ready.
    outputs: list[tuple[Path, bytes]] = []
    if args.ora:
        from lasagna.export.ora import encode_ora

        outputs.append((Path(args.ora), encode_ora(stack, composite=composite, warn=_warn)))
    if args.psd:
        from lasagna.export.psd import encode_psd

        outputs.append((Path(args.psd), encode_psd(stack, composite=composite, warn=_warn)))
    layer_files: dict[str, bytes] = {}
    meta = None
    if args.layers:
        layer_files, meta = layer_pngs(stack)
    try:
        for path, data in outputs:
            atomic_write_bytes(path, data)
            print(f"wrote {path}")
        if args.layers:
            folder = Path(args.layers)
            for name, data in layer_files.items():
                atomic_write_bytes(folder / name, data)
            atomic_write_text(folder / "layers.json", json.dumps(meta, indent=2) + "\n")
            print(f"wrote {len(layer_files)} layer PNGs and layers.json to {folder}")
    except OSError as exc:
        raise PathError(f"cannot write ({exc.strerror or exc}); expected a writable location",
                        where=str(exc.filename or "output")) from None
    return 0


def _validate_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("stack", help="stack folder or its stack.json")
    _max_pixels_arg(p)


def cmd_validate(args) -> int:
    stack = _load(args)
    doc = stack.document
    extra = f"; {len(stack.not_rendered)} learned layer(s) not rendered" if stack.not_rendered else ""
    print(f"ok: {len(doc.layers)} layers ({doc.canvas.width}x{doc.canvas.height}, blend_space={doc.blend_space}){extra}")
    return 0


def _schema_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", nargs="?", choices=["stack", "preset"], default="stack",
                   help="which schema to print (default: stack)")
    p.add_argument("--out", metavar="DIR", help="write every schema into DIR instead of printing one")


def cmd_schema(args) -> int:
    from lasagna.document import schemas, write_schemas

    if args.out:
        _check_writable(Path(args.out), folder=True)
        for path in write_schemas(args.out):
            print(f"wrote {path}")
        return 0
    from lasagna.document.schema import schema_text

    sys.stdout.write(schema_text(schemas()[f"{args.name}.schema.json"]))
    return 0


def _import_ora_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("ora", help="OpenRaster file to read")
    p.add_argument("-o", "--output", required=True, metavar="FOLDER", help="stack folder to create")
    p.add_argument("--force", action="store_true", help="overwrite a stack already in FOLDER")
    _max_pixels_arg(p)


def cmd_import_ora(args) -> int:
    from lasagna.export.ora import import_ora

    out = Path(args.output)
    _check_writable(out, folder=True)
    if (out / "stack.json").exists() and not args.force:
        raise PathError("already holds a stack.json; expected a new folder (or --force to overwrite)", where=str(out))
    stack = import_ora(args.ora, max_pixels=args.max_pixels)
    stack.save(out)
    print(f"wrote {out / 'stack.json'} ({len(stack.ids)} layers, {stack.width}x{stack.height})")
    return 0


def _demo_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", default="out/demo", metavar="DIR", help="output folder (default out/demo)")
    p.add_argument("--steps", type=int, default=None, metavar="N",
                   help="per-image steps for a preset without an amortised generator (default: the preset's)")


def cmd_demo(args) -> int:
    """Relight and colourise the bundled examples (``lasagna.demo``); falls back to the example stack."""
    from lasagna.demo import run_demo

    out = Path(args.output)
    _check_writable(out, folder=True)
    if args.steps is not None and args.steps < 1:
        raise LasagnaError(f"expected a positive integer, got {args.steps}", where="--steps")
    run_demo(out, steps=args.steps, warn=_warn)
    return 0


@dataclass(frozen=True)
class Command:
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


def _lazy(module: str, name: str) -> Callable:
    """A function of another tier, imported only when its subcommand runs (startup stays light)."""
    def call(*args):
        return getattr(importlib.import_module(module), name)(*args)

    call.__name__ = name
    return call


COMMANDS: dict[str, Command] = {
    "composite": Command("render a stack's composite PNG", _composite_args, cmd_composite),
    "export": Command("export a stack as OpenRaster, PSD and/or per-layer PNGs", _export_args, cmd_export),
    "validate": Command("check a stack's document and every PNG it names", _validate_args, cmd_validate),
    "schema": Command("print or write the JSON Schemas", _schema_args, cmd_schema),
    "import-ora": Command("read an OpenRaster file into a new stack folder", _import_ora_args, cmd_import_ora),
    "edit": Command("add a learned layer (relight, colourise, …) to an image or stack; writes a stack folder",
                    _lazy("lasagna.cli_learned", "edit_arguments"), _lazy("lasagna.cli_learned", "run_edit")),
    "render": Command("render a stack's learned layers from their stored generator and settings",
                      _lazy("lasagna.cli_learned", "render_arguments"), _lazy("lasagna.cli_learned", "run_render")),
    "layers": Command("list the learned-layer catalogue: presets, priors, correctives, generators",
                      _lazy("lasagna.cli_learned", "layers_arguments"), _lazy("lasagna.cli_learned", "run_layers")),
    "demo": Command("relight, colourise and light the bundled examples; writes stacks and one sheet to look at",
                    _demo_args, cmd_demo),
    "world": Command("write procedural scenes with ground truth as layer-stack folders",
                     _lazy("lasagna.world.cli", "world_arguments"), _lazy("lasagna.world.cli", "run_world")),
    "train-prior": Command("train a bundled conditional prior on the procedural world (resumable)",
                           _lazy("lasagna.priors.train", "build_parser"), _lazy("lasagna.priors.train", "run")),
    "train-corrective": Command("train the LMC-SDS manifold corrective b̂ of a prior (resumable)",
                                _lazy("lasagna.losses.corrective_train", "build_parser"),
                                _lazy("lasagna.losses.corrective_train", "run")),
    "train-layer": Command("train a preset's amortised layer generator on the world (resumable)",
                           _lazy("lasagna.cli_learned", "train_layer_arguments"),
                           _lazy("lasagna.cli_learned", "run_train_layer")),
}


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, exit 2 (argparse prints the whole usage otherwise)
        self.exit(2, f"{self.prog}: error: {message}; see '{self.prog} --help'\n")


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The parser; with ``argv``, only the chosen subcommand's arguments are built (they may import
    their tier), the others are listed by name and help alone."""
    parser = _Parser(prog=PROG, description="Layered image compositing with learned layers.")
    parser.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    chosen = None if argv is None else next((a for a in argv if not a.startswith("-")), None)
    for name, command in COMMANDS.items():
        p = sub.add_parser(name, help=command.help, description=command.help)
        if argv is None or name == chosen:
            command.add_arguments(p)
        p.set_defaults(run=command.run)
    return parser


def _one_line(text: str) -> str:
    return " ".join(text.split())


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the exit status (0 ok, 2 bad input, 130 interrupted)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = build_parser(argv).parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("default")
            warnings.showwarning = lambda message, *a, **k: _warn(_one_line(str(message)))  # type: ignore[assignment]
            return args.run(args)
    except KeyboardInterrupt:
        return 130
    except LasagnaError as err:
        print(f"{PROG}: error: {_one_line(str(err))}", file=sys.stderr)
        return 2
    except ValidationError as err:  # a config built from the arguments broke a rule of its model
        first = err.errors()[0]
        loc = ".".join(str(x) for x in first["loc"])
        more = f" (and {err.error_count() - 1} more)" if err.error_count() > 1 else ""
        where = f"{args.command}.{loc}" if loc else args.command
        print(f"{PROG}: error: {where}: {_one_line(first['msg'])}{more}", file=sys.stderr)
        return 2
    except MemoryError:
        print(f"{PROG}: error: out of memory; expected a smaller stack (see --max-pixels)", file=sys.stderr)
        return 2
    except OSError as err:
        where = err.filename or "I/O"
        print(f"{PROG}: error: {where}: {err.strerror or err}; expected a readable input and a writable output",
              file=sys.stderr)
        return 2
    except Exception as err:  # a bug, not bad input: still one line, the traceback on request
        if os.environ.get("LASAGNA_DEBUG"):
            raise
        print(f"{PROG}: error: internal error ({type(err).__name__}: {_one_line(str(err))}); "
              "expected none: please report it (LASAGNA_DEBUG=1 shows the traceback)", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
