"""Liveness, readiness and Prometheus metrics (not behind the bearer token: probes and scrapers)."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from quietframe.service.deps import MetricsDep
from quietframe.service.errors import NotReady
from quietframe.service.metrics import CONTENT_TYPE, Metrics
from quietframe.service.schemas import Health
from quietframe.service.sessions import SessionRegistry

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health, summary="Liveness")
async def healthz() -> Health:
    return Health(status="ok")


@router.get(
    "/readyz",
    response_model=Health,
    summary="Readiness",
    responses={503: {"description": "models not loaded or warm-up failed"}},
)
async def readyz(request: Request) -> Health:
    """Ready once every model is loaded and has denoised a warm-up frame."""
    models = getattr(request.app.state, "models", None)
    sessions = getattr(request.app.state, "sessions", None)
    if models is None or sessions is None or not models.ready:
        raise NotReady("models are loading")
    return Health(
        status="ready",
        detail={
            "models": models.names,
            "default_model": models.default,
            "sessions": len(sessions.sessions),
        },
    )


@router.get("/metrics", summary="Prometheus metrics", response_class=Response)
async def metrics(request: Request, metrics: MetricsDep) -> Response:
    sessions = getattr(request.app.state, "sessions", None)
    if sessions is not None:
        observe_load(metrics, sessions)
    return Response(metrics.render(), media_type=CONTENT_TYPE)


def observe_load(metrics: Metrics, sessions: SessionRegistry) -> None:
    """The load gauges as of this scrape. A frame is in flight while its body is received (an
    upload slot) and then while it holds its session's lock (waiting for a worker, denoising,
    storing): the two never overlap."""
    denoising = sum(session.lock.locked() for session in sessions.sessions.values())
    metrics.observe_load(
        frames_in_flight=sessions.upload_slots.count + denoising,
        frame_slots=sessions.settings.worker_count,
        reserved_bytes=sessions.admission.used_bytes,
    )
