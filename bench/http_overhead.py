"""HTTP end-to-end cost of the service vs the runtime alone, throughput, memory per session.

    python -m quietframe.bench.http_overhead [--width 1280 --height 720] [--frames 8]

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
= albedo x shading with 4-spp-like multiplicative noise; Blender multilayer channel names.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import socket
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from quietframe.bench import cli_args


def synthetic_buffers(width: int, height: int, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    x += 2.0 * seed  # the camera pans 2 px per frame
    tiles = ((x // 97).astype(int) * 7 + (y // 61).astype(int) * 13) % 17
    palette = np.random.default_rng(0).uniform(0.05, 0.9, size=(17, 3)).astype(np.float32)
    albedo = palette[tiles]
    normal = np.stack([np.sin(x / 300), np.cos(y / 200), np.ones_like(x)], -1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    depth = 4.0 + 2.0 * np.sin(x / 400) * np.cos(y / 300)
    shading = 0.3 + 0.7 * np.clip(normal[..., 2:3], 0, 1)
    noise = rng.gamma(4.0, 1 / 4.0, size=(height, width, 3))  # mean 1, like 4 spp
    color = albedo * shading * noise
    motion = np.stack([np.full_like(x, 2.0), np.zeros_like(x)], -1)  # to t-1: 2 px right
    return {"color": color, "albedo": albedo, "normal": normal, "depth": depth, "motion": motion}


def blender_exr(buffers: dict[str, np.ndarray], compression: str, half: bool,
                attributes: dict[str, str] | None = None) -> bytes:
    """`attributes`: more header attributes (e.g. Cycles' `cycles.ViewLayer.samples`)."""
    import OpenEXR

    dtype = np.float16 if half else np.float32
    layer = "ViewLayer"
    channels = {}
    for name, pass_name, comps in (
        ("color", "Combined", "RGB"),
        ("albedo", "Denoising Albedo", "RGB"),
        ("normal", "Denoising Normal", "XYZ"),
    ):
        for i, c in enumerate(comps):
            channels[f"{layer}.{pass_name}.{c}"] = buffers[name][..., i]
    channels[f"{layer}.Combined.A"] = np.ones_like(buffers["depth"])
    channels[f"{layer}.Denoising Depth.Z"] = buffers["depth"]
    m = buffers["motion"]  # Cycles Vector: y up
    channels.update(
        {
            f"{layer}.Vector.X": m[..., 0],
            f"{layer}.Vector.Y": -m[..., 1],
            f"{layer}.Vector.Z": -m[..., 0],
            f"{layer}.Vector.W": m[..., 1],
        }
    )
    header = {
        "compression": getattr(OpenEXR, f"{compression.upper()}_COMPRESSION"),
        "type": OpenEXR.scanlineimage,
        **(attributes or {}),
    }
    arrays = {k: np.ascontiguousarray(v, dtype=dtype) for k, v in channels.items()}
    out = io.BytesIO()
    OpenEXR.File(header, arrays).write(out)
    return out.getvalue()


def rss_mib(pid: int, field: str = "VmRSS") -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    return float("nan")


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
    from quietframe.client import Client
    from quietframe.runtime import Denoiser

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


def start_server(port: int, env: dict[str, str]) -> subprocess.Popen:
    import httpx

    cmd = [sys.executable, "-m", "quietframe.service.cli", "--port", str(port)]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=2).status_code == 200:
                return proc
        except httpx.TransportError:
            time.sleep(0.2)
    proc.kill()
    raise RuntimeError("server did not start")


def stream(
    url: str, size, body: dict, exrs: list[bytes], count: int, log: list, keep: bool = False
) -> None:
    from quietframe.client import Client

    with Client(url, timeout_s=600) as client:
        sid = client.create_session(*size, **body)["id"]
        for i in range(count):
            start = time.perf_counter()
            result = client.send_frame(sid, i, exrs[i % len(exrs)])
            log.append((1e3 * (time.perf_counter() - start), result.timings_ms))
        if not keep:
            client.delete_session(sid)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


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


def run_threads(threads: list[threading.Thread]) -> float:
    """Start every thread, wait for all; the wall seconds that took."""
    start = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> int:
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
    args = parser.parse_args(argv)

    from quietframe.runtime import default_model_path
    from quietframe.service import frames as exr

    model = args.model or default_model_path()
    size = (args.width, args.height)
    buffers = [synthetic_buffers(*size, seed) for seed in range(4)]
    exrs = [blender_exr(b, args.compression, not args.float) for b in buffers]
    # The runtime gets exactly what the service would hand it (decoded, converted buffers).
    header = exr.read_header(exrs[0], 1 << 16, 1 << 16)
    sources = exr.resolve(header.channels, ("color", "albedo", "normal", "depth"), ("motion",))
    decoded = [exr.decode(data, sources).buffers for data in exrs]
    results: dict = {
        "size": f"{args.width}x{args.height}",
        "model": model.name,
        "input": f"{args.compression} {'float' if args.float else 'half'}, "
        f"{len(exrs[0]) / 2**20:.1f} MiB/frame",
        "output": f"{args.precision}, compression {args.output_compression}",
        "threads": args.threads,
        "cpus": os.cpu_count(),
    }

    env = {
        **os.environ,
        "QUIETFRAME_THREADS": str(args.threads),
        "QUIETFRAME_WORKERS": str(args.workers),
        "QUIETFRAME_LOG_LEVEL": "warning",
    }
    if args.model:
        env["QUIETFRAME_MODELS_DIR"] = str(args.model.parent)
        env["QUIETFRAME_DEFAULT_MODEL"] = args.model.stem
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    server = start_server(port, env)
    body = {"precision": args.precision}
    if args.output_compression != "input":
        body["compression"] = args.output_compression
    try:
        alone, e2e, timed = paired(model, args.threads, decoded, url, size, body, exrs, args.frames)
        stages = {
            k: round(statistics.median(s[k] for s in timed), 1)
            for k in ("decode", "denoise", "encode", "total")
        }
        results["runtime_ms"] = round(statistics.median(alone), 1)
        results["http_ms"] = round(statistics.median(e2e), 1)
        results["server_stages_ms"] = stages
        results["transfer_and_http_ms"] = round(results["http_ms"] - stages["total"], 1)
        # Median of per-frame ratios: each pair ran back to back under the same load.
        results["overhead_ratio"] = round(
            statistics.median(h / r for h, r in zip(e2e, alone, strict=True)), 3
        )
        # Against the server's own denoise stage: the cost of HTTP + EXR I/O alone.
        results["overhead_ratio_vs_server_denoise"] = round(
            statistics.median(h / s["denoise"] for h, s in zip(e2e, timed, strict=True)), 3
        )

        throughput = {}
        for n in (int(s) for s in args.sessions.split(",")):
            logs: list[list] = [[] for _ in range(n)]
            threads = [
                threading.Thread(target=stream, args=(url, size, body, exrs, args.frames, logs[k]))
                for k in range(n)
            ]
            wall = run_threads(threads)
            done = sum(len(entries) for entries in logs)
            throughput[n] = {
                "frames_per_s": round(done / wall, 3),
                "ms_per_frame_per_session": round(
                    statistics.median(t for e in logs for t, _ in e), 1
                ),
                "peak_rss_mib": round(rss_mib(server.pid, "VmHWM"), 1),
            }
        results["throughput"] = throughput
    finally:
        server.terminate()
        server.wait(timeout=30)

    # Memory per session, on a fresh server: resident memory after start-up, then after
    # `hold` sessions have each denoised two frames and keep their history and last reply.
    server = start_server(port, env)
    try:
        idle = rss_mib(server.pid)
        hold, held = 4, []
        stream(url, size, body, exrs, 2, held, keep=True)  # first: arenas and pools grow
        first = rss_mib(server.pid)
        for _ in range(hold - 1):
            stream(url, size, body, exrs, 2, held, keep=True)
        after = rss_mib(server.pid)
        results["memory_mib"] = {
            "idle": round(idle, 1),
            "one_session": round(first, 1),
            f"{hold}_sessions": round(after, 1),
            "per_extra_session": round((after - first) / (hold - 1), 1),
            "peak": round(rss_mib(server.pid, "VmHWM"), 1),
        }
        from quietframe.runtime import Denoiser

        state = Denoiser(model, threads=1).info.state_nbytes(args.height, args.width)
        results["state_mib_per_session"] = round(state / 2**20, 1)
    finally:
        server.terminate()
        server.wait(timeout=30)

    print(json.dumps(results, indent=2))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
