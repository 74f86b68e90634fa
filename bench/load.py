"""Load: N sessions x M frames at a given size against one server on 127.0.0.1.

    python -m quietframe.bench.load [--sessions 4] [--frames 8] [--width 640 --height 360]
    python -m quietframe.bench.soak [--minutes 2] ...   (session churn for a set time)

Starts a `quietframe serve` process (env QUIETFRAME_*), streams every session on its own thread
(frames in order, as a render farm does), and reports: requests and errors (by status),
latency p50/p99 of a frame request (upload + denoise + download), frames/s over all sessions,
the server's peak RSS (VmHWM), and non-finite values in the replies' pixels. A client honours
Retry-After on 429/503 as the CLI does (at most RETRIES times a frame; retries are counted,
not errors). Frames are the render-like synthetic Blender EXRs of
bench/http_overhead.py. Bounded by the counts given; loopback only.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from collections import Counter

import numpy as np

from quietframe.bench import cli_args
from quietframe.bench.http_overhead import (
    blender_exr,
    loopback_server,
    rss_mib,
    run_threads,
    synthetic_buffers,
)


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def frames_for(width: int, height: int, count: int) -> list[bytes]:
    return [blender_exr(synthetic_buffers(width, height, i), "zip", True) for i in range(count)]


RETRIES = 20
RETRY_STATUSES = (429, 503)


class Tally:
    """Latencies and statuses from all client threads."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.latency_ms: list[float] = []
        self.statuses: Counter = Counter()
        self.failures: list[str] = []
        self.retries = 0
        self.non_finite = 0  # pixel values in replies that are NaN or Inf

    def add_reply(self, body: bytes) -> None:
        count = non_finite_values(body)
        with self.lock:
            self.non_finite += count

    def add(self, status: int, ms: float | None, detail: str = "") -> None:
        with self.lock:
            self.statuses[status] += 1
            if ms is not None and status == 200:
                self.latency_ms.append(ms)
            if status != 200 and len(self.failures) < 5:
                self.failures.append(f"{status}: {detail[:200]}")


def non_finite_values(exr: bytes) -> int:
    import io

    import OpenEXR

    with OpenEXR.File(io.BytesIO(exr), separate_channels=True) as f:
        return sum(int((~np.isfinite(c.pixels)).sum()) for part in f.parts
                   for c in part.channels.values() if c.pixels.dtype.kind == "f")


def post_frame(http, url: str, body: bytes, tally: Tally):
    """The frame's final response, after honouring Retry-After on 429/503."""
    for _ in range(RETRIES):
        r = http.post(url, content=body, headers={"content-type": "image/x-exr"})
        if r.status_code not in RETRY_STATUSES:
            break
        with tally.lock:
            tally.retries += 1
        time.sleep(float(r.headers.get("retry-after", "1")))
    return r


def run_session(http, url: str, size, frames: list[bytes], count: int, tally: Tally) -> None:
    r = http.post(f"{url}/v1/sessions", json={"width": size[0], "height": size[1]})
    if r.status_code != 201:
        tally.add(r.status_code, None, r.text)
        return
    sid = r.json()["id"]
    for i in range(count):
        start = time.perf_counter()
        try:
            r = post_frame(http, f"{url}/v1/sessions/{sid}/frames/{i}",
                           frames[i % len(frames)], tally)
            tally.add(r.status_code, 1e3 * (time.perf_counter() - start), r.text[:200])
            if r.status_code == 200:
                tally.add_reply(r.content)
        except Exception as exc:  # transport errors count as errors
            tally.add(0, None, repr(exc))
    http.delete(f"{url}/v1/sessions/{sid}")


def server_env(threads: int, workers: int) -> dict[str, str]:
    return {
        **os.environ,
        "QUIETFRAME_THREADS": str(threads),
        "QUIETFRAME_WORKERS": str(workers),
        "QUIETFRAME_LOG_LEVEL": "warning",
    }


def report(tally: Tally, seconds: float, peak_rss: float, **extra) -> dict:
    done = len(tally.latency_ms)
    return {
        **extra,
        "requests": sum(tally.statuses.values()),
        "errors": sum(v for k, v in tally.statuses.items() if k != 200),
        "statuses": dict(tally.statuses),
        "retries": tally.retries,
        "non_finite_values": tally.non_finite,
        "p50_ms": round(percentile(tally.latency_ms, 50), 1),
        "p99_ms": round(percentile(tally.latency_ms, 99), 1),
        "frames_per_s": round(done / seconds, 2),
        "seconds": round(seconds, 1),
        "server_peak_rss_mib": round(peak_rss),
        "failures": tally.failures,
    }


def main(argv: list[str] | None = None) -> int:
    import httpx

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, default=4)
    parser.add_argument("--frames", type=int, default=8, help="frames per session")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=360)
    cli_args.add_threads(parser, help="server onnxruntime threads per frame")
    cli_args.add_workers(parser)
    args = parser.parse_args(argv)
    size = (args.width, args.height)
    frames = frames_for(*size, 4)
    tally = Tally()
    with loopback_server(server_env(args.threads, args.workers)) as (url, server):
        with httpx.Client(timeout=600) as http:
            session_args = (http, url, size, frames, args.frames, tally)
            seconds = run_threads([
                threading.Thread(target=run_session, args=session_args)
                for _ in range(args.sessions)
            ])
        peak = rss_mib(server.pid, "VmHWM")
    result = report(
        tally, seconds, peak, size=f"{size[0]}x{size[1]}", sessions=args.sessions,
        frames_per_session=args.frames, exr_mib=round(len(frames[0]) / 2**20, 2),
    )
    print(json.dumps(result, indent=1))
    return 1 if result["errors"] or result["non_finite_values"] else 0


if __name__ == "__main__":
    sys.exit(main())
