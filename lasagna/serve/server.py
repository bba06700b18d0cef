"""Running the editor on uvicorn: the bound socket, and the limits that keep it answering under abuse.

A local editor is still a server: a page, a script or a neighbour on the network can open connections and
never finish them. uvicorn alone holds a connection that never completes its request head forever, counts
it against ``limit_concurrency`` (so stalled sockets turn every real request into a 503), and once the
process runs out of file descriptors asyncio logs a traceback per failed ``accept``. Here:

* ``bind`` binds the listening socket before anything is printed: a busy port is one line, not a URL that
  does not work followed by uvicorn's message.
* ``EditorProtocol`` (uvicorn's h11 protocol) closes a connection that has not sent a complete request head
  within ``HttpLimits.head_timeout_s`` of connecting or of its last response (a slow body, once the head is
  in, is ``lasagna.serve.app._body``'s deadline), and caps open connections: past the cap the oldest
  connection still waiting for a head is closed, so stalled sockets make room for a real request instead of
  locking it out.
* ``connection_cap`` sizes that cap from the process's file-descriptor limit (raised to its hard limit
  first), with room left for the accept backlog and the files a save writes; ``serve`` turns an accept
  that still fails for want of descriptors into one warning line every few seconds.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import socket
import time

import h11
from uvicorn import Config, Server
from uvicorn.protocols.http.h11_impl import H11Protocol

from lasagna.errors import LasagnaError
from lasagna.serve.app import HttpLimits

RESERVED_FDS = 64
"""Descriptors kept free of connections: the stack's files during a save, the log, Python's own."""
FD_WARNING_INTERVAL_S = 10.0
"""At most one "out of file descriptors" line per this many seconds (asyncio retries accept every second)."""

log = logging.getLogger("lasagna.serve")


def bind(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host``:``port`` (0: a free port); one line if it cannot be had."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn: a TIME_WAIT port is free
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            raise LasagnaError(
                f"port {port} on {host} is in use; expected a free port: pass another --port, or leave it out "
                "for a free one"
            ) from None
        if exc.errno == errno.EACCES:
            raise LasagnaError(
                f"port {port} on {host} needs privileges to bind; expected a port above 1023", "--port"
            ) from None
        raise LasagnaError(
            f"cannot bind {host}:{port} ({exc.strerror or exc}); expected an address of this machine", "--host"
        ) from None
    sock.listen(HttpLimits.backlog)  # connections queue from now (the URL is printed before uvicorn starts)
    return sock


def connection_cap(limits: HttpLimits) -> tuple[int, int]:
    """(open connections allowed, accept backlog) that fit this process's file-descriptor limit, after
    raising its soft limit to the hard one: ``cap + backlog + RESERVED_FDS`` descriptors at most."""
    try:
        import resource

        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        if hard == resource.RLIM_INFINITY or hard > soft:
            want = hard if hard != resource.RLIM_INFINITY else max(soft, 65536)
            try:
                resource.setrlimit(resource.RLIMIT_NOFILE, (want, hard))
                soft = want
            except (OSError, ValueError):
                pass
    except ImportError:  # Windows: no RLIMIT_NOFILE; select() and the CRT allow a few thousand sockets
        soft = 2048
    budget = max(16, soft - RESERVED_FDS)
    backlog = max(8, min(limits.backlog, budget // 4))
    return max(8, min(limits.max_connections, budget - backlog)), backlog


class EditorProtocol(H11Protocol):
    """uvicorn's h11 protocol with a deadline for each request head and a cap on open connections (module
    docstring). ``limits`` and ``cap`` are set on a subclass by ``server_config``."""

    limits: HttpLimits = HttpLimits()
    cap: int = 256

    def connection_made(self, transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self.opened = time.monotonic()
        self._arm_head_deadline()
        if len(self.connections) > self.cap:
            waiting = [
                c
                for c in self.connections
                if isinstance(c, EditorProtocol) and c.waiting_for_head() and not c.transport.is_closing()
            ]
            victim = min(waiting, key=lambda c: c.opened) if waiting else self
            victim.close("the server is at its connection limit")

    def waiting_for_head(self) -> bool:
        """No request in progress: none yet, or the last one answered (keep-alive or an unread body)."""
        return self.cycle is None or self.cycle.response_complete

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if not self.waiting_for_head():  # a head arrived: the app's own deadlines hold from here
            self._cancel_head_deadline()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing():
            self._arm_head_deadline()  # the next head, or the end of a body nobody read, by then

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_head_deadline()
        super().connection_lost(exc)

    def close(self, why: str) -> None:
        self._cancel_head_deadline()
        if not self.transport.is_closing():
            log.debug("closing %s: %s", self.client, why)
            try:
                self.conn.send(h11.ConnectionClosed())
            except h11.LocalProtocolError:
                pass
            self.transport.close()

    def _arm_head_deadline(self) -> None:
        self._cancel_head_deadline()
        self.head_deadline = self.loop.call_later(
            self.limits.head_timeout_s, self.close, "no complete request head in time"
        )

    def _cancel_head_deadline(self) -> None:
        handle = getattr(self, "head_deadline", None)
        if handle is not None:
            handle.cancel()
            self.head_deadline = None


def server_config(app, sock: socket.socket, limits: HttpLimits, *, log_level: str = "warning") -> Config:
    """uvicorn's ``Config`` for ``app`` on the bound ``sock`` with ``limits``."""
    cap, backlog = connection_cap(limits)
    protocol = type("EditorProtocol", (EditorProtocol,), {"limits": limits, "cap": cap})
    host, port = sock.getsockname()[:2]
    return Config(
        app,
        host=host,
        port=port,
        http=protocol,
        log_level=log_level,
        lifespan="off",
        backlog=backlog,
        # uvicorn answers 503 once connections or running requests reach this. Connections are capped by
        # EditorProtocol (the oldest stalled one closed), but a burst of accepts (up to the backlog) lands
        # before the closes do: the limit sits above both, so stalled sockets never turn a real request away.
        limit_concurrency=cap + backlog + 1,
        timeout_keep_alive=limits.keep_alive_s,
        h11_max_incomplete_event_size=limits.max_head_bytes,
    )


def _quiet_accept_errors(loop: asyncio.AbstractEventLoop, context: dict) -> None:
    """The loop's exception handler: an accept that failed for want of descriptors is one warning line
    every ``FD_WARNING_INTERVAL_S`` (asyncio retries each second, with a traceback each time); the rest as
    asyncio reports it."""
    exc = context.get("exception")
    if isinstance(exc, OSError) and exc.errno in (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM):
        now = time.monotonic()
        if now - getattr(loop, "_lasagna_fd_warned", -FD_WARNING_INTERVAL_S) >= FD_WARNING_INTERVAL_S:
            loop._lasagna_fd_warned = now  # type: ignore[attr-defined]
            log.warning("lasagna serve: out of file descriptors (%s); new connections wait", exc.strerror)
        return
    loop.default_exception_handler(context)


async def serve(server: Server, sock: socket.socket) -> None:
    """Run ``server`` on ``sock`` until it is told to exit (``server.should_exit``) or Ctrl-C."""
    asyncio.get_running_loop().set_exception_handler(_quiet_accept_errors)
    await server.serve(sockets=[sock])


__all__ = ["EditorProtocol", "bind", "connection_cap", "serve", "server_config"]
