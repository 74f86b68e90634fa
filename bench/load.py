"""Load: N sessions x M frames at a given size against one server on 127.0.0.1; or, with
`--soak`, session churn for a set time and the server's RSS slope.

    python -m quietframe.bench.load [--sessions 4] [--frames 8] [--width 640 --height 360]
    python -m quietframe.bench.load --soak 2 [--clients 2] [--frames 4] [--width 320 ...]

Starts a `quietframe serve` process (env QUIETFRAME_*), streams every session on its own thread
(frames in order, as a render farm does), and reports: requests and errors (by status),
latency p50/p99 of a frame request (upload + denoise + download), frames/s over all sessions,
the server's peak RSS (VmHWM), and non-finite values in the replies' pixels. A client honours
Retry-After on 429/503 as the CLI does (at most RETRIES times a frame; retries are counted,
not errors). Frames are the render-like synthetic Blender EXRs of bench/synthetic.py. Bounded
by the counts given; loopback only.

`--soak MINUTES`: each of `--clients` threads loops: create a session, send `--frames` frames,
delete it (every few rounds one session is left to expire instead, after the server's `--ttl`,
and one upload is aborted mid-body). The server's RSS is sampled every second; the slope
(MiB/min, least squares) over the second half of the run says whether memory grows with churn
once warm. Also reports requests, errors and status counts.
"""
from __future__ import annotations

import argparse
import io
import json
import socket
import sys
import threading
import time
from collections import Counter

import httpx
import numpy as np

from quietframe.bench import cli_args
from quietframe.bench.loopback import loopback_server, rss_mib, run_threads, server_env
from quietframe.bench.synthetic import blender_exr, synthetic_buffers

# The defaults of each mode: a load run streams a few sessions of a working size, a soak
# churns many small ones (what a leak per session would show in).
DEFAULTS = {"load": {"sessions": 4, "frames": 8, "width": 640, "height": 360},
            "soak": {"clients": 2, "frames": 4, "width": 320, "height": 180, "ttl": 20.0}}


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
    import OpenEXR  # the serve and client extras, as the server's replies need

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


def abort_upload(port: int, sid: str, data: bytes) -> None:
    """Half a frame body, then the connection closes (a client that went away)."""
    head = (
        f"POST /v1/sessions/{sid}/frames/0 HTTP/1.1\r\nHost: x\r\n"
        f"Content-Type: image/x-exr\r\nContent-Length: {len(data)}\r\n\r\n"
    )
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(head.encode() + data[: len(data) // 2])


def churn(http, url, port, size, frames, count, deadline, tally, ttl_leave: bool) -> None:
    """One soak client: sessions created, streamed and deleted until `deadline`."""
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


def load(args: argparse.Namespace, size: tuple[int, int], frames: list[bytes]) -> dict:
    """Every session on its own thread through one server; the report."""
    tally = Tally()
    with loopback_server(server_env(args.threads, args.workers)) as (url, server):
        with httpx.Client(timeout=600) as http:
            session_args = (http, url, size, frames, args.frames, tally)
            seconds = run_threads([
                threading.Thread(target=run_session, args=session_args)
                for _ in range(args.sessions)
            ])
        peak = rss_mib(server.pid, "VmHWM")
    return report(
        tally, seconds, peak, size=f"{size[0]}x{size[1]}", sessions=args.sessions,
        frames_per_session=args.frames, exr_mib=round(len(frames[0]) / 2**20, 2),
    )


def soak(args: argparse.Namespace, size: tuple[int, int], frames: list[bytes]) -> dict:
    """`--soak`: session churn for the minutes given, the server's RSS sampled every second;
    the report with the RSS slope over the second half."""
    env = server_env(args.threads, args.workers)
    env["QUIETFRAME_SESSION_TTL_S"] = str(args.ttl)
    tally, samples = Tally(), []
    deadline = time.monotonic() + 60 * args.soak
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
    return report(
        tally, seconds, peak, size=f"{size[0]}x{size[1]}", clients=args.clients,
        rss_start_mib=round(float(rss[0])), rss_end_mib=round(float(rss[-1])),
        rss_slope_mib_per_min_second_half=round(slope, 2),
    )


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, help="sessions streamed at once (default 4)")
    parser.add_argument("--frames", type=int, help="frames per session (default 8; --soak 4)")
    parser.add_argument("--width", type=int, help="default 640; --soak 320")
    parser.add_argument("--height", type=int, help="default 360; --soak 180")
    cli_args.add_threads(parser, help="server onnxruntime threads per frame")
    cli_args.add_workers(parser)
    churning = parser.add_argument_group("soak", "session churn for a set time instead")
    churning.add_argument("--soak", type=float, metavar="MINUTES",
                          help="churn sessions for this long; report the RSS slope")
    churning.add_argument("--clients", type=int, help="client threads churning (default 2)")
    churning.add_argument("--ttl", type=float, help="server session TTL, s (default 20)")
    args = parser.parse_args(argv)
    if args.soak is not None and args.soak <= 0:
        parser.error("--soak: the minutes to churn for, > 0")
    mode = "soak" if args.soak else "load"
    other = [f"--{k}" for k in DEFAULTS["soak" if mode == "load" else "load"]
             if k not in DEFAULTS[mode] and getattr(args, k) is not None]
    if other:
        parser.error(f"{', '.join(other)}: not read {'with' if args.soak else 'without'} "
                     "--soak")
    for key, value in DEFAULTS[mode].items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    size = (args.width, args.height)
    frames = frames_for(*size, 4)
    result = (soak if args.soak else load)(args, size, frames)
    print(json.dumps(result, indent=1))
    if args.soak:  # a soak reports; its figure is the slope, read by whoever runs it
        return 0
    return 1 if result["errors"] or result["non_finite_values"] else 0


if __name__ == "__main__":
    sys.exit(main())
