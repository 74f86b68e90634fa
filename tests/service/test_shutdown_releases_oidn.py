"""A server that stops releases the OIDN devices its models and its sessions' streams made: each
live device holds one of the process's ~1000 pthread keys (pyoidn fails `pthread_key_create`
past that), so a process that starts many servers (a test run, a supervisor) ran out before."""

from __future__ import annotations

import pytest
from conftest import LAYOUTS, make_buffers, service_settings, write_exr
from fastapi.testclient import TestClient

from quietframe.service.main import create_app


def live_devices(app) -> int:
    models = app.state.models
    return sum(len(models.denoiser(n).prepass._all) for n in models.names
               if models.denoiser(n).prepass is not None)


def test_stopping_releases_the_models_and_the_streams_devices():
    app = create_app(service_settings())
    with TestClient(app) as client:
        if not any(app.state.models.denoiser(n).prepass for n in app.state.models.names):
            pytest.skip("needs an OIDN tier installed (pyoidn)")
        assert live_devices(app) > 0  # the warm-up made some
        sid = client.post("/v1/sessions", json={"width": 64, "height": 48,
                                                 "model": "oidn-history"}).json()["id"]
        reply = client.post(f"/v1/sessions/{sid}/frames/0",
                            content=write_exr(LAYOUTS["plain-normal"](make_buffers())),
                            headers={"content-type": "image/x-exr"})
        assert reply.status_code == 200, reply.text
        stream = app.state.sessions.table.sessions[sid].stream
        assert stream is not None and stream.oidn is not None and stream.oidn._device
    assert live_devices(app) == 0
    assert stream.oidn._device is None
