"""Soak: session churn against one server on 127.0.0.1 for a set time; the server's RSS slope.

    python -m quietframe.bench.soak [--minutes 2] [--clients 2] [--frames 4] [--width 320 ...]

Each client thread loops: create a session, send `frames` frames, delete it (every few rounds
one session is left to expire instead, and one upload is aborted mid-body). The server's RSS is
sampled every second; the slope (MiB/min, least squares) over the second half of the run says
whether memory grows with churn once warm. Also reports requests, errors and status counts.
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import threading
import time

import numpy as np

from quietframe.bench import cli_args
from quietframe.bench.http_overhead import loopback_server, rss_mib
from quietframe.bench.load import Tally, frames_for, report, server_env


def abort_upload(port: int, sid: str, data: bytes) -> None:
    """Half a frame body, then the connection closes (a client that went away)."""
    head = (
        f"POST /v1/sessions/{sid}/frames/0 HTTP/1.1\r\nHost: x\r\n"
        f"Content-Type: image/x-exr\r\nContent-Length: {len(data)}\r\n\r\n"
    )
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(head.encode() + data[: len(data) // 2])


def churn(http, url, port, size, frames, count, deadline, tally, ttl_leave: bool) -> None:
    round_ = 0
    while time.monotonic() < deadline:
        round_ += 1
        r = http.post(f"{url}/v1/sessions", json={"width": size[0], "height": size[1]})
        if r.status_code != 201:
            tally.add(r.status_code, None, r.text)
            time.sleep(1)
            continue
        sid = r.json()["id"]
        if round_ % 5 == 0:
            abort_upload(port, sid, frames[0])
        for i in range(count):
            start = time.perf_counter()
            r = http.post(
                f"{url}/v1/sessions/{sid}/frames/{i}",
                content=frames[i % len(frames)],
                headers={"content-type": "image/x-exr"},
            )
            tally.add(r.status_code, 1e3 * (time.perf_counter() - start), r.text)
        if not (ttl_leave and round_ % 7 == 0):  # else left for the TTL reaper
            http.delete(f"{url}/v1/sessions/{sid}")


def main(argv: list[str] | None = None) -> int:
    import httpx

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=2.0)
    parser.add_argument("--clients", type=int, default=2)
    parser.add_argument("--frames", type=int, default=4, help="frames per session")
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=180)
    cli_args.add_threads(parser, help="server onnxruntime threads per frame")
    cli_args.add_workers(parser)
    parser.add_argument("--ttl", type=float, default=20.0, help="server session TTL (s)")
    args = parser.parse_args(argv)
    size = (args.width, args.height)
    frames = frames_for(*size, 4)
    env = server_env(args.threads, args.workers)
    env["QUIETFRAME_SESSION_TTL_S"] = str(args.ttl)
    tally, samples = Tally(), []
    deadline = time.monotonic() + 60 * args.minutes
    with loopback_server(env) as (url, server), httpx.Client(timeout=600) as http:
        port = int(url.rsplit(":", 1)[1])
        workers = [
            threading.Thread(
                target=churn,
                args=(http, url, port, size, frames, args.frames, deadline, tally, i == 0),
            )
            for i in range(args.clients)
        ]
        start = time.monotonic()
        for w in workers:
            w.start()
        while any(w.is_alive() for w in workers):
            samples.append((time.monotonic() - start, rss_mib(server.pid)))
            time.sleep(1)
        seconds = time.monotonic() - start
        peak = rss_mib(server.pid, "VmHWM")
    t, rss = np.array(samples).T
    half = t >= t[-1] / 2
    slope = float(np.polyfit(t[half], rss[half], 1)[0]) * 60 if half.sum() > 2 else float("nan")
    result = report(
        tally, seconds, peak, size=f"{size[0]}x{size[1]}", clients=args.clients,
        rss_start_mib=round(float(rss[0])), rss_end_mib=round(float(rss[-1])),
        rss_slope_mib_per_min_second_half=round(slope, 2),
    )
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
