"""model=auto decides on what a frame really carries (present but unusable buffers count as
absent), and says so in an ASCII header; the CLI's model table."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from quietframe.client import Client
from quietframe.runtime.usable_buffers import unusable_buffers

FIXTURES = Path(__file__).resolve().parent / "fixtures" / "blender"


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


def test_auto_on_a_motion_blur_frame_chooses_a_model_without_history(live_server):
    """Cycles writes an all-zero Vector with motion blur on: the frame names motion but has
    none, so auto must not choose a tier that accumulates along motion vectors."""
    with Client(live_server.url) as client:
        stateless = {m["name"] for m in client.models()["models"] if not m["state"]}
        if not stateless:
            pytest.skip("no installed model without temporal state")
        session = client.create_session(64, 36)
        try:
            data = (FIXTURES / "motion_blur.0002.exr").read_bytes()
            result = client.send_frame(session["id"], 2, data)
            choice = client.session(session["id"])["choice"]
        finally:
            client.delete_session(session["id"])
    assert choice["model"] in stateless, choice
    assert result.missing == ()  # the stateless model takes no motion: nothing reads as lost
    assert "motion" not in choice["buffers"]


def test_choice_header_is_ascii_and_spells_symbols_out():
    from quietframe.service.model_choice import Choice
    from quietframe.service.sessions import choice_header

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
