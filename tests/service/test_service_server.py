"""Against a real uvicorn server on 127.0.0.1: round trips, concurrent sessions, state isolation,
retry races, and a killed-and-restarted server with durable state."""

from __future__ import annotations

import signal
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from conftest import LAYOUTS, make_buffers, read_exr, shot, write_exr
from server_support import free_port, start_cli_server

from quietframe.client import Client

SIZE = (64, 48)


def colour(data: bytes) -> np.ndarray:
    """The denoised colour of a reply (the reply holds every channel of the input)."""
    _, channels = read_exr(data)
    for prefix in ("ViewLayer.Combined.", "Ci.", ""):
        for names in ([prefix + c for c in "RGB"], [prefix + c for c in "rgb"]):
            if all(n in channels for n in names):
                return np.stack([channels[n] for n in names], -1)
    raise AssertionError(f"no colour channels in {sorted(channels)}")


def run_sequence(url: str, frames: list[bytes], first: int = 0,
                 model: str = "auto") -> list[bytes]:
    with Client(url) as client:
        sid = client.create_session(*SIZE, model)["id"]
        return [client.send_frame(sid, first + i, f).exr for i, f in enumerate(frames)]


def test_sequence_round_trip(live_server):
    # A model with history: auto serves a static shot (all-zero Vector) per frame.
    frames, model = shot(6, "blender"), "nbg-2l-3g"
    with Client(live_server.url) as client:
        session = client.create_session(*SIZE, model, precision="half")
        results = [client.send_frame(session["id"], i, f) for i, f in enumerate(frames)]
        status = client.session(session["id"])
        client.delete_session(session["id"])
    assert [r.reset for r in results] == ["first-frame"] + ["none"] * 5
    # A static shot: its Vector layer is all zero, reported missing (not a static camera).
    assert all(r.timings_ms["denoise"] > 0 and r.missing == ("motion",) for r in results)
    header, channels = read_exr(results[-1].exr)
    _, given = read_exr(frames[-1])
    assert sorted(channels) == sorted(given)  # every channel comes back
    beauty = {f"ViewLayer.Combined.{c}" for c in "RGB"}
    assert all(channels[n].dtype == np.float16 for n in beauty)  # precision: the colour only
    assert all(c.dtype == np.float32 for n, c in channels.items() if n not in beauty)
    assert all(c.shape == (48, 64) for c in channels.values())
    assert header["quietframe.frame"] == "5"
    assert np.isfinite(colour(results[-1].exr)).all()
    assert status["frames_done"] == 6 and status["last_index"] == 5
    # Temporal history is used: the last frame differs from the same frame denoised alone.
    alone = run_sequence(live_server.url, frames[-1:], model=model)[0]
    assert not np.allclose(colour(results[-1].exr), colour(alone), rtol=1e-3, atol=1e-4)


def test_concurrent_sessions_are_isolated(live_server):
    shots = [
        shot(4, layout, seed=k)
        for k, layout in enumerate(["plain-normal", "arnold", "renderman-ci", "blender"])
    ]
    references = [run_sequence(live_server.url, s) for s in shots]
    with ThreadPoolExecutor(4) as pool:
        results = list(pool.map(lambda s: run_sequence(live_server.url, s), shots))
    for got, expected in zip(results, references, strict=True):
        for a, b in zip(got, expected, strict=True):
            np.testing.assert_allclose(colour(a), colour(b), rtol=1e-5, atol=1e-6)


def test_same_frame_sent_twice_at_once_is_denoised_once(live_server):
    frames = shot(2)
    with Client(live_server.url) as client:
        sid = client.create_session(*SIZE)["id"]
        client.send_frame(sid, 0, frames[0])
        with ThreadPoolExecutor(3) as pool:
            results = list(pool.map(lambda _: client.send_frame(sid, 1, frames[1]), range(3)))
        assert len({r.exr for r in results}) == 1
        assert sorted(r.replayed for r in results) == [False, True, True]
        assert client.session(sid)["frames_done"] == 2


def test_async_client_streams_sessions_in_parallel(live_server):
    import asyncio

    from quietframe.client import AsyncClient

    shots = [shot(3, seed=k) for k in range(3)]

    async def one(client, frames):
        sid = (await client.create_session(*SIZE))["id"]
        out = [await client.send_frame(sid, i, f) for i, f in enumerate(frames)]
        await client.delete_session(sid)
        return out

    async def main():
        async with AsyncClient(live_server.url) as client:
            return await asyncio.gather(*(one(client, s) for s in shots))

    results = asyncio.run(main())
    assert [[r.reset for r in seq] for seq in results] == [["first-frame", "none", "none"]] * 3


def test_killed_server_continues_sequence_from_durable_state(tmp_path, live_server):
    frames = shot(5, "arnold")
    reference = run_sequence(live_server.url, frames)
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    server = start_cli_server(port, tmp_path, QUIETFRAME_LOG_JSON="true")
    try:
        with Client(url) as client:
            sid = client.create_session(*SIZE)["id"]
            first = [client.send_frame(sid, i, frames[i]) for i in range(3)]
        server.send_signal(signal.SIGKILL)  # no shutdown hook: only what was on disk survives
        server.wait(timeout=30)
        assert sorted(p.name for p in tmp_path.iterdir()) == [f"{sid}.json", f"{sid}.npz"]
        server = start_cli_server(port, tmp_path, QUIETFRAME_LOG_JSON="true")
        with Client(url) as client:
            assert client.session(sid)["last_index"] == 2
            retry = client.send_frame(sid, 2, frames[2])  # the lost-response retry, after restart
            rest = [client.send_frame(sid, i, frames[i]) for i in (3, 4)]
            client.delete_session(sid)
        assert retry.replayed and retry.exr == first[2].exr
        assert [r.reset for r in rest] == ["none", "none"]  # no visible reset
        # the reference ran without a store: a stored history is rounded to float16
        # (state_codec), which moves later frames by a few 1e-5
        for got, expected in zip(first + rest, reference, strict=True):
            np.testing.assert_allclose(colour(got.exr), colour(expected), rtol=1e-3, atol=1e-5)
        assert not list(tmp_path.iterdir())  # deleted sessions leave no state behind
    finally:
        server.kill()
        server.wait(timeout=30)


def test_motion_estimated_from_the_aux_survives_a_kill(tmp_path):
    """A motion-blurred Cycles pan (all-zero Vector): the history follows motion estimated from
    the aux, whose forward-backward check reads the previous frame's depth, kept beside the
    probe in the stored state. After kill -9 the next frames continue exactly as a session of
    the same durable server that was never killed: the same estimate, no reset, the same
    bytes (the writer continues from the stored values, state_codec)."""
    from pathlib import Path

    sequences = Path(__file__).resolve().parents[1] / "fixtures" / "blender_sequences"
    frames = [(sequences / f"motion_blur.{t:04d}.exr").read_bytes() for t in range(1, 5)]
    model, size = "oidn-fast-history", (128, 72)
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    server = start_cli_server(port, tmp_path, QUIETFRAME_LOG_JSON="true")
    try:
        with Client(url) as client:
            sid = client.create_session(*size, model)["id"]
            reference = [client.send_frame(sid, i, f) for i, f in enumerate(frames)]
            client.delete_session(sid)
            sid = client.create_session(*size, model)["id"]
            first = [client.send_frame(sid, i, frames[i]) for i in range(2)]
        assert all("motion estimated from the aux" in r.motion for r in reference[1:])
        server.send_signal(signal.SIGKILL)
        server.wait(timeout=30)
        assert b"motion_depth" in np.load(tmp_path / f"{sid}.npz")["meta"].tobytes()
        server = start_cli_server(port, tmp_path, QUIETFRAME_LOG_JSON="true")
        with Client(url) as client:
            rest = [client.send_frame(sid, i, frames[i]) for i in (2, 3)]
            client.delete_session(sid)
        assert [r.reset for r in rest] == ["none", "none"]
        for got, expected in zip(first + rest, reference, strict=True):
            assert got.motion == expected.motion  # the same share of the frame trusted
            np.testing.assert_array_equal(colour(got.exr), colour(expected.exr))
    finally:
        server.kill()
        server.wait(timeout=30)


@pytest.mark.parametrize("layout", ["blender", "renderman-rgb"])
def test_missing_motion_over_http(live_server, layout):
    data = write_exr(LAYOUTS[layout](make_buffers(motion=False)))
    with Client(live_server.url) as client:
        sid = client.create_session(*SIZE, model="nbg-2l-3g")["id"]  # motion optional
        assert client.send_frame(sid, 0, data).missing == ("motion",)
