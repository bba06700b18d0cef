"""The ``lasagna`` console script: the only place that parses arguments or prints.

    lasagna composite STACK [-o out.png] [-v]     render STACK/composite.png (or out.png)
    lasagna export STACK [--ora F] [--psd F] [--layers DIR]
    lasagna validate STACK                        check the document and every PNG: "ok: N layers"
    lasagna schema [stack|preset] [--out DIR]     print (or write) the JSON Schemas
    lasagna import-ora IN.ora -o FOLDER           an OpenRaster file as a stack folder
    lasagna import-psd IN.psd -o FOLDER           a layered PSD as a stack folder (groups, masks, modes)
    lasagna edit IMAGE --layer P --condition L -o OUT   add a learned layer; writes a stack folder
    lasagna render STACK [--all]                  render the learned layers not rendered yet (--all: every one)
    lasagna light STACK --light L [--relief G]    re-light a surface layer in place from its normal map
    lasagna add-surface STACK MAP.png [--light L] a normal map of your own as a surface layer
    lasagna layers                                list the learned-layer catalogue
    lasagna prior add PATH --name N               register your own prior (a diffusers folder) as --layer N
    lasagna serve STACK|IMAGE [--port N]          the layer editor in the browser (lasagna-layers[serve])
    lasagna demo -o DIR                           relight, colourise and light the bundled examples
    lasagna world -o DIR --split S --count N      procedural scenes as stack folders (lasagna.world)
    lasagna train-prior --task T --out DIR        train a conditional prior on the world (resumable)
    lasagna train-corrective --prior P --out DIR  train or fit the LMC-SDS corrective b̂ of a prior
    lasagna train-layer --preset P [--out DIR]    train a preset's amortised generator
    lasagna train-surface --input I --out DIR     train a surface estimator on the world (resumable)

One module per command (``lasagna/cli/<command>.py``, ``-`` spelled ``_``), each with one convention:
``HELP`` (one line), ``add_arguments(parser)`` and ``run(args) -> exit status``. A command's module
imports the tiers it drives inside those functions, so ``lasagna --help`` stays light. Library modules
raise and return; they never print.

STACK is a stack folder or its stack.json. Any bad input ends with one line on stderr,
``lasagna: error: <where>: <what>; expected <…>``, exit status 2, no traceback, and no output file
touched: every output is rendered/encoded in memory and written atomically at the end. Set
``LASAGNA_DEBUG=1`` to see the traceback of an unexpected error. Ctrl-C exits with 130; SIGTERM is
handled like Ctrl-C (every temporary removed, every output as it was) and exits with 143.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import warnings
from collections.abc import Sequence
from types import ModuleType
from typing import NoReturn

from pydantic import ValidationError

from lasagna.cli import (
    add_surface,
    composite,
    demo,
    edit,
    export,
    import_ora,
    import_psd,
    layers,
    light,
    prior,
    render,
    schema,
    serve,
    train_corrective,
    train_layer,
    train_prior,
    train_surface,
    validate,
    world,
)
from lasagna.cli.common import COMPUTING, PROG, add_command, one_line, set_progress, set_threads, warn
from lasagna.errors import LasagnaError, describe_validation_error
from lasagna.limits import is_out_of_memory, memory_budget_scope, out_of_memory
from lasagna.version import __version__

# The subcommands in the order ``lasagna --help`` lists them.
COMMANDS: dict[str, ModuleType] = {
    "composite": composite,
    "export": export,
    "validate": validate,
    "schema": schema,
    "import-ora": import_ora,
    "import-psd": import_psd,
    "edit": edit,
    "render": render,
    "light": light,
    "add-surface": add_surface,
    "layers": layers,
    "prior": prior,
    "serve": serve,
    "demo": demo,
    "world": world,
    "train-prior": train_prior,
    "train-corrective": train_corrective,
    "train-layer": train_layer,
    "train-surface": train_surface,
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
        add_command(sub, name, command, arguments=argv is None or name == chosen)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the exit status (0 ok, 2 bad input, 130 Ctrl-C, 143 SIGTERM)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = build_parser(argv).parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0)
    # SIGTERM is raised as Ctrl-C's KeyboardInterrupt, so every ``except BaseException`` clean-up runs
    # (temporaries removed, outputs left as they were) before the process ends; the status says which.
    terminated: list[int] = []

    def on_sigterm(signum, frame):
        terminated.append(signum)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second SIGTERM must not cut the clean-up short
        raise KeyboardInterrupt

    in_main_thread = threading.current_thread() is threading.main_thread()  # signal() works only there
    previous = signal.signal(signal.SIGTERM, on_sigterm) if in_main_thread else None
    try:
        status = _run(args)
    finally:
        if in_main_thread:
            signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)
    return 128 + signal.SIGTERM if terminated else status


def process_exit(status: int) -> NoReturn:
    """End the process with ``status``. A worker that ``torchrun`` started (``TORCHELASTIC_RUN_ID`` and ``WORLD_SIZE``
    > 1 in its environment) ends with ``os._exit`` once its output is flushed: its process group is destroyed by
    then (``shutdown_distributed``), but torch's distributed runtime can leave a C++ thread joinable, and destroying
    it at interpreter teardown aborts the process ("terminate called without an active exception", SIGABRT) after
    the work succeeded — seen on this CPU under load in 2 of 16 two-process runs. Every file is written (atomically)
    before ``main`` returns, so skipping teardown loses nothing."""
    if int(os.environ.get("WORLD_SIZE", "1")) > 1 and "TORCHELASTIC_RUN_ID" in os.environ:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(status)
    sys.exit(status)


def console() -> NoReturn:
    """The ``lasagna`` command (``[project.scripts]``): ``main`` ended by ``process_exit``."""
    process_exit(main())


def _run(args: argparse.Namespace) -> int:
    """Run the parsed command; every failure becomes one line on stderr and its exit status."""
    try:
        with warnings.catch_warnings(), memory_budget_scope(getattr(args, "memory_budget", None)):
            warnings.simplefilter("default")
            warnings.showwarning = lambda message, *a, **k: warn(one_line(str(message)))  # type: ignore[assignment]
            set_progress(getattr(args, "progress", False))
            if args.command in COMPUTING:  # before any torch work: torch's default oversubscribes a busy CPU
                set_threads(getattr(args, "threads", None))
            return args.run(args)
    except KeyboardInterrupt:
        return 130
    except LasagnaError as err:
        print(f"{PROG}: error: {one_line(str(err))}", file=sys.stderr)
        return 2
    except ValidationError as err:  # a config built from the arguments broke a rule of its model
        print(f"{PROG}: error: {one_line(str(describe_validation_error(err, prefix=args.command)))}", file=sys.stderr)
        return 2
    except MemoryError as err:  # an allocation the budget's estimate did not foresee
        print(f"{PROG}: error: {one_line(str(out_of_memory(err, args.command)))}", file=sys.stderr)
        return 2
    except RecursionError:  # a structure nested past Python's stack (the JSON readers refuse this first)
        print(f"{PROG}: error: {args.command}: input nested too deeply; expected a flatter input", file=sys.stderr)
        return 2
    except RuntimeError as err:
        if not is_out_of_memory(err):
            return _internal_error(err)
        print(f"{PROG}: error: {one_line(str(out_of_memory(err, args.command)))}", file=sys.stderr)
        return 2
    except OSError as err:
        where = err.filename or "I/O"
        print(
            f"{PROG}: error: {where}: {err.strerror or err}; expected a readable input and a writable output",
            file=sys.stderr,
        )
        return 2
    except Exception as err:  # a bug, not bad input: still one line, the traceback on request
        return _internal_error(err)


def _internal_error(err: Exception) -> int:
    if os.environ.get("LASAGNA_DEBUG"):
        raise err
    print(
        f"{PROG}: error: internal error ({type(err).__name__}: {one_line(str(err))}); "
        "expected none: please report it (LASAGNA_DEBUG=1 shows the traceback)",
        file=sys.stderr,
    )
    return 2
