"""``lasagna serve``: the layer editor in the browser, on one stack folder (or an image, an ORA or a PSD: a new one).

    lasagna serve STACK|IMAGE [--host 127.0.0.1] [--port N] [--no-browser]

Prints the URL with its access token and serves until Ctrl-C (exit 0 then). Binds 127.0.0.1 unless told
otherwise; another address is reachable from other machines, so a warning says so. The port is bound before
anything else: a busy one is one line ("port N on HOST is in use; …", exit 2), before any URL is printed.
Slow or unfinished requests and connection floods are bounded (``lasagna.serve.server``). Needs the ``serve``
extra (Starlette and uvicorn): without it, one line says how to install it.
"""

from __future__ import annotations

import argparse
import asyncio
import sys

from lasagna.cli.common import PROG, device_argument, max_pixels_argument, warn
from lasagna.errors import LasagnaError
from lasagna.version import install_hint

HELP = "open the layer editor in the browser on a stack folder, an image, or an ORA or PSD file"
EXAMPLE = (
    "lasagna serve photo.jpg --no-browser   # a new stack folder photo.stack/ beside it; prints the URL",
    "lasagna serve painting.ora --no-browser   # its layers imported into painting.stack/",
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "stack",
        help="a stack folder (or its stack.json), or an image or an OpenRaster or PSD file: a new <stem>.stack folder "
        "beside it",
    )
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, default=None, help="port (default: a free one)")
    p.add_argument("--no-browser", action="store_true", help="print the URL without opening a browser")
    max_pixels_argument(p)
    device_argument(p)


def run(args: argparse.Namespace) -> int:
    # Refusals before the editor's imports (torch among them): a bad port, a stack or image that would not open.
    if args.port is not None and not 0 < args.port < 65536:
        raise LasagnaError(f"expected a port in [1, 65535], got {args.port}", "--port")
    from lasagna.serve import survey_target

    survey_target(args.stack, max_pixels=args.max_pixels)
    try:
        import starlette  # noqa: F401
        import uvicorn
    except ImportError:
        raise LasagnaError(
            f"the editor needs Starlette and uvicorn; expected them installed: {install_hint('serve')}", "serve"
        ) from None
    from lasagna.heap import tune_heap
    from lasagna.serve import LOOPBACK, allowed_hosts, new_token, open_target
    from lasagna.serve.app import HttpLimits, create_app
    from lasagna.serve.server import bind, serve, server_config
    from lasagna.serve.session import EditSession

    tune_heap("server")  # before anything renders (lasagna/heap.py, the two profiles)

    # Bound first: a busy port is one line before anything is made or printed (no URL that does not work).
    sock = bind(args.host, args.port or 0)
    with sock:
        folder, made = open_target(args.stack, max_pixels=args.max_pixels, warn=warn)
        if made:
            print(f"{PROG}: made the stack folder {folder} from {args.stack}")
        session = EditSession(folder, device=args.device, max_pixels=args.max_pixels)
        port = int(sock.getsockname()[1])
        token = new_token()
        if args.host not in LOOPBACK:
            warn(
                f"binding {args.host}: the editor is reachable from other machines (anyone with the token edits "
                f"{folder})"
            )
        shown = "127.0.0.1" if args.host in ("0.0.0.0", "::") else args.host
        host = f"[{shown}]" if ":" in shown else shown
        url = f"http://{host}:{port}/?token={token}"
        limits = HttpLimits()
        app = create_app(session, token, allowed_hosts(args.host, port), limits)
        server = uvicorn.Server(server_config(app, sock, limits))
        print(f"{PROG} serve: editing {folder}")
        print(f"  {url}")
        print("  Ctrl-C stops the server (unsaved changes are not written).", flush=True)
        if not args.no_browser:
            import webbrowser

            try:
                webbrowser.open(url)
            except Exception:  # noqa: BLE001 - no browser is not an error: the URL is printed
                pass
        try:
            asyncio.run(serve(server, sock))
        except KeyboardInterrupt:
            pass
    print(f"{PROG} serve: stopped", file=sys.stderr)
    return 0
