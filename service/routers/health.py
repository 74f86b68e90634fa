"""Liveness, readiness and Prometheus metrics (not behind the bearer token: probes and scrapers)."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from quietframe.service.deps import MetricsDep
from quietframe.service.errors import NotReady
from quietframe.service.metrics import CONTENT_TYPE
from quietframe.service.schemas import Health

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
async def metrics(metrics: MetricsDep) -> Response:
    return Response(metrics.render(), media_type=CONTENT_TYPE)
