"""A session naming a model that reads the frame's spp (the noise-aware learned tiers, the
oidn-history tiers), on frames whose header states none and without a `spp` option: the spp is
estimated at the shot's first frame (service/shot_choice.estimate_for_shot), the model given it
for every frame of the shot, the reply saying it in X-Quietframe-Samples; a cut estimates again,
and a durable session keeps the shot's estimate across a restart. Over a real socket."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from conftest import LAYOUTS, LiveServer, make_buffers, read_exr, write_exr

from quietframe.client import Client
from quietframe.service.noise_estimate import load_calibration, shot_samples

SIZE = (64, 48)
LEARNED = "nbg-2l-3g"  # reads the spp; below its own input from some spp on (its card)
PLAIN = "nbg-2l-1g"  # reads none


def noisy_frame(lit: float, seed: int = 1) -> tuple[bytes, dict[str, np.ndarray]]:
    """A smooth picture and no spp in its header: with `lit` 1 every pixel has 1% grain (a
    clean frame), below 1 only that share of pixels got light, scaled up (a frame of very few
    samples)."""
    b = make_buffers(height=SIZE[1], width=SIZE[0])
    y, x = np.mgrid[0 : SIZE[1], 0 : SIZE[0]]
    smooth = np.stack([0.5 + 0.3 * x / SIZE[0], 0.4 + 0.2 * y / SIZE[1], 0.3 + 0 * x], -1)
    rng = np.random.default_rng(seed)
    if lit >= 1:
        light = 1 + 0.01 * rng.standard_normal((SIZE[1], SIZE[0], 1))
    else:
        light = (rng.random((SIZE[1], SIZE[0], 1)) < lit) / lit
    b["color"] = np.maximum(smooth * light, 0).astype(np.float32)
    b["albedo"][:] = 0.5
    return write_exr(LAYOUTS["plain-normal"](b)), b


CLEAN, GRAINY = 1.0, 0.05  # estimated at the calibration's ceiling (32), and at ~3 spp


def expected(lit: float, seed: int = 1) -> float:
    """What the service's estimate must say for noisy_frame(lit, seed) (the shipped fit)."""
    _, b = noisy_frame(lit, seed)
    spp = shot_samples(b["color"].transpose(2, 0, 1), b["albedo"].transpose(2, 0, 1),
                       load_calibration())
    assert spp is not None
    return spp


def below_input_from(name: str) -> float:
    """The spp from which the model's card says it is below its own noisy input."""
    from quietframe.runtime import Denoiser, find_model
    from quietframe.service.model_profiles import profile_of

    start = profile_of(name, Denoiser(find_model(name), threads=1), None).worse_than_input_from()
    assert start is not None
    return start


def colour(data: bytes) -> np.ndarray:
    _, channels = read_exr(data)
    return np.stack([channels[c] for c in "RGB"])


def test_a_named_model_is_given_the_shots_estimate_until_the_next_cut(live_server):
    clean, grainy = expected(CLEAN), expected(GRAINY, seed=3)
    # the shipped fit tells them apart, on either side of where the card says the model goes
    # below its input (a frame there would be warned, were its spp stated)
    assert clean > below_input_from(LEARNED) > grainy >= 1
    with Client(live_server.url) as client:
        sid = client.create_session(*SIZE, model=LEARNED)["id"]
        first = client.send_frame(sid, 0, noisy_frame(CLEAN)[0])
        assert first.samples == f"{clean:g}; source=estimate"
        # an estimate is not judged against the card: it is off by stops at either end
        assert not first.warning
        # the shot's other frames keep its estimate, whatever their own noise
        later = client.send_frame(sid, 1, noisy_frame(GRAINY, seed=2)[0])
        assert later.samples == first.samples and later.reset == "none"
        # a cut starts a new shot: estimated again
        body = noisy_frame(GRAINY, seed=3)[0]
        cut = client.send_frame(sid, 2, body, cut=True)
        assert cut.samples == f"{grainy:g}; source=estimate"
        # the model was given the estimate: the same pixels as a session stating it
        stated = client.create_session(*SIZE, model=LEARNED, model_options={"spp": grainy})
        same = client.send_frame(stated["id"], 0, body)
        assert not same.samples
        np.testing.assert_allclose(colour(cut.exr), colour(same.exr), rtol=1e-5, atol=1e-6)


def test_a_black_first_frame_leaves_the_estimate_to_the_next_frame(live_server):
    b = make_buffers(height=SIZE[1], width=SIZE[0])
    b["color"][:] = 0
    black = write_exr(LAYOUTS["plain-normal"](b))
    with Client(live_server.url) as client:
        sid = client.create_session(*SIZE, model=LEARNED)["id"]
        assert not client.send_frame(sid, 0, black).samples  # nothing to measure: the default
        second = client.send_frame(sid, 1, noisy_frame(CLEAN)[0])
        third = client.send_frame(sid, 2, noisy_frame(GRAINY, seed=2)[0])
    assert second.samples == third.samples == f"{expected(CLEAN):g}; source=estimate"


def test_no_estimate_where_the_spp_is_stated_or_not_read(live_server):
    body = noisy_frame(CLEAN)[0]
    cycles = make_buffers(height=SIZE[1], width=SIZE[0], noise=4)
    with Client(live_server.url) as client:
        for model, options, frame in (
            (LEARNED, {"spp": 8}, body),  # the session states it
            (LEARNED, {}, write_exr(LAYOUTS["blender"](cycles),
                                    {"cycles.ViewLayer.samples": "8"})),  # the header does
            (PLAIN, {}, body),  # the model reads no spp
            ("auto", {}, body),  # auto says its estimate in X-Quietframe-Choice
        ):
            sid = client.create_session(*SIZE, model=model, model_options=options)["id"]
            result = client.send_frame(sid, 0, frame)
            assert not result.samples, (model, options)
            client.delete_session(sid)


def test_a_durable_session_keeps_its_shots_estimate_across_a_restart(tmp_path):
    state = tmp_path / "state"
    with LiveServer(state_dir=str(state)) as live, \
            Client(live.url) as client:
        sid = client.create_session(*SIZE, model=LEARNED)["id"]
        first = client.send_frame(sid, 0, noisy_frame(CLEAN)[0])
    with LiveServer(state_dir=str(state)) as live, \
            Client(live.url) as client:
        after = client.send_frame(sid, 1, noisy_frame(GRAINY, seed=2)[0])
    assert after.reset == "none" and after.samples == first.samples
    assert after.samples == f"{expected(CLEAN):g}; source=estimate"


@pytest.mark.skipif(not shutil.which("redis-server"), reason="needs redis-server")
def test_a_replica_adopting_the_session_keeps_the_shots_estimate(tmp_path):
    """Two replicas sharing Redis: the shot's first frame on one, the next on the other, which
    adopts the session from the store with its shot's estimate."""
    from conftest import redis_server, service_settings
    from fastapi.testclient import TestClient

    from quietframe.service.main import create_app
    from quietframe.wire.protocol import Header

    with redis_server(tmp_path) as url:
        a, b = (TestClient(create_app(service_settings(replica_id=name, store_url=url)))
                for name in "ab")
        with a, b:
            sid = a.post("/v1/sessions", json={"width": SIZE[0], "height": SIZE[1],
                                               "model": LEARNED}).json()["id"]
            replies = [c.post(f"/v1/sessions/{sid}/frames/{i}", content=noisy_frame(lit, i)[0],
                              headers={"content-type": "image/x-exr"})
                       for i, (c, lit) in enumerate(((a, CLEAN), (b, GRAINY)))]
    assert [r.status_code for r in replies] == [200, 200]
    assert replies[1].headers[Header.RESET] == "none"
    assert (replies[1].headers[Header.SAMPLES] == replies[0].headers[Header.SAMPLES]
            == f"{expected(CLEAN, seed=0):g}; source=estimate")
