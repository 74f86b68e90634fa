"""Shared fixtures. Service/client: EXR frames in the channel layouts of common renderers."""

from __future__ import annotations

import contextlib
import io
import signal

import numpy as np
import pytest

# ---- EXR frames in renderer layouts (service and client tests) ------------------------------
# Every layout is a function (buffers) -> {channel name: (H, W) array}, where `buffers` holds
# canonical arrays in quietframe's convention; motion is converted *into* the renderer's
# convention here, so a test can check that the service converts it back.


def _split(array: np.ndarray, names: str | list[str], prefix: str) -> dict[str, np.ndarray]:
    return {f"{prefix}{n}": array[..., i] for i, n in enumerate(names)}


def layout_blender(b, view_layer="ViewLayer", noisy=False):
    color_layer = "Noisy Image" if noisy else "Combined"
    ch = _split(b["color"], "RGB", f"{view_layer}.{color_layer}.")
    ch[f"{view_layer}.{color_layer}.A"] = np.ones_like(b["depth"])
    if noisy:  # Blender's own denoised Combined sits next to the noisy image
        ch.update(_split(b["color"] * 0 + 7, "RGB", f"{view_layer}.Combined."))
    ch.update(_split(b["albedo"], "RGB", f"{view_layer}.Denoising Albedo."))
    ch.update(_split(b["normal"], "XYZ", f"{view_layer}.Denoising Normal."))
    ch[f"{view_layer}.Denoising Depth.Z"] = b["depth"]
    ch[f"{view_layer}.Depth.Z"] = b["depth"] + 100  # plain Z pass: lower priority
    if "motion" in b:
        # Cycles Vector.XY: position in t-1 minus position in t, raster y up; ZW: position in
        # t minus position in t+1 at constant velocity (forward motion -motion: (-Z, +W)).
        m = b["motion"]
        ch[f"{view_layer}.Vector.X"], ch[f"{view_layer}.Vector.Y"] = m[..., 0], -m[..., 1]
        ch[f"{view_layer}.Vector.Z"], ch[f"{view_layer}.Vector.W"] = m[..., 0], -m[..., 1]
    return ch


def layout_arnold(b, old=False):
    ch = _split(b["color"], "RGB", "")
    ch["A"] = np.ones_like(b["depth"])
    ch.update(_split(b["albedo"], "RGB", "diffuse_albedo." if old else "denoise_albedo."))
    ch.update(_split(b["normal"], "XYZ", "N."))
    ch["Z"] = b["depth"]
    if "motion" in b:  # raw forward screen motion over the shutter (one frame), y up
        m = b["motion"]
        ch.update(
            _split(np.stack([-m[..., 0], m[..., 1], 0 * m[..., 0]], -1), "RGB", "motionvector.")
        )
    return ch


def layout_renderman(b, beauty="Ci"):
    ch = _split(b["color"], "rgb", "Ci.") if beauty == "Ci" else _split(b["color"], "RGB", "")
    ch["a"] = np.ones_like(b["depth"])
    ch.update(_split(b["albedo"], "rgb", "albedo."))
    ch.update(_split(b["normal"], "xyz", "Nn."))
    ch["z"] = b["depth"]
    if "motion" in b:  # backward: offset to the previous frame; forward: to the next
        ch.update(_split(b["motion"], "rg", "backward."))
        ch.update(_split(-b["motion"], "rg", "forward."))
    return ch


def layout_plain(b, normal_prefix="normal.", depth_name="Z"):
    ch = _split(b["color"], "RGB", "")
    ch.update(_split(b["albedo"], "RGB", "albedo."))
    ch.update(_split(b["normal"], "XYZ", normal_prefix))
    ch[depth_name] = b["depth"]
    if "motion" in b:
        ch.update(_split(b["motion"], "XY", "motion."))
    return ch


LAYOUTS = {
    "blender": layout_blender,
    "blender-noisy-image": lambda b: layout_blender(b, noisy=True),
    "arnold": layout_arnold,
    "arnold-old-albedo": lambda b: layout_arnold(b, old=True),
    "renderman-ci": layout_renderman,
    "renderman-rgb": lambda b: layout_renderman(b, beauty="RGB"),
    "plain-normal": layout_plain,
    "plain-N-depth": lambda b: layout_plain(b, normal_prefix="N.", depth_name="depth"),
}


def make_buffers(height=48, width=64, seed=0, motion=True, noise=None) -> dict[str, np.ndarray]:
    """Canonical buffers with distinct values per channel, so a wrong mapping shows. `noise`
    seeds the colour alone: frames of one static shot share geometry and differ in noise."""
    rng = np.random.default_rng(seed)
    normal = rng.normal(size=(height, width, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    b = {
        "color": (rng.random((height, width, 3)) * [1.0, 2.0, 3.0]).astype(np.float32),
        "albedo": (0.2 + 0.1 * rng.random((height, width, 3)) + [0.0, 0.2, 0.4]).astype(np.float32),
        "normal": normal,
        "depth": (5.0 + rng.random((height, width))).astype(np.float32),
    }
    if noise is not None:
        b["color"] = (
            np.random.default_rng(noise).random((height, width, 3)) * [1.0, 2.0, 3.0]
        ).astype(np.float32)
    if motion:
        b["motion"] = np.stack(
            [np.full((height, width), 1.5), np.full((height, width), -0.5)], -1
        ).astype(np.float32)
    return b


def write_exr(
    channels: dict[str, np.ndarray], header: dict | None = None, dtype=np.float32, compression=None
) -> bytes:
    import OpenEXR

    attributes = {
        "compression": compression if compression is not None else OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
    }
    attributes.update(header or {})
    arrays = {k: np.ascontiguousarray(v, dtype=dtype) for k, v in channels.items()}
    out = io.BytesIO()
    OpenEXR.File(attributes, arrays).write(out)
    return out.getvalue()


def read_exr(data: bytes) -> tuple[dict, dict[str, np.ndarray]]:
    import OpenEXR

    f = OpenEXR.File(io.BytesIO(data), separate_channels=True)
    return f.header(), {k: v.pixels for k, v in f.channels().items()}


def frame_bytes(
    layout="plain-normal", seed=0, height=48, width=64, motion=True, header=None, dtype=np.float32
) -> bytes:
    return write_exr(LAYOUTS[layout](make_buffers(height, width, seed, motion)), header, dtype)


def shot(n: int, layout="plain-normal", **kw) -> list[bytes]:
    """`n` frames of one static shot: same geometry (zero motion), fresh colour noise each."""
    frames = []
    for i in range(n):
        b = make_buffers(noise=100 + i, **kw)
        b["motion"][:] = 0
        frames.append(write_exr(LAYOUTS[layout](b)))
    return frames


# ---- runtime settings -----------------------------------------------------------------------


@pytest.fixture
def runtime_env(monkeypatch):
    """set(name, value) sets a variable the runtime reads (None: unsets it) and has the runtime's
    settings read again: runtime/settings.py reads them once per process. After the test they
    are read again from the restored environment."""
    from quietframe.runtime.settings import runtime_settings

    def set_variable(name: str, value: str | None) -> None:
        if value is None:
            monkeypatch.delenv(name, raising=False)
        else:
            monkeypatch.setenv(name, value)
        runtime_settings.cache_clear()

    yield set_variable
    runtime_settings.cache_clear()


# ---- service fixtures -----------------------------------------------------------------------


def service_settings(**overrides):
    """Settings for tests: small thread counts; models from the package (or
    QUIETFRAME_MODELS_DIR, read by Settings itself)."""
    import os

    from quietframe.runtime import installed_models
    from quietframe.service.settings import Settings

    if not installed_models() and not os.environ.get("QUIETFRAME_MODELS_DIR"):
        pytest.skip("no model in quietframe.models (models/*.onnx) and no QUIETFRAME_MODELS_DIR")

    base = {"threads": 1, "workers": 2, "log_json": False}
    base.update(overrides)
    return Settings(**base)


_LOADED: dict[tuple, object] = {}  # the installed models, loaded once per (threads, default)


def loaded_models(settings):
    """A model registry for `settings`, shared by the apps of this test run where the settings
    install nothing of their own (loading every model costs ~1 s an app); None otherwise."""
    from quietframe.service.model_registry import ModelRegistry

    if settings.models_dir is not None:
        return None  # a test's own folder may change between its apps
    key = (settings.model_threads, settings.default_model)
    if key not in _LOADED:
        _LOADED[key] = ModelRegistry(settings)
    return _LOADED[key]


def app_for(settings):
    from quietframe.service.main import create_app

    return create_app(settings, loaded=loaded_models(settings))


def serve(kind: str, **overrides):
    """(started client, server or None): TestClient in-process, or a LiveServer + httpx."""
    if kind == "testclient":
        from fastapi.testclient import TestClient

        client = TestClient(app_for(service_settings(**overrides)))
        client.__enter__()
        return client, None
    import httpx

    server = LiveServer(**overrides).__enter__()
    return httpx.Client(base_url=server.url, timeout=60), server


def close(client, server) -> None:
    if server is None:
        client.__exit__(None, None, None)
    else:
        client.close()
        server.__exit__()


class ThreadedServer:
    """An ASGI app served by uvicorn on 127.0.0.1 in a background thread; `url` once entered."""

    start_timeout_s = 60

    def __init__(self, app, port: int = 0) -> None:
        import threading

        import uvicorn

        self.app = app
        config = uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning")
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    def __enter__(self):
        import time

        self.thread.start()
        deadline = time.monotonic() + self.start_timeout_s
        while not self.server.started:
            if not self.thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError(f"{type(self).__name__} did not start")
            time.sleep(0.02)
        port = self.server.servers[0].sockets[0].getsockname()[1]
        self.port, self.url = port, f"http://127.0.0.1:{port}"
        return self

    def __exit__(self, *_) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=30)


class LiveServer(ThreadedServer):
    """A real quietframe server on 127.0.0.1 in a background thread."""

    def __init__(self, port: int = 0, **overrides) -> None:
        super().__init__(app_for(service_settings(**overrides)), port)


@pytest.fixture(scope="session")
def live_server():
    """One default server for the whole run (loading and warming every model costs seconds a
    start); tests that need other settings start their own."""
    with LiveServer() as server:
        yield server


@contextlib.contextmanager
def hard_timeout(seconds: int):
    """Raise TimeoutError in the test once it runs past `seconds` (pytest-timeout is not a
    dependency): tests that drive servers and sockets must not hang the suite."""

    def expire(*_) -> None:
        raise TimeoutError(f"test ran past {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


@contextlib.contextmanager
def redis_server(folder):
    """A redis-server on loopback for the tests of the Redis store, no persistence; its URL.
    Skips the test where redis-server is not installed (Debian package redis-server)."""
    import shutil
    import socket
    import subprocess
    import time

    import redis

    if not shutil.which("redis-server"):
        pytest.skip("needs redis-server (Debian package redis-server)")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = subprocess.Popen(
        ["redis-server", "--port", str(port), "--bind", "127.0.0.1", "--save", "",
         "--appendonly", "no", "--dir", str(folder)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    try:
        client, deadline = redis.Redis(port=port, socket_timeout=1), time.monotonic() + 10
        while True:
            try:
                client.ping()
                break
            except redis.RedisError:
                assert time.monotonic() < deadline, "redis-server did not start"
                time.sleep(0.05)
        yield f"redis://127.0.0.1:{port}/0"
    finally:
        server.terminate()
        server.wait(10)
