"""Hostile connections against a real uvicorn server (#28, defects 10 and 17): stalled request heads, slow
and unfinished bodies, uploads that hold memory, a process out of file descriptors, a busy port. Real
sockets; each test bounded to seconds. Timings are liveness bounds only ("answers within 30 s")."""

from __future__ import annotations

import asyncio
import http.client
import os
import resource
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest

pytest.importorskip("starlette")
pytest.importorskip("uvicorn")

from lasagna.cli import main  # noqa: E402
from lasagna.serve import allowed_hosts  # noqa: E402
from lasagna.serve.app import HttpLimits, create_app  # noqa: E402
from lasagna.serve.server import bind, serve, server_config  # noqa: E402
from lasagna.serve.session import EditSession  # noqa: E402
from tests.support.tinylayers import ROOT  # noqa: E402

TOKEN = "hostile-token"
LIVENESS_S = 30.0
"""A real request must be answered within this while the server is under attack (a generous bound: it
fails only when the server is locked out, not when the machine is slow)."""


@pytest.fixture
def folder(tmp_path):
    out = tmp_path / "basic"
    shutil.copytree(ROOT / "examples" / "stacks" / "basic", out)
    return out


class Server:
    """The editor on uvicorn in a thread, configured as ``lasagna serve`` configures it, with ``limits``."""

    def __init__(self, folder, limits: HttpLimits):
        import uvicorn

        self.sock = bind("127.0.0.1", 0)
        self.port = self.sock.getsockname()[1]
        app = create_app(EditSession(folder), TOKEN, allowed_hosts("127.0.0.1", self.port), limits)
        self.server = uvicorn.Server(server_config(app, self.sock, limits))
        self.thread = threading.Thread(target=asyncio.run, args=(serve(self.server, self.sock),), daemon=True)
        self.thread.start()
        deadline = time.monotonic() + LIVENESS_S
        while not self.server.started and time.monotonic() < deadline:
            time.sleep(0.01)
        assert self.server.started

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=10)
        self.sock.close()

    def connect(self) -> socket.socket:
        return socket.create_connection(("127.0.0.1", self.port), timeout=LIVENESS_S)

    def get(self, path: str = "/api/state") -> http.client.HTTPResponse:
        c = http.client.HTTPConnection("127.0.0.1", self.port, timeout=LIVENESS_S)
        c.request("GET", path, headers={"X-Lasagna-Token": TOKEN})
        r = c.getresponse()
        r.body = r.read()
        c.close()
        return r


@pytest.fixture
def start(folder):
    servers = []

    def make(**limits) -> Server:
        servers.append(Server(folder, HttpLimits(**limits)))
        return servers[-1]

    yield make
    for s in servers:
        s.stop()


def stalled_head(server: Server) -> socket.socket:
    s = server.connect()
    s.sendall(f"POST /api/upload?version=1 HTTP/1.1\r\nHost: 127.0.0.1:{server.port}\r\nX-Lasagna-".encode())
    return s


def closed_by_server(s: socket.socket) -> bool:
    """Whether the server closed ``s`` (reads to EOF, or a reset) within ``LIVENESS_S``."""
    s.settimeout(LIVENESS_S)
    try:
        while s.recv(65536):
            pass
    except ConnectionResetError:
        pass
    except TimeoutError:
        return False
    return True


def response(s: socket.socket) -> bytes:
    """The raw response on ``s``: its head and as much body as its Content-Length says."""
    s.settimeout(LIVENESS_S)
    data = b""
    while b"\r\n\r\n" not in data:
        data += s.recv(65536) or b"\r\n\r\n"
    head, _, body = data.partition(b"\r\n\r\n")
    length = next((int(h.split(b":")[1]) for h in head.split(b"\r\n") if h.lower().startswith(b"content-length")), 0)
    while len(body) < length:
        chunk = s.recv(65536)
        if not chunk:
            break
        body += chunk
    return head + b"\r\n\r\n" + body


# ---- stalled connections ------------------------------------------------------------------------------


def test_the_editor_answers_under_300_stalled_connections(start):
    server = start(max_connections=64)  # the cap a 256-descriptor process gets, or lower
    stalled = [stalled_head(server) for _ in range(300)]
    try:
        r = server.get()
        assert r.status == 200, r.body
    finally:
        for s in stalled:
            s.close()


def test_a_stalled_request_head_is_closed_after_the_head_timeout(start):
    server = start(head_timeout_s=0.5)
    silent, partial = server.connect(), stalled_head(server)
    assert closed_by_server(silent) and closed_by_server(partial)
    assert server.get().status == 200


def test_a_stalled_body_is_408_and_closed(start):
    server = start(body_idle_s=0.5)
    s = server.connect()
    s.sendall(
        f"POST /api/upload?version=1 HTTP/1.1\r\nHost: 127.0.0.1:{server.port}\r\nX-Lasagna-Token: {TOKEN}\r\n"
        "Content-Length: 1000000\r\n\r\n".encode()
        + b"\x89PNG" * 10
    )
    answer = response(s)
    assert answer.startswith(b"HTTP/1.1 408"), answer[:200]
    assert b"the request body stopped after 40 bytes" in answer
    assert closed_by_server(s)


def test_an_unread_body_does_not_hold_the_connection(start):
    """A POST refused before its body is read (no token here) and then trickled forever is closed."""
    server = start(head_timeout_s=0.5)
    s = server.connect()
    s.sendall(f"POST /api/upload HTTP/1.1\r\nHost: 127.0.0.1:{server.port}\r\nContent-Length: 999999\r\n\r\nx".encode())
    assert s.recv(65536).startswith(b"HTTP/1.1 403")
    s.sendall(b"y")  # the body keeps coming, slowly
    assert closed_by_server(s)


def test_uploads_in_flight_are_bounded(start):
    server = start(max_in_flight_bytes=3_000_000, body_idle_s=5.0)
    head = (
        f"POST /api/upload?version=1 HTTP/1.1\r\nHost: 127.0.0.1:{server.port}\r\nX-Lasagna-Token: {TOKEN}\r\n"
        "Content-Length: 2000000\r\n\r\n"
    ).encode()
    first = server.connect()
    first.sendall(head + b"x" * 1000)  # 2 MB reserved and waiting
    time.sleep(0.2)
    second = server.connect()
    second.sendall(head + b"x" * 1000)
    answer = response(second)
    assert answer.startswith(b"HTTP/1.1 429"), answer[:200]
    assert b"try again" in answer
    first.close()
    second.close()


# ---- out of file descriptors --------------------------------------------------------------------------


def _serve_with_few_descriptors(folder, port: int) -> subprocess.Popen:
    def limit():
        resource.setrlimit(resource.RLIMIT_NOFILE, (256, 256))

    cmd = [sys.executable, "-m", "lasagna.cli", "serve", str(folder), "--port", str(port), "--no-browser"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=limit, env=env)


@pytest.mark.skipif(sys.platform == "win32", reason="RLIMIT_NOFILE is POSIX")
def test_lasagna_serve_with_256_descriptors_answers_under_300_stalled_connections(folder):
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    proc = _serve_with_few_descriptors(folder, port)
    stalled = []
    try:
        token = None
        for _ in range(3):  # "lasagna serve: editing …", the URL, "Ctrl-C …"
            line = proc.stdout.readline()
            if "token=" in line:
                token = line.strip().rsplit("token=", 1)[1]
        assert token, proc.stderr.read() if proc.poll() is not None else "no URL printed"
        for _ in range(300):
            s = socket.create_connection(("127.0.0.1", port), timeout=LIVENESS_S)
            s.sendall(b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\n")
            stalled.append(s)
        c = http.client.HTTPConnection("127.0.0.1", port, timeout=LIVENESS_S)
        c.request("GET", "/api/state", headers={"X-Lasagna-Token": token})
        r = c.getresponse()
        assert r.status == 200, r.read()
        c.close()
    finally:
        for s in stalled:
            s.close()
        proc.send_signal(signal.SIGINT)
        try:
            _, err = proc.communicate(timeout=LIVENESS_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
    assert "Traceback" not in err and len(err) < 2000, err[:2000]


# ---- a busy port ----------------------------------------------------------------------------------------


def test_a_busy_port_is_one_line_and_exit_2_before_any_url(folder, capsys):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        status = main(["serve", str(folder), "--port", str(port), "--no-browser"])
    out, err = capsys.readouterr()
    assert status == 2
    assert out == "" and "token" not in err
    assert err.splitlines() == [
        f"lasagna: error: port {port} on 127.0.0.1 is in use; expected a free port: pass another --port, or "
        "leave it out for a free one"
    ]
