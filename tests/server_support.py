"""A `quietframe serve` in its own process, for tests that kill it (kill -9, restart)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time

import httpx


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_cli_server(port: int, state_dir, **env: str) -> subprocess.Popen:
    """`quietframe serve` (the README command) with durable state in `state_dir`, ready;
    `env`: more QUIETFRAME_* settings."""
    environ = {**os.environ, "QUIETFRAME_THREADS": "1", **env}
    cmd = [sys.executable, "-m", "quietframe.client.cli", "serve", "--port", str(port),
           "--state-dir", str(state_dir)]
    proc = subprocess.Popen(cmd, env=environ, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"server exited: {proc.stderr.read().decode()[-2000:]}")
        try:
            if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=1).status_code == 200:
                return proc
        except httpx.TransportError:
            pass
        time.sleep(0.1)
    proc.kill()
    raise RuntimeError("server did not become ready")
