"""Past one box, measured: replicas behind HAProxy, their sessions in Redis (docs/deployment.md).

    python -m quietframe.bench.replicas throughput [--replicas 1,2] [--sessions 8] [--frames 6]
    python -m quietframe.bench.replicas store [--sizes 1080p] [--repeats 5]
    python -m quietframe.bench.replicas estimate [--replicas 100] [--cameras 1000]

`throughput` starts redis-server, N `quietframe serve` replicas and HAProxy (deploy/haproxy.cfg)
on loopback, streams every session on its own thread through the load balancer and reports
frames/s and the p50/p99 of a frame request; `--no-store` runs one replica alone, state in
memory, as the baseline the store's cost is read against. `store` times what the store adds to
a frame (the write of state + reply, the version check) for Redis and for a folder (the shared
volume's case), at the size given, with the default model's real state shapes. `estimate`
is the paper estimate for a farm. `Cluster` is what tests/deploy/test_replicas_failover.py starts.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterable
from pathlib import Path

import httpx
import numpy as np

from quietframe.bench.harness import RuntimeMethod
from quietframe.bench.load import Tally, frames_for, report
from quietframe.bench.synthetic import blender_exr, synthetic_buffers
from quietframe.runtime import installed_models
from quietframe.runtime.buffers import planes_from_hwc
from quietframe.service.session_store import Reply, SessionStore, record

MODEL = "nbg-2l-3g"  # the fast tier, with a temporal state (a failover must carry it)
HAPROXY_CFG = Path(__file__).resolve().parents[1] / "deploy" / "haproxy.cfg"
SIZES = {"512x288": (512, 288), "720p": (1280, 720), "1080p": (1920, 1080), "4k": (3840, 2160)}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(check, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if check():
            return
        time.sleep(0.1)
    raise TimeoutError(f"{what} not ready after {timeout_s:g} s")


def http_ok(url: str) -> bool:
    try:
        return httpx.get(url, timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


class Cluster:
    """redis-server, `quietframe serve` replicas and HAProxy on loopback, in one temp folder;
    `close()` ends every process it started (use as a context manager)."""

    def __init__(self, replicas: int = 2, threads: int = 1, workers: int = 1,
                 haproxy_cfg: Path = HAPROXY_CFG, store: bool = True,
                 persistence: str = "always", **settings) -> None:
        self.folder = Path(tempfile.mkdtemp(prefix="qf-cluster-"))
        self.procs: dict[str, subprocess.Popen] = {}
        self.threads, self.workers, self.settings = threads, workers, settings
        self.persistence = persistence  # appendfsync always / everysec, or "none"
        self.redis_port = free_port() if store else None
        self.ports = {f"r{i + 1}": free_port() for i in range(replicas)}
        self.lb_port = free_port()
        self.haproxy_cfg = haproxy_cfg
        self.url = f"http://127.0.0.1:{self.lb_port}"

    def __enter__(self) -> Cluster:
        try:
            self.start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *_) -> None:
        self.close()

    def start(self) -> None:
        if self.redis_port is not None:
            self.start_redis()
        for name in self.ports:
            self.start_replica(name)
        for name in self.ports:
            self.wait_replica(name)
        if not self.ports:  # the store alone (the `store` measurement)
            return
        if len(self.ports) > 1 or self.redis_port is not None:
            self.start_haproxy()
        else:  # one replica without a store: the baseline, addressed directly
            self.url = self.replica_url("r1")

    def _spawn(self, name: str, command: list[str], env: dict | None = None) -> None:
        log = open(self.folder / f"{name}.log", "ab")
        self.procs[name] = subprocess.Popen(
            command, env=env, stdout=log, stderr=subprocess.STDOUT, cwd=self.folder
        )
        log.close()

    def start_redis(self) -> None:
        # appendfsync always (default): a restarted redis-server has every committed frame (the
        # outage case of the test); the deployment's trade-off is in docs/deployment.md.
        aof = ["--appendonly", "no"] if self.persistence == "none" else [
            "--appendonly", "yes", "--appendfsync", self.persistence]
        self._spawn("redis", ["redis-server", "--port", str(self.redis_port), "--bind",
                              "127.0.0.1", "--save", "", *aof, "--dir", str(self.folder),
                              "--proto-max-bulk-len", "2gb"])
        wait_for(self.redis_answers, 20, "redis-server")

    def redis_answers(self) -> bool:
        import redis

        try:
            return bool(redis.Redis(port=self.redis_port, socket_timeout=1).ping())
        except redis.RedisError:
            return False

    def replica_url(self, name: str) -> str:
        return f"http://127.0.0.1:{self.ports[name]}"

    def start_replica(self, name: str) -> None:
        env = {**os.environ, "QUIETFRAME_REPLICA_ID": name, "QUIETFRAME_LOG_JSON": "false",
               **{f"QUIETFRAME_{k.upper()}": str(v) for k, v in self.settings.items()}}
        if self.redis_port is not None:
            env["QUIETFRAME_STORE_URL"] = f"redis://127.0.0.1:{self.redis_port}/0"
        self._spawn(name, [sys.executable, "-m", "quietframe.service.cli", "--port",
                           str(self.ports[name]), "--threads", str(self.threads), "--workers",
                           str(self.workers), "--log-level", "warning"], env)

    def wait_replica(self, name: str, timeout_s: float = 120) -> None:
        def ready() -> bool:
            if self.procs[name].poll() is not None:
                raise RuntimeError(f"replica {name} exited: {self.log(name)[-2000:]}")
            return http_ok(f"{self.replica_url(name)}/readyz")

        wait_for(ready, timeout_s, f"replica {name}")

    def start_haproxy(self) -> None:
        env = {**os.environ, "QF_LISTEN": f"127.0.0.1:{self.lb_port}"}
        env.update({f"QF_REPLICA{i + 1}": f"127.0.0.1:{port}"
                    for i, port in enumerate(self.ports.values())})
        cfg = self.haproxy_cfg
        if len(self.ports) == 1:  # the one-replica run: the same file with r2 left out
            cfg = self.folder / "haproxy-1.cfg"
            lines = self.haproxy_cfg.read_text().splitlines()
            cfg.write_text("\n".join(ln for ln in lines if "server r2" not in ln) + "\n")
        self._spawn("haproxy", ["haproxy", "-db", "-f", str(cfg)], env)
        wait_for(lambda: http_ok(f"{self.url}/healthz"), 20, "haproxy")

    def kill(self, name: str) -> None:
        """kill -9: no shutdown handler runs."""
        proc = self.procs[name]
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)

    def log(self, name: str) -> str:
        path = self.folder / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def close(self) -> None:
        stop_processes(self.procs.values())
        shutil.rmtree(self.folder, ignore_errors=True)


def stop_processes(procs: Iterable[subprocess.Popen]) -> None:
    """Terminate every process, then wait for each (killed after 10 s)."""
    procs = list(procs)
    for proc in procs:
        if proc.poll() is None:
            proc.terminate()
    for proc in procs:
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


# ---- throughput -------------------------------------------------------------------------------


def stream(url: str, size: tuple[int, int], frames: list[bytes], tally) -> None:
    """One camera: create a session through `url`, send every frame in order, delete it."""
    with httpx.Client(timeout=300) as http:
        r = http.post(f"{url}/v1/sessions",
                      json={"width": size[0], "height": size[1], "model": MODEL})
        if r.status_code != 201:
            tally.add(r.status_code, None, r.text)
            return
        sid = r.json()["id"]
        for i, body in enumerate(frames):
            start = time.perf_counter()
            try:
                r = http.post(f"{url}/v1/sessions/{sid}/frames/{i}", content=body,
                              headers={"content-type": "image/x-exr"})
                tally.add(r.status_code, 1e3 * (time.perf_counter() - start), r.text[:200])
            except httpx.HTTPError as exc:
                tally.add(0, None, repr(exc))
        http.delete(f"{url}/v1/sessions/{sid}")


def throughput(replicas: int, sessions: int, frames: list[bytes], size, store: bool) -> dict:
    workers = 2 if replicas == 1 else 1  # both cores busy either way (threads = 1 per frame)
    with Cluster(replicas, threads=1, workers=workers, store=store) as cluster:
        stream(cluster.url, size, frames[:1], Tally())  # warm-up: onnxruntime's arena
        tally = Tally()
        threads = [threading.Thread(target=stream, args=(cluster.url, size, frames, tally))
                   for _ in range(sessions)]
        start = time.perf_counter()
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        seconds = time.perf_counter() - start
    row = report(tally, seconds, 0.0, replicas=replicas, sessions=sessions,
                 store="redis" if store else "none (memory)",
                 load_balancer="haproxy" if (store or replicas > 1) else "none")
    row.pop("server_peak_rss_mib")  # several processes: not measured here
    return row


# ---- the store's cost per frame -----------------------------------------------------------------


def session_payload(width: int, height: int) -> tuple[dict, dict[str, np.ndarray], bytes]:
    """meta, state (the default model's after two render-like frames at this size, probe
    included, as a session keeps it) and a reply the size of a render-like ZIP EXR at this
    size, as a frame stores them."""
    path = next(p for p in installed_models() if p.stem == MODEL)
    method = RuntimeMethod(path, threads=2)
    for i in range(2):
        method(planes_from_hwc(synthetic_buffers(width, height, i)))
    state = method.state
    assert state is not None
    reply = blender_exr(synthetic_buffers(width, height, 0), "zip", True)
    meta = {"id": "A" * 22, "model": MODEL, "width": width, "height": height, "last_index": 1,
            "frames_done": 1, "resets": 1, "choice": None}
    return meta, state, reply


def stored_bytes(meta: dict, state: dict[str, np.ndarray], reply: bytes) -> int:
    """What a store is sent for this state and reply (service/state_codec.py's form)."""
    stored, arrays = record(meta, dict(state), Reply(1, reply, {}, len(reply), "0" * 64))
    return len(json.dumps(stored)) + sum(a.nbytes for a in arrays.values())


def time_store(store, meta, state, reply, repeats: int, shapes) -> dict:
    answer = Reply(1, reply, {"X-Quietframe-Frame": "1"}, len(reply), "0" * 64)
    writes, checks, reads = [], [], []
    version = ""
    if store.shared:
        store.write_spec(meta)
    for _ in range(repeats):
        t0 = time.perf_counter()
        if store.shared:
            assert (store.version(meta["id"]) or "") == version
        t1 = time.perf_counter()
        version = store.write(meta, state, answer, version)
        t2 = time.perf_counter()
        store.read(meta["id"], shapes)
        t3 = time.perf_counter()
        checks.append(t1 - t0)
        writes.append(t2 - t1)
        reads.append(t3 - t2)
    store.delete(meta["id"])
    ms = lambda xs: round(1e3 * float(np.median(xs)), 2)  # noqa: E731
    return {"write_ms": ms(writes), "version_check_ms": ms(checks),
            "per_frame_ms": round(ms(writes) + ms(checks), 2), "failover_read_ms": ms(reads)}


def store_costs(size_name: str, repeats: int) -> list[dict]:
    from quietframe.service.state_store_redis import RedisStore  # redis: this command alone

    width, height = SIZES[size_name]
    meta, state, reply = session_payload(width, height)
    shapes = {name: a.shape for name, a in state.items()}
    state_bytes = sum(a.nbytes for a in state.values())
    rows = []
    base = {"size": size_name, "state_float32_mib": round(state_bytes / 2**20, 1),
            "reply_mib": round(len(reply) / 2**20, 2),
            "bytes_per_frame_mib": round(stored_bytes(meta, state, reply) / 2**20, 1)}
    for persistence in ("always", "everysec", "none"):
        with Cluster(replicas=0, persistence=persistence) as cluster:
            store = RedisStore(f"redis://127.0.0.1:{cluster.redis_port}/0", 900, 30)
            what = "no persistence" if persistence == "none" else f"AOF fsync {persistence}"
            rows.append({**base, "store": f"redis on loopback, {what}",
                         **time_store(store, meta, state, reply, repeats, shapes)})
    for label, folder in (("folder on local disk (shared-volume stand-in)", None),
                          ("folder on /dev/shm (no disk)", "/dev/shm")):
        with tempfile.TemporaryDirectory(dir=folder) as tmp:
            store = SessionStore(Path(tmp), fsync=False)
            rows.append({**base, "store": label,
                         **time_store(store, meta, state, reply, repeats, shapes)})
    return rows


# ---- paper estimate ----------------------------------------------------------------------------


def estimate(replicas: int, cameras: int, size_name: str, seconds_per_frame: float) -> dict:
    """What the store and the load balancer carry for a farm: every frame writes its session's
    state and reply once; a failover reads one session back."""
    width, height = SIZES[size_name]
    meta, state, reply = session_payload(width, height)  # the `store` measurement's
    exr = len(reply)  # a render-like Blender EXR (ZIP, half) in, about as large out
    frames_s = min(cameras, replicas) / seconds_per_frame  # one frame per replica at a time
    per_frame = stored_bytes(meta, state, reply)
    return {
        "size": size_name, "replicas": replicas, "cameras": cameras,
        "seconds_per_frame_per_replica": seconds_per_frame, "frames_per_s": round(frames_s, 1),
        "store_write_mb_s": round(frames_s * per_frame / 1e6), "store_bytes_per_frame_mb":
        round(per_frame / 1e6, 1), "store_memory_gb": round(cameras * per_frame / 1e9, 1),
        "lb_mb_s_each_way": round(frames_s * exr / 1e6), "lb_requests_per_s": round(frames_s, 1),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="what", required=True)
    t = sub.add_parser("throughput")
    t.add_argument("--replicas", default="1,2")
    t.add_argument("--sessions", type=int, default=8)
    t.add_argument("--frames", type=int, default=6)
    t.add_argument("--width", type=int, default=512)
    t.add_argument("--height", type=int, default=288)
    t.add_argument("--no-store", action="store_true", help="also one replica alone, no store")
    s = sub.add_parser("store")
    s.add_argument("--sizes", default="1080p")
    s.add_argument("--repeats", type=int, default=5)
    e = sub.add_parser("estimate")
    e.add_argument("--replicas", type=int, default=100)
    e.add_argument("--cameras", type=int, default=1000)
    e.add_argument("--size", default="1080p")
    e.add_argument("--seconds-per-frame", type=float, default=1.85,
                   help="one replica's time per frame (docs/reliability.md: 1080p, 2 threads)")
    args = parser.parse_args(argv)
    if args.what == "throughput":
        size = (args.width, args.height)
        frames = frames_for(args.width, args.height, args.frames)
        runs = [(1, False)] if args.no_store else []
        runs += [(int(n), True) for n in args.replicas.split(",")]
        rows = [throughput(n, args.sessions, frames, size, store) for n, store in runs]
    elif args.what == "store":
        rows = [row for name in args.sizes.split(",") for row in store_costs(name, args.repeats)]
    else:
        rows = [estimate(args.replicas, args.cameras, args.size, args.seconds_per_frame)]
    for row in rows:
        print(json.dumps(row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
