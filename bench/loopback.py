"""A `quietframe serve` process on 127.0.0.1 for the service benchmarks, and what they read of it.

The service benchmarks start the server, stream to it from threads and read its memory with
these, so that their figures compare.
"""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx

START_TIMEOUT_S = 120  # a cold start loads every installed model


def server_env(threads: int, workers: int) -> dict[str, str]:
    """This process's environment with the server's threads and workers (QUIETFRAME_*); its
    log at warning, so that request lines do not cost the measured server time."""
    return {
        **os.environ,
        "QUIETFRAME_THREADS": str(threads),
        "QUIETFRAME_WORKERS": str(workers),
        "QUIETFRAME_LOG_LEVEL": "warning",
    }


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(port: int, env: dict[str, str]) -> subprocess.Popen:
    """`quietframe serve` on `port`, returned once /readyz answers 200."""
    cmd = [sys.executable, "-m", "quietframe.service.cli", "--port", str(port)]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=2).status_code == 200:
                return proc
        except httpx.TransportError:
            time.sleep(0.2)
    proc.kill()
    raise RuntimeError("server did not start")


@contextlib.contextmanager
def loopback_server(env: dict[str, str]) -> Iterator[tuple[str, subprocess.Popen]]:
    """A `quietframe serve` process on a free loopback port: (url, process), stopped on exit."""
    port = free_port()
    server = start_server(port, env)
    try:
        yield f"http://127.0.0.1:{port}", server
    finally:
        server.terminate()
        server.wait(30)


def rss_mib(pid: int, field: str = "VmRSS") -> float:
    """A process's resident memory (`VmHWM`: its peak) from /proc, in MiB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    return float("nan")


def run_threads(threads: list[threading.Thread]) -> float:
    """Start every thread, wait for all; the wall seconds that took."""
    start = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return time.perf_counter() - start
