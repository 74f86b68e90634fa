"""A model asked for by name at an spp where its card's `input_margin` says it made a
validation-zoo shot worse than its own noisy input is served as asked, and the reply says so in
X-Quietframe-Warning (service/below_input.py); `auto` and models without the figure get no
warning (a frame whose spp nothing states is judged at the shot's estimate: test_shot_samples).
Over a real socket, with the shipped cards."""

from __future__ import annotations

import httpx
import pytest
from conftest import LAYOUTS, make_buffers, write_exr

from quietframe.wire.protocol import Header

SIZE = {"width": 64, "height": 48}
LEARNED = "nbg-2l-3g"  # below its input from 11.6 spp on a validation shot (its card)


def frame(spp: float | None, seed: int = 1) -> bytes:
    """A Cycles frame whose header states `spp` (None: no spp attribute, a plain layout)."""
    if spp is None:
        return write_exr(LAYOUTS["plain-normal"](make_buffers(noise=seed)))
    return write_exr(LAYOUTS["blender"](make_buffers(noise=seed)),
                     {"cycles.ViewLayer.samples": str(spp)})


def installed(url: str, *names: str) -> None:
    models = {m["name"] for m in httpx.get(f"{url}/v1/models").json()["models"]}
    if not set(names) <= models:
        pytest.skip(f"needs {', '.join(names)} installed")


def create(url: str, **fields) -> httpx.Response:
    reply = httpx.post(f"{url}/v1/sessions", json={**SIZE, **fields})
    assert reply.status_code == 201, reply.text
    return reply


def send(url: str, sid: str, index: int, body: bytes) -> httpx.Response:
    reply = httpx.post(f"{url}/v1/sessions/{sid}/frames/{index}", content=body,
                       headers={"content-type": "image/x-exr"}, timeout=60)
    assert reply.status_code in (200, 202), reply.text
    return reply


def warning_of(url: str, spp: float | None, model: str) -> str | None:
    sid = create(url, model=model).json()["id"]
    try:
        return send(url, sid, 0, frame(spp)).headers.get(Header.WARNING)
    finally:
        httpx.delete(f"{url}/v1/sessions/{sid}")


def test_a_named_learned_model_above_its_range_is_served_with_the_warning(live_server):
    url = live_server.url
    installed(url, LEARNED)
    sid = create(url, model=LEARNED).json()["id"]
    body = frame(64)
    reply = send(url, sid, 0, body)
    assert reply.headers[Header.MODEL].startswith(f"{LEARNED} ")
    assert reply.content[:4] == b"v/1\x01"  # the denoised EXR, as asked
    text = reply.headers[Header.WARNING]
    assert text == (f"{LEARNED} is below its own noisy input from 11.6 spp on a validation-zoo "
                    "shot (this frame: 64 spp, -1.35 dB there); use model=auto or an OIDN tier")
    assert text.isascii()
    # the retry's stored reply says it again, and so does every later frame at that spp
    again = send(url, sid, 0, body)
    assert again.headers[Header.REPLAYED] == "true" and again.headers[Header.WARNING] == text
    assert send(url, sid, 1, frame(64, seed=2)).headers[Header.WARNING] == text
    # the same session's frame at 2 spp is within the model's range
    assert Header.WARNING not in send(url, sid, 2, frame(2, seed=3)).headers
    httpx.delete(f"{url}/v1/sessions/{sid}")


@pytest.mark.parametrize("spp, model", [
    (1, LEARNED),  # in its range: +6.96 dB over its input on the worst shot
    (64, "auto"),  # auto never runs it there
    (64, "oidn-frame"),  # no input_margin section on its card
])
def test_no_warning_in_range_for_auto_or_without_the_figure(
        live_server, spp, model):
    url = live_server.url
    installed(url, LEARNED, "oidn-frame")
    assert warning_of(url, spp, model) is None


def test_auto_running_the_learned_model_for_its_shot_is_not_warned(live_server):
    """An auto session told the shot's model (`shot_model`, another chunk's choice) runs it at
    64 spp without a warning: the choice was auto's, not the user's naming of a model."""
    url = live_server.url
    installed(url, LEARNED)
    sid = create(url, model="auto").json()["id"]
    try:
        reply = httpx.post(f"{url}/v1/sessions/{sid}/frames/0", content=frame(64),
                           params={"shot_model": LEARNED},
                           headers={"content-type": "image/x-exr"}, timeout=60)
        assert reply.status_code == 200, reply.text
        assert reply.headers[Header.MODEL].startswith(f"{LEARNED} ")
        assert Header.WARNING not in reply.headers
    finally:
        httpx.delete(f"{url}/v1/sessions/{sid}")


def test_a_look_ahead_session_releases_the_frame_with_its_warning(live_server):
    url = live_server.url
    installed(url, LEARNED)
    sid = create(url, model=LEARNED, lookahead=1).json()["id"]
    try:
        assert send(url, sid, 0, frame(64)).status_code == 202
        released = send(url, sid, 1, frame(1, seed=2))  # carries frame 0, at 64 spp
        assert released.headers[Header.FRAME] == "0"
        assert "(this frame: 64 spp" in released.headers[Header.WARNING]
        finished = httpx.post(f"{url}/v1/sessions/{sid}/frames/1/finish", timeout=60)
        assert finished.status_code == 200 and Header.WARNING not in finished.headers
    finally:
        httpx.delete(f"{url}/v1/sessions/{sid}")


def test_a_session_created_with_an_spp_option_in_the_range_is_warned_at_creation(live_server):
    """The learned tiers read the frame's spp (their noise level), so a session may state it as
    model_options.spp: nbg-2l-3g's card puts 64 spp in the range where it loses to its input."""
    url = live_server.url
    installed(url, LEARNED)
    created = create(url, model=LEARNED, model_options={"spp": 64})
    text = created.headers[Header.WARNING]
    assert text.startswith(f"{LEARNED} is below its own noisy input from 11.6 spp")
    assert "(the session's model_options.spp: 64 spp, -1.35 dB there)" in text
    sid = created.json()["id"]
    try:  # the option is the frame's spp too, whatever its header says (none here)
        reply = send(url, sid, 0, frame(None))
        assert "(this frame: 64 spp, -1.35 dB there)" in reply.headers[Header.WARNING]
    finally:
        httpx.delete(f"{url}/v1/sessions/{sid}")
    low = create(url, model=LEARNED, model_options={"spp": 4})  # +0.81 dB there: in range
    assert Header.WARNING not in low.headers
    httpx.delete(f"{url}/v1/sessions/{low.json()['id']}")
