"""``lasagna serve``: the layer editor in the browser, on one stack folder (or an image: a new stack folder).

    lasagna serve STACK|IMAGE [--host 127.0.0.1] [--port N] [--no-browser]

Prints the URL with its access token and serves until Ctrl-C (exit 0 then). Binds 127.0.0.1 unless told
otherwise; another address is reachable from other machines, so a warning says so. Needs the ``serve``
extra (Starlette and uvicorn): without it, one line says how to install it.
"""

from __future__ import annotations

import argparse
import sys

from lasagna.cli.common import PROG, device_argument, max_pixels_argument, warn
from lasagna.errors import LasagnaError

HELP = "open the layer editor in the browser on a stack folder or an image"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("stack", help="a stack folder (or its stack.json), or an image: a new <stem>.stack folder beside it")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, default=None, help="port (default: a free one)")
    p.add_argument("--no-browser", action="store_true", help="print the URL without opening a browser")
    max_pixels_argument(p)
    device_argument(p)


def run(args: argparse.Namespace) -> int:
    try:
        import starlette  # noqa: F401
        import uvicorn
    except ImportError:
        raise LasagnaError(
            "the editor needs Starlette and uvicorn; expected them installed: pip install 'lasagna[serve]'", "serve"
        ) from None
    from lasagna.heap import tune_heap
    from lasagna.serve import LOOPBACK, allowed_hosts, free_port, new_token, open_target
    from lasagna.serve.app import create_app
    from lasagna.serve.session import EditSession

    tune_heap("server")  # before anything renders (lasagna/heap.py, the two profiles)

    if args.port is not None and not 0 < args.port < 65536:
        raise LasagnaError(f"expected a port in [1, 65535], got {args.port}", "--port")
    folder, made = open_target(args.stack, max_pixels=args.max_pixels)
    if made:
        print(f"{PROG}: made the stack folder {folder} from {args.stack}")
    session = EditSession(folder, device=args.device, max_pixels=args.max_pixels)
    port = args.port or free_port(args.host)
    token = new_token()
    if args.host not in LOOPBACK:
        warn(f"binding {args.host}: the editor is reachable from other machines (anyone with the token edits {folder})")
    shown = "127.0.0.1" if args.host in ("0.0.0.0", "::") else args.host
    host = f"[{shown}]" if ":" in shown else shown
    url = f"http://{host}:{port}/?token={token}"
    app = create_app(session, token, allowed_hosts(args.host, port))
    print(f"{PROG} serve: editing {folder}")
    print(f"  {url}")
    print("  Ctrl-C stops the server (unsaved changes are not written).", flush=True)
    if not args.no_browser:
        import webbrowser

        try:
            webbrowser.open(url)
        except Exception:  # noqa: BLE001 - no browser is not an error: the URL is printed
            pass
    config = uvicorn.Config(app, host=args.host, port=port, log_level="warning", lifespan="off")
    server = uvicorn.Server(config)
    try:
        server.run()
    except KeyboardInterrupt:
        pass
    print(f"{PROG} serve: stopped", file=sys.stderr)
    return 0
