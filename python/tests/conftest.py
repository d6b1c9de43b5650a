"""Fixtures: the real release server binary on a free port, and a cuttable TCP proxy."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import threading
import time
from pathlib import Path
from typing import Callable, Iterator, List, Optional

import pytest

REPO = Path(__file__).resolve().parents[2]
SERVER_BIN = Path(os.environ.get("BLAPOSE_SERVER_BIN", REPO / "target" / "release" / "blapose-server"))
CLIENT_BIN = Path(os.environ.get("BLAPOSE_CLIENT_BIN", REPO / "target" / "release" / "blapose-client"))
EXAMPLES = sorted((REPO / "examples").glob("*.npz"))


class Server:
    """A blapose-server process listening on 127.0.0.1:<free port>."""

    def __init__(self, tmp: Path, *args: str) -> None:
        if not SERVER_BIN.exists():
            pytest.fail(f"{SERVER_BIN} is missing: cargo build --release -p blapose-server -p blapose-client")
        self.log_path = tmp / f"server-{time.monotonic_ns()}.log"
        self._log = open(self.log_path, "wb")
        # --addr 127.0.0.1:0: the OS picks a free port, the server logs it.
        self.proc = subprocess.Popen(
            [str(SERVER_BIN), "--addr", "127.0.0.1:0", "--no-metrics", *args],
            stdout=self._log,
            stderr=subprocess.STDOUT,
            env={**os.environ, "RUST_LOG": "info", "NO_COLOR": "1"},
        )
        deadline = time.monotonic() + 60
        while True:
            text = self.log_path.read_text(errors="replace")
            m = re.search(r"serving blapose\.v1 addr=127\.0\.0\.1:(\d+)", text)
            if m:
                self.port = int(m.group(1))
                break
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                pytest.fail(f"blapose-server did not start:\n{text}")
            time.sleep(0.02)
        self.url = f"http://127.0.0.1:{self.port}"

    def stop(self, sig: int = signal.SIGTERM) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()


@pytest.fixture(scope="session")
def server(tmp_path_factory) -> Iterator[Server]:
    """One shared default server (embedded weights) for the whole test run."""
    srv = Server(tmp_path_factory.mktemp("server"))
    yield srv
    srv.stop()


@pytest.fixture
def start_server(tmp_path) -> Iterator[Callable[..., Server]]:
    """Start a dedicated server with extra flags; stopped after the test."""
    started: List[Server] = []

    def start(*args: str) -> Server:
        srv = Server(tmp_path, *args)
        started.append(srv)
        return srv

    yield start
    for srv in started:
        srv.stop()


class Proxy:
    """A TCP proxy in front of the server whose connections can be cut at will.

    ``pause_downstream()`` stops forwarding server -> client bytes (answers pile
    up unseen, as on a dying link); ``cut()`` closes every open connection (and
    lifts the pause for the connections that come after).
    """

    def __init__(self, upstream_port: int) -> None:
        self.upstream = ("127.0.0.1", upstream_port)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(16)
        self.port = self.sock.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        self.conns: List[socket.socket] = []
        self.accepted = 0
        self._lock = threading.Lock()
        self._flowing = threading.Event()
        self._flowing.set()
        self._closed = False
        self._dead: set = set()
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while not self._closed:
            try:
                client, _ = self.sock.accept()
            except OSError:
                return
            try:
                upstream = socket.create_connection(self.upstream)
            except OSError:
                client.close()
                continue
            for s in (client, upstream):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self.conns += [client, upstream]
                self.accepted += 1
            threading.Thread(target=self._pump, args=(client, upstream, None), daemon=True).start()
            threading.Thread(target=self._pump, args=(upstream, client, self._flowing), daemon=True).start()

    def _pump(self, src: socket.socket, dst: socket.socket, gate: Optional[threading.Event]) -> None:
        try:
            while True:
                data = src.recv(65536)
                if not data:
                    break
                if gate is not None:
                    gate.wait()
                    if id(dst) in self._dead:
                        break
                dst.sendall(data)
        except OSError:
            pass
        finally:
            for s in (src, dst):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    def pause_downstream(self) -> None:
        self._flowing.clear()

    def cut(self) -> None:
        with self._lock:
            conns, self.conns = self.conns, []
        for s in conns:
            self._dead.add(id(s))
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()
        old = self._flowing
        self._flowing = threading.Event()
        self._flowing.set()
        old.set()  # release the paused pumps (they see _cut and stop)

    def close(self) -> None:
        self._closed = True
        self.cut()
        self.sock.close()


@pytest.fixture
def proxy(server: Server) -> Iterator[Proxy]:
    p = Proxy(server.port)
    yield p
    p.close()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
