"""Dependencies: the lifespan-held registries and settings, and the optional bearer-token check."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Request

from quietframe.service.errors import NotReady, Unauthorized
from quietframe.service.metrics import Metrics
from quietframe.service.model_registry import ModelRegistry
from quietframe.service.sessions import SessionRegistry
from quietframe.service.settings import Settings


def _settings(request: Request) -> Settings:
    return request.app.state.settings


def _metrics(request: Request) -> Metrics:
    return request.app.state.metrics


def _sessions(request: Request) -> SessionRegistry:
    registry = getattr(request.app.state, "sessions", None)
    if registry is None:
        raise NotReady("the server is still starting")
    return registry


def _models(request: Request) -> ModelRegistry:
    models = getattr(request.app.state, "models", None)
    if models is None:
        raise NotReady("the server is still starting")
    return models


SettingsDep = Annotated[Settings, Depends(_settings)]
MetricsDep = Annotated[Metrics, Depends(_metrics)]
SessionsDep = Annotated[SessionRegistry, Depends(_sessions)]
ModelsDep = Annotated[ModelRegistry, Depends(_models)]


def require_auth(request: Request, settings: SettingsDep) -> None:
    """With QUIETFRAME_AUTH_TOKEN set, /v1 needs `Authorization: Bearer <token>`."""
    if settings.auth_token is None:
        return
    scheme, _, token = request.headers.get("authorization", "").partition(" ")
    expected = settings.auth_token.get_secret_value().encode()
    if scheme.lower() != "bearer" or not hmac.compare_digest(token.strip().encode(), expected):
        raise Unauthorized(
            "missing or wrong bearer token (header 'Authorization: Bearer <token>')",
            headers={"WWW-Authenticate": 'Bearer realm="quietframe"'},
        )
