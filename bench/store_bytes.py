"""What a frame writes to the session store, counted by the store: Redis's own byte counter
(INFO stats total_net_input_bytes) around each frame, and for a state folder the session
file's size.

    python -m quietframe.bench.store_bytes [--size 1080p] [--frames 2] [--model auto]
        [--spp 16] [--stores redis,folder] [--threads 2] [--json rows.json]
        [--server-pythonpath DIR]

Starts redis-server (no persistence: what it writes to disk follows what it receives) and one
`quietframe serve` on loopback (bench/replicas.Cluster), and streams `frames` Cycles-style frames
(bench/synthetic.py's render-like Blender EXR: half float, ZIP, `cycles.ViewLayer.samples` =
spp in the header, so `auto` chooses as for a Cycles render) through one session; then the same
against a server with a state folder. Prints per store and frame the bytes written and the
session's float32 form (its state tensors and reply as the server holds them: what a store was
sent before service/state_codec.py) with their ratio, and redis-server's own CPU seconds for
the frame (INFO cpu: what bounds the frames one primary takes); then a retry of the last frame on a
replica that has only the store's record (Redis: the other replica; the folder: the server after
kill -9 and a restart), which must replay the same bytes.

`--server-pythonpath DIR` runs the servers from another checkout's package (e.g. the commit
before a change, for its figure measured rather than computed).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import httpx

from quietframe.bench.cli_args import add_json, add_threads
from quietframe.bench.replicas import SIZES, Cluster
from quietframe.bench.synthetic import blender_exr, synthetic_buffers

EXR = {"content-type": "image/x-exr"}
MIB = 2**20


def frames_for(size: tuple[int, int], count: int, spp: int) -> list[bytes]:
    header = {"cycles.ViewLayer.samples": str(spp)}
    return [blender_exr(synthetic_buffers(*size, i), "zip", True, header) for i in range(count)]


class RedisBytes:
    """Bytes Redis received (its own counter, every command of the frame's write included)."""

    def __init__(self, port: int) -> None:
        import redis

        self.client = redis.Redis(port=port)

    def count(self) -> tuple[int, float]:
        """(bytes received, CPU seconds of redis-server: what one primary spends a frame)."""
        stats, cpu = self.client.info("stats"), self.client.info("cpu")
        return (int(stats["total_net_input_bytes"]),
                float(cpu["used_cpu_user"]) + float(cpu["used_cpu_sys"]))

    def before(self, sid: str) -> None:
        self.start = self.count()

    def after(self, sid: str) -> int:
        end = self.count()
        self.cpu_s = end[1] - self.start[1]
        return end[0] - self.start[0]


class FolderBytes:
    """The session file's size: a frame replaces the file whole (temp file + rename)."""

    cpu_s = float("nan")

    def __init__(self, folder: Path) -> None:
        self.folder = folder

    def before(self, sid: str) -> None:
        pass

    def after(self, sid: str) -> int:
        return (self.folder / f"{sid}.npz").stat().st_size


def stream(url: str, size: tuple[int, int], model: str, frames: list[bytes],
           measure: RedisBytes | FolderBytes) -> tuple[str, list[dict], bytes]:
    """One session: (its id, a row per frame: bytes written to the store, the float32
    form, ..., the last reply)."""
    rows = []
    with httpx.Client(base_url=url, timeout=900) as http:
        r = http.post("/v1/sessions", json={"width": size[0], "height": size[1], "model": model})
        r.raise_for_status()
        sid = r.json()["id"]
        for i, body in enumerate(frames):
            measure.before(sid)
            start = time.perf_counter()
            reply = http.post(f"/v1/sessions/{sid}/frames/{i}", content=body, headers=EXR)
            seconds = time.perf_counter() - start
            reply.raise_for_status()
            written = measure.after(sid)
            status = http.get(f"/v1/sessions/{sid}").json()
            rows.append({"frame": i, "written": written, "store_cpu_s": measure.cpu_s,
                         "float32_form": status["memory_bytes"],
                         "request": len(body), "reply": len(reply.content),
                         "seconds": round(seconds, 2),
                         "model": reply.headers.get("x-quietframe-model"),
                         "choice": reply.headers.get("x-quietframe-choice")})
    return sid, rows, reply.content


def retry(url: str, sid: str, index: int, body: bytes, reply: bytes, how: str) -> dict:
    """The last frame again, on a replica that has only the store's record of it."""
    with httpx.Client(base_url=url, timeout=900) as http:
        start = time.perf_counter()
        again = http.post(f"/v1/sessions/{sid}/frames/{index}", content=body, headers=EXR)
        seconds = time.perf_counter() - start
        http.delete(f"/v1/sessions/{sid}")
    return {"how": how, "status": again.status_code,
            "replayed": again.headers.get("x-quietframe-replayed") == "true",
            "same_bytes": again.content == reply, "seconds": round(seconds, 2)}


def measure_redis(args, size: tuple[int, int], frames: list[bytes], last: int) -> dict:
    with Cluster(replicas=2, threads=args.threads, workers=1, persistence="none") as cluster:
        sid, rows, reply = stream(cluster.replica_url("r1"), size, args.model, frames,
                                  RedisBytes(cluster.redis_port))
        again = retry(cluster.replica_url("r2"), sid, last, frames[-1], reply,
                      "on the other replica")
    return {"store": "redis (total_net_input_bytes)", "rows": rows, "retry": again}


def measure_folder(args, size: tuple[int, int], frames: list[bytes], last: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp, \
            Cluster(replicas=1, threads=args.threads, workers=1, store=False,
                    state_dir=tmp) as cluster:
        sid, rows, reply = stream(cluster.replica_url("r1"), size, args.model, frames,
                                  FolderBytes(Path(tmp)))
        cluster.kill("r1")
        cluster.start_replica("r1")
        cluster.wait_replica("r1")
        again = retry(cluster.replica_url("r1"), sid, last, frames[-1], reply,
                      "after kill -9 and a restart")
    return {"store": "state folder (.npz size)", "rows": rows, "retry": again}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", choices=SIZES, default="1080p")
    p.add_argument("--frames", type=int, default=2)
    p.add_argument("--model", default="auto")
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--stores", default="redis,folder", help="which stores to measure")
    p.add_argument("--server-pythonpath", default=None)
    add_threads(p)
    add_json(p)
    args = p.parse_args(argv)
    if args.server_pythonpath:  # Cluster's processes inherit this environment
        os.environ["PYTHONPATH"] = args.server_pythonpath
    size = SIZES[args.size]
    frames = frames_for(size, args.frames, args.spp)
    results = []
    last, stores = len(frames) - 1, args.stores.split(",")
    if "redis" in stores:
        results.append(measure_redis(args, size, frames, last))
    if "folder" in stores:
        results.append(measure_folder(args, size, frames, last))
    print(f"{args.size}, model {args.model}, {args.spp} spp, {args.frames} frames, "
          f"{args.threads} threads; servers from {args.server_pythonpath or 'this checkout'}")
    print("| store | frame | model | written MiB | float32 form MiB | ratio | request MiB "
          "| frame s | redis-server CPU s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for result in results:
        for r in result["rows"]:
            print(f"| {result['store']} | {r['frame']} | {r['model']} | "
                  f"{r['written'] / MIB:.1f} | {r['float32_form'] / MIB:.1f} | "
                  f"{r['written'] / r['float32_form']:.3f} | {r['request'] / MIB:.1f} | "
                  f"{r['seconds']} | {r['store_cpu_s']:.3f} |")
    for result in results:
        print(f"{result['store']}: retry of the last frame {result['retry']}")
    if results and results[0]["rows"][0]["choice"]:
        print(f"choice: {results[0]['rows'][0]['choice']}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
