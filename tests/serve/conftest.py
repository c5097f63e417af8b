"""A real ``dbb-serve`` process on the session's small bundles, and helpers to talk to it."""

from __future__ import annotations

import asyncio
import os
import re
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

import pytest

READY = re.compile(r"dbb-serve ready: (http://\S+)")


@dataclass
class Served:
    proc: subprocess.Popen
    url: str                 # http://host:port/[?token=...]
    lines: list[str]

    @property
    def ws(self) -> str:
        base = self.url.split("?")[0].replace("http", "ws", 1)
        token = self.url.partition("?")[2]
        return base + "ws" + (f"?{token}" if token else "")

    @property
    def port(self) -> int:
        return int(self.url.split(":")[2].split("/")[0])

    def workers(self) -> list[int]:
        out = subprocess.run(["pgrep", "-P", str(self.proc.pid)], capture_output=True, text=True, check=False)
        return [int(p) for p in out.stdout.split()]

    def stop(self, sig=signal.SIGINT, timeout: float = 20.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            return self.proc.wait(timeout)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()


def start_server(*args, timeout: float = 240.0, port: int = 0) -> Served:
    """``dbb-serve ARGS --port PORT`` (0: a free one), returned once it printed its ready line
    (stderr, merged)."""
    cmd = [sys.executable, "-c", "from dbb_capture.cli.serve import main; main()", *map(str, args), "--port", str(port)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "COLUMNS": "200"})
    lines: list[str] = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line.rstrip())
        m = READY.search(line)
        if m:
            # Keep reading what it prints, so a full pipe never blocks it.
            threading.Thread(target=lambda: [lines.append(x.rstrip()) for x in proc.stdout], daemon=True).start()
            return Served(proc, m.group(1), lines)
    proc.kill()
    raise AssertionError("dbb-serve did not get ready:\n" + "\n".join(lines))


def run(coro):
    return asyncio.run(coro)


@pytest.fixture(scope="session")
def server(static_bundle, dynamic_bundle):
    """Both session bundles served side by side, with the thesis protocol on free ports."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        seed = s.getsockname()[1]
    srv = start_server(static_bundle, dynamic_bundle, "--seed-port", seed)
    srv.seed_port = seed
    yield srv
    srv.stop()
