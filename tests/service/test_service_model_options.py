"""A session's run-time model options (`model_options`, `--model-option`) against a real
uvicorn server on 127.0.0.1: the affinity model's kernel size chosen per session changes the
denoised frames, is checked at creation against the model's declared inputs (and, for auto,
against every installed model that declares it), is listed by /v1/models and survives a
restart of a durable server. Copies of the shipped affinity-h16-k5gc, nbg-2l-3g (both take the
frame's spp) and nbg-2l-1g (no run-time options) sit in models_dir; 64x64 frames."""

from __future__ import annotations

import json
import shutil

import httpx
import numpy as np
import pytest
from conftest import LiveServer, read_exr, shot

from quietframe.client import Client
from quietframe.client.cli import build_parser, main, session_options

SIZE = (64, 64)
ALLOWED = [5, 7, 9, 11, 13]
AFFINITY, DEFAULT = "affinity-h16-k5gc", 5  # the shipped affinity model and its card's default
PLAIN = "nbg-2l-1g"  # a shipped model that takes no run-time options
HINT = "GET /v1/models lists each model's options"


@pytest.fixture(scope="module")
def models_dir(tmp_path_factory):
    from quietframe.runtime import find_model

    folder = tmp_path_factory.mktemp("models")
    for name in (AFFINITY, "nbg-2l-3g", PLAIN):
        shutil.copy(find_model(name), folder / f"{name}.onnx")
    return folder


@pytest.fixture(scope="module")
def server(models_dir):
    with LiveServer(models_dir=str(models_dir)) as live:
        yield live


@pytest.fixture(scope="module")
def frames() -> list[bytes]:
    return shot(3, height=SIZE[1], width=SIZE[0])


def colour(data: bytes) -> np.ndarray:
    _, channels = read_exr(data)
    return np.stack([channels[c] for c in "RGB"])


def denoise(url: str, frames: list[bytes], model: str, **options) -> list[np.ndarray]:
    with Client(url) as client:
        session = client.create_session(*SIZE, model=model, model_options=options)
        assert session["model_options"] == options
        out = [colour(client.send_frame(session["id"], i, f).exr) for i, f in enumerate(frames)]
        client.delete_session(session["id"])
    return out


def refused(url: str, model: str, options: dict, code: str = "invalid_model_options") -> str:
    """The detail of a refused creation, checking that no session was created."""
    before = httpx.get(f"{url}/readyz").json()["detail"]["sessions"]
    body = {"width": SIZE[0], "height": SIZE[1], "model": model, "model_options": options}
    r = httpx.post(f"{url}/v1/sessions", json=body)
    assert r.status_code == 422 and r.json()["error"] == code, r.text
    assert httpx.get(f"{url}/readyz").json()["detail"]["sessions"] == before
    return r.json()["detail"]


def test_kernel_size_changes_the_denoised_frames(server, frames):
    nine = denoise(server.url, frames, AFFINITY, kernel_size=9)
    five = denoise(server.url, frames, AFFINITY, kernel_size=5)
    default = denoise(server.url, frames, AFFINITY)  # DEFAULT, the card's
    assert all(np.isfinite(f).all() for f in (*nine, *five))
    for a, b, c in zip(nine, five, default, strict=True):
        assert not np.allclose(a, b, rtol=1e-3, atol=1e-4)
        assert not np.allclose(a, c, rtol=1e-3, atol=1e-4)
    again = denoise(server.url, frames, AFFINITY, kernel_size=9)  # the session's, not noise
    for a, b in zip(nine, again, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_the_session_shows_its_options(server):
    with Client(server.url) as client:
        created = client.create_session(*SIZE, model=AFFINITY,
                                        model_options={"kernel_size": 7})
        status = client.session(created["id"])
        client.delete_session(created["id"])
    assert created["model_options"] == status["model_options"] == {"kernel_size": 7}
    assert isinstance(status["model_options"]["kernel_size"], int)


def test_a_value_outside_the_allowed_ones_is_refused(server):
    detail = refused(server.url, AFFINITY, {"kernel_size": 6})
    assert f"kernel_size must be one of {ALLOWED}, got 6" in detail and HINT in detail
    assert "must be one of" in refused(server.url, AFFINITY, {"kernel_size": 9.5})
    # not a number at all: the request's own validation
    assert "kernel_size" in refused(server.url, AFFINITY, {"kernel_size": "9"},
                                    code="invalid_request")
    refused(server.url, AFFINITY, {"kernel_size": True}, code="invalid_request")


def test_an_unknown_option_names_the_models_options(server):
    detail = refused(server.url, AFFINITY, {"kernal_size": 9})
    assert "has no option kernal_size" in detail
    assert f"its options: kernel_size (one of {ALLOWED}, default {DEFAULT})" in detail


def test_an_option_on_a_model_without_inputs_is_refused(server):
    detail = refused(server.url, PLAIN, {"kernel_size": 9})
    assert f"'{PLAIN}' has no option kernel_size: it takes no run-time options" in detail
    # every installed model that takes the option is named (the shipped affinity tier too)
    named = detail.split("models with kernel_size: ")[1].split(";")[0].split(", ")
    assert AFFINITY in named and "nbg-2l-3g" not in named


def test_auto_takes_an_option_some_model_has_and_gives_it_only_to_those(server, frames):
    with Client(server.url) as client:
        session = client.create_session(*SIZE, model="auto", model_options={"kernel_size": 9})
        assert session["model_options"] == {"kernel_size": 9}
        # auto chooses a measured model (the untrained export has no table): an NBG model,
        # which has no kernel_size and runs without it
        result = client.send_frame(session["id"], 0, frames[0])
        client.delete_session(session["id"])
    assert np.isfinite(colour(result.exr)).all()
    detail = refused(server.url, "auto", {"strength": 1})
    assert "no installed model has option strength" in detail
    assert "options of the installed models: kernel_size" in detail
    assert f"one of {ALLOWED}, got 6" in refused(server.url, "auto", {"kernel_size": 6})


def test_models_lists_each_models_options(server, capsys):
    models = {m["name"]: m for m in httpx.get(f"{server.url}/v1/models").json()["models"]}
    options = {o["name"]: o for o in models[AFFINITY]["options"]}
    assert set(options) == {"kernel_size", "spp"}  # spp: its noise level
    option = options["kernel_size"]
    assert option["name"] == "kernel_size" and option["default"] == DEFAULT
    assert option["allowed"] == ALLOWED and "kernel size" in option["doc"]
    assert [o["name"] for o in models["nbg-2l-3g"]["options"]] == ["spp"]
    assert models[PLAIN]["options"] == []
    assert main(["models", "--server", server.url]) == 0
    listing = capsys.readouterr().out
    assert f"options: kernel_size (default {DEFAULT}; one of 5, 7, 9, 11, 13)" in listing


def test_options_survive_a_restart_and_older_sessions_still_load(tmp_path, models_dir, frames):
    state = tmp_path / "state"
    with LiveServer(models_dir=str(models_dir), state_dir=str(state)) as live:
        reference = denoise(live.url, frames, AFFINITY, kernel_size=9)
        with Client(live.url) as client:
            sid = client.create_session(*SIZE, model=AFFINITY,
                                        model_options={"kernel_size": 9})["id"]
            old = client.create_session(*SIZE, model="nbg-2l-3g")["id"]
            for i in range(2):
                client.send_frame(sid, i, frames[i])
                client.send_frame(old, i, frames[i])
    _strip_model_options(state, old)  # as written before sessions had options
    with LiveServer(models_dir=str(models_dir), state_dir=str(state)) as live, \
            Client(live.url) as client:
        assert client.session(sid)["model_options"] == {"kernel_size": 9}
        assert client.session(old)["model_options"] == {}
        last = client.send_frame(sid, 2, frames[2])
        assert client.send_frame(old, 2, frames[2]).reset == "none"
    assert last.reset == "none"
    np.testing.assert_allclose(colour(last.exr), reference[2], rtol=1e-5, atol=1e-6)


def _strip_model_options(folder, session_id: str) -> None:
    """Remove `model_options` from a durable session's settings file and state file."""
    spec = folder / f"{session_id}.json"
    meta = json.loads(spec.read_text())
    del meta["model_options"]
    spec.write_text(json.dumps(meta))
    path = folder / f"{session_id}.npz"
    with np.load(path) as z:
        arrays = {name: z[name] for name in z.files}
    meta = json.loads(arrays["meta"].tobytes())
    del meta["model_options"]
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    with open(path, "wb") as f:
        np.savez(f, **arrays)


def test_cli_parses_model_options(tmp_path, capsys):
    def parsed(*flags: str) -> dict:
        args = build_parser().parse_args(["denoise", "in/", "--out", "out/", *flags])
        return session_options(args)["model_options"]

    options = parsed("--model-option", "kernel_size=9", "--model-option", "strength=0.5",
                     "--model-option", " gain = 2.0")
    assert options == {"kernel_size": 9, "strength": 0.5, "gain": 2}
    assert [type(v) for v in options.values()] == [int, float, int]
    assert parsed() == {}
    for bad in ("kernel_size", "=9", "kernel_size=big", "kernel_size=nan", "kernel_size="):
        with pytest.raises(SystemExit) as exit_:
            parsed("--model-option", bad)
        assert exit_.value.code == 2
        err = capsys.readouterr().err
        assert "argument --model-option: expected NAME=VALUE" in err and repr(bad) in err


def test_cli_denoise_sends_model_options(tmp_path, server, frames):
    src, out = tmp_path / "in", tmp_path / "out"
    src.mkdir()
    for i, data in enumerate(frames):
        (src / f"shot.{1001 + i}.exr").write_bytes(data)
    code = main(["denoise", "--server", server.url, str(src), "--out", str(out), "--quiet",
                 "--model", AFFINITY, "--model-option", "kernel_size=9"])
    assert code == 0
    expected = denoise(server.url, frames, AFFINITY, kernel_size=9)
    for i, reference in enumerate(expected):
        np.testing.assert_allclose(colour((out / f"shot.{1001 + i}.exr").read_bytes()),
                                   reference, rtol=1e-5, atol=1e-6)
    with pytest.raises(SystemExit):  # a bad option is a usage error before any request
        main(["denoise", "--server", server.url, str(src), "--out", str(out),
              "--model-option", "kernel_size"])


@pytest.fixture(scope="module")
def history_server(tmp_path_factory):
    """A server with oidn-history (which takes the frame's spp) and its pre-stage."""
    pytest.importorskip("pyoidn")
    from quietframe.runtime import find_model

    folder = tmp_path_factory.mktemp("history-models")
    for name in ("oidn-history", "aligned-accumulation"):
        shutil.copy(find_model(name), folder / f"{name}.onnx")
    with LiveServer(models_dir=str(folder)) as live:
        yield live


def sliding_shot(samples: str | None) -> list[bytes]:
    """Three frames of one flat surface under a sub-pixel motion (a history that is resampled),
    fresh noise each; `samples`: the Cycles header's spp (None: no such attribute)."""
    from conftest import LAYOUTS, make_buffers, write_exr

    out = []
    for i in range(3):
        b = make_buffers(height=SIZE[1], width=SIZE[0], noise=100 + i)
        b["normal"][:] = (0.0, 0.0, 1.0)
        b["depth"][:] = 5.0
        header = {"cycles.ViewLayer.samples": samples} if samples else None
        out.append(write_exr(LAYOUTS["plain-normal"](b), header))
    return out


def test_the_header_spp_reaches_a_model_that_takes_it(history_server):
    """oidn-history keeps less resampled history for a cleaner frame: the spp comes from the
    Cycles header, or the session's option, which wins over the header's; 0 is refused. (The
    Cycles header also turns OIDN's rows bottom-up, so the shots compared all carry it.)"""
    url = history_server.url
    stated = {s: denoise(url, sliding_shot(s), "oidn-history") for s in ("1", "64")}
    assert np.allclose(stated["1"][0], stated["64"][0], atol=1e-6)  # no history yet
    assert not np.allclose(stated["1"][-1], stated["64"][-1], rtol=1e-3, atol=1e-4)
    optioned = denoise(url, sliding_shot("1"), "oidn-history", spp=64)
    for a, b in zip(stated["64"], optioned, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    unstated = denoise(url, sliding_shot(None), "oidn-history", spp=64)  # no header: top-down
    assert not np.allclose(unstated[0], stated["64"][0], rtol=1e-3, atol=1e-4)
    assert "spp must be at least 1, got 0" in refused(url, "oidn-history", {"spp": 0})
    listed = {m["name"]: m["options"] for m in httpx.get(f"{url}/v1/models").json()["models"]}
    assert [(o["name"], o["default"], o["minimum"]) for o in listed["oidn-history"]] == [
        ("spp", 4.0, 1.0)]
