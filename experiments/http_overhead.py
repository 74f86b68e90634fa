"""HTTP end-to-end cost of the service vs the runtime alone, throughput, memory per session.

    python -m quietframe.experiments.http_overhead [--width 1280 --height 720] [--frames 8]

1. runtime alone: `Denoiser.denoise` on decoded numpy buffers, state carried (ms/frame);
2. end to end: a `quietframe serve` process on 127.0.0.1, one session, frames sent one after
   the other with the sync client (EXR upload, decode, denoise, encode, EXR download);
   the two alternate frame by frame; overhead ratio = median over frames of end-to-end ms /
   runtime ms (target <= 1.15);
3. throughput with 1, 2 and 4 sessions streaming concurrently (frames/s over all sessions);
4. the server's resident memory: after start-up, and the increase per open session holding
   history (peak RSS, VmHWM from /proc).

Frames are synthetic but render-like, so that EXR compression costs what it would on a real
render: piecewise-constant albedo, smooth normals and depth, a constant camera pan, and colour
= albedo x shading with 4-spp-like multiplicative noise; Blender multilayer channel names
(bench/synthetic.py, as the service benchmarks' frames). The server is bench/loopback.py's.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import threading
import time
from pathlib import Path

from quietframe.bench import cli_args
from quietframe.bench.loopback import loopback_server, rss_mib, run_threads, server_env
from quietframe.bench.synthetic import blender_exr, synthetic_buffers
from quietframe.client import Client
from quietframe.runtime import Denoiser, default_model_path
from quietframe.service import frames as exr

SESSIONS_HELD = 4  # sessions holding their history for the memory per session


def paired(
    model: Path,
    threads: int,
    decoded: list[dict],
    url: str,
    size,
    body: dict,
    exrs: list[bytes],
    count: int,
) -> tuple[list[float], list[float], list[dict]]:
    """Alternate one frame through the runtime alone (this process, the server idle) and the
    same frame over HTTP, so that both see the same load on a shared machine.
    Returns (runtime ms, end-to-end ms, server stage timings), first two frames dropped."""
    denoiser = Denoiser(model, threads=threads)
    alone, e2e, stages, state = [], [], [], None
    with Client(url, timeout_s=600) as client:
        sid = client.create_session(*size, **body)["id"]
        for i in range(count + 2):
            start = time.perf_counter()
            result = denoiser.denoise(decoded[i % len(decoded)], state)
            alone.append(1e3 * (time.perf_counter() - start))
            state = result.state
            start = time.perf_counter()
            reply = client.send_frame(sid, i, exrs[i % len(exrs)])
            e2e.append(1e3 * (time.perf_counter() - start))
            stages.append(reply.timings_ms)
        client.delete_session(sid)
    return alone[2:], e2e[2:], stages[2:]


def stream(
    url: str, size, body: dict, exrs: list[bytes], count: int, log: list, keep: bool = False
) -> None:
    """One session streams `count` frames one after the other; (ms, server stages) per frame
    into `log`. `keep`: the session is left open (holding its history)."""
    with Client(url, timeout_s=600) as client:
        sid = client.create_session(*size, **body)["id"]
        for i in range(count):
            start = time.perf_counter()
            result = client.send_frame(sid, i, exrs[i % len(exrs)])
            log.append((1e3 * (time.perf_counter() - start), result.timings_ms))
        if not keep:
            client.delete_session(sid)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=720)
    parser.add_argument("--frames", type=int, default=8, help="timed frames per measurement")
    parser.add_argument("--model", type=Path, help=".onnx file (default: the installed default)")
    cli_args.add_threads(parser, help="onnxruntime threads, runtime and server alike")
    cli_args.add_workers(parser)
    parser.add_argument("--compression", default="zip", help="input EXR compression")
    parser.add_argument("--float", action="store_true", help="float32 input (default half)")
    parser.add_argument(
        "--output-compression",
        default="input",
        help="session 'compression' (input keeps the input's)",
    )
    parser.add_argument("--precision", default="input", choices=("input", "half", "float"))
    parser.add_argument("--sessions", default="1,2,4", help="concurrency levels")
    cli_args.add_json(parser)
    return parser.parse_args(argv)


def sent_frames(args: argparse.Namespace) -> tuple[list[bytes], list[dict]]:
    """The EXRs sent, and what the runtime alone is given for them: exactly what the service
    hands it (decoded, converted buffers)."""
    size = (args.width, args.height)
    buffers = [synthetic_buffers(*size, seed) for seed in range(4)]
    exrs = [blender_exr(b, args.compression, not args.float) for b in buffers]
    header = exr.read_header(exrs[0], 1 << 16, 1 << 16)
    sources = exr.resolve(header.channels, ("color", "albedo", "normal", "depth"), ("motion",))
    return exrs, [exr.decode(data, sources).buffers for data in exrs]


def overhead(model: Path, args: argparse.Namespace, url: str, body: dict, exrs: list[bytes],
             decoded: list[dict]) -> dict:
    """Steps 1-2: the runtime alone and end to end, paired frame by frame, and their ratios."""
    size = (args.width, args.height)
    alone, e2e, timed = paired(model, args.threads, decoded, url, size, body, exrs, args.frames)
    stages = {
        k: round(statistics.median(s[k] for s in timed), 1)
        for k in ("decode", "denoise", "encode", "total")
    }
    results = {"runtime_ms": round(statistics.median(alone), 1),
               "http_ms": round(statistics.median(e2e), 1), "server_stages_ms": stages}
    results["transfer_and_http_ms"] = round(results["http_ms"] - stages["total"], 1)
    # Median of per-frame ratios: each pair ran back to back under the same load.
    results["overhead_ratio"] = round(
        statistics.median(h / r for h, r in zip(e2e, alone, strict=True)), 3
    )
    # Against the server's own denoise stage: the cost of HTTP + EXR I/O alone.
    results["overhead_ratio_vs_server_denoise"] = round(
        statistics.median(h / s["denoise"] for h, s in zip(e2e, timed, strict=True)), 3
    )
    return results


def throughput(args: argparse.Namespace, url: str, server_pid: int, body: dict,
               exrs: list[bytes]) -> dict:
    """Step 3: frames/s with each number of sessions streaming at once."""
    size = (args.width, args.height)
    out = {}
    for n in (int(s) for s in args.sessions.split(",")):
        logs: list[list] = [[] for _ in range(n)]
        threads = [
            threading.Thread(target=stream, args=(url, size, body, exrs, args.frames, logs[k]))
            for k in range(n)
        ]
        wall = run_threads(threads)
        done = sum(len(entries) for entries in logs)
        out[n] = {
            "frames_per_s": round(done / wall, 3),
            "ms_per_frame_per_session": round(
                statistics.median(t for e in logs for t, _ in e), 1
            ),
            "peak_rss_mib": round(rss_mib(server_pid, "VmHWM"), 1),
        }
    return out


def memory_per_session(args: argparse.Namespace, url: str, server_pid: int, body: dict,
                       exrs: list[bytes]) -> dict:
    """Step 4, on a fresh server: resident memory after start-up, then after SESSIONS_HELD
    sessions have each denoised two frames and keep their history and last reply."""
    size = (args.width, args.height)
    idle = rss_mib(server_pid)
    held: list = []
    stream(url, size, body, exrs, 2, held, keep=True)  # first: arenas and pools grow
    first = rss_mib(server_pid)
    for _ in range(SESSIONS_HELD - 1):
        stream(url, size, body, exrs, 2, held, keep=True)
    after = rss_mib(server_pid)
    return {
        "idle": round(idle, 1),
        "one_session": round(first, 1),
        f"{SESSIONS_HELD}_sessions": round(after, 1),
        "per_extra_session": round((after - first) / (SESSIONS_HELD - 1), 1),
        "peak": round(rss_mib(server_pid, "VmHWM"), 1),
    }


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    model = args.model or default_model_path()
    exrs, decoded = sent_frames(args)
    results: dict = {
        "size": f"{args.width}x{args.height}",
        "model": model.name,
        "input": f"{args.compression} {'float' if args.float else 'half'}, "
        f"{len(exrs[0]) / 2**20:.1f} MiB/frame",
        "output": f"{args.precision}, compression {args.output_compression}",
        "threads": args.threads,
        "cpus": os.cpu_count(),
    }
    env = server_env(args.threads, args.workers)
    if args.model:
        env["QUIETFRAME_MODELS_DIR"] = str(args.model.parent)
        env["QUIETFRAME_DEFAULT_MODEL"] = args.model.stem
    body = {"precision": args.precision}
    if args.output_compression != "input":
        body["compression"] = args.output_compression
    with loopback_server(env) as (url, server):
        results |= overhead(model, args, url, body, exrs, decoded)
        results["throughput"] = throughput(args, url, server.pid, body, exrs)
    with loopback_server(env) as (url, server):
        results["memory_mib"] = memory_per_session(args, url, server.pid, body, exrs)
        state = Denoiser(model, threads=1).info.state_nbytes(args.height, args.width)
        results["state_mib_per_session"] = round(state / 2**20, 1)
    print(json.dumps(results, indent=2))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
