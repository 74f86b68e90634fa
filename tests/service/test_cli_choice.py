"""model=auto decides on what a frame really carries (present but unusable buffers count as
absent), and says so in an ASCII header; the CLI's model table."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from quietframe.client import Client
from quietframe.runtime.usable_buffers import unusable_buffers

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures" / "blender"


def test_unusable_buffers_all_zero_motion_and_constant_depth():
    moving = np.zeros((2, 4, 4), np.float32)
    moving[0, 1, 1] = 0.5
    depth = np.full((1, 4, 4), 7.0, np.float32)
    depth[0, 0] = 0.0  # sky: a no-hit marker, not a second depth
    depth[0, 1] = 1e10
    assert unusable_buffers({"motion": moving * 0, "depth": depth}) == ("motion", "depth")
    varied = depth.copy()
    varied[0, 3, 3] = 9.0
    assert unusable_buffers({"motion": moving, "depth": varied, "color": moving}) == ()
    assert unusable_buffers({"depth": np.zeros((1, 4, 4), np.float32)}) == ("depth",)


def test_auto_on_motion_blur_frames_keeps_one_model_and_follows_the_aux(live_server):
    """Cycles writes an all-zero Vector with motion blur on. That is no evidence either way (a
    locked-off shot writes the same), so auto decides as if the pass were there, and the
    chosen model reads its history along motion estimated from the aux where the aux moved:
    on this moving camera frame 3 keeps its history (reset `none`, the estimate's share in
    X-Quietframe-Motion) and the same model, so nothing pops; with `motion: rendered-only` it
    comes back with a fresh history (`no-usable-motion`) instead."""
    for fields, reset, said in (({}, "none", "motion estimated from the aux"),
                                ({"motion": "rendered-only"}, "no-usable-motion",
                                 "history not used")):
        with Client(live_server.url) as client:
            temporal = {m["name"] for m in client.models()["models"] if m["state"]}
            session = client.create_session(64, 36, **fields)
            try:
                results = [client.send_frame(session["id"], t, (
                    FIXTURES / f"motion_blur.{t:04d}.exr").read_bytes()) for t in (2, 3)]
                choice = client.session(session["id"])["choice"]
            finally:
                client.delete_session(session["id"])
        assert "motion" in choice["buffers"]  # counted as present: the history follows the aux
        assert results[0].model == results[1].model  # one model for the shot
        if choice["model"] in temporal:
            assert results[1].reset == reset, results[1]
            assert results[1].motion.startswith("moving") and said in results[1].motion, \
                results[1].motion


def test_choice_header_is_ascii_and_spells_symbols_out():
    from quietframe.service.choice_policy import Choice
    from quietframe.service.shot_choice import choice_header

    choice = Choice("m", "looks like log2 σ 3.82, 1.1× the steadiest", 4.0, "estimate", ())
    text = choice_header(choice)
    assert text.isascii() and "?" not in text and "sigma 3.82" in text and "1.1x" in text


def test_swagger_ui_is_served_from_the_package():
    """/docs works offline: the page's script and style come from this server, not a CDN."""
    pytest.importorskip("swagger_ui_bundle")
    from conftest import service_settings
    from fastapi.testclient import TestClient

    from quietframe.service.main import create_app

    with TestClient(create_app(service_settings())) as client:
        page = client.get("/docs")
        assert page.status_code == 200 and "cdn" not in page.text.lower()
        script = client.get("/docs/assets/swagger-ui-bundle.js")
        assert script.status_code == 200 and len(script.content) > 100_000
        assert client.get("/docs/assets/swagger-ui.css").status_code == 200
        assert client.get("/openapi.json").status_code == 200
