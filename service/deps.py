"""Dependencies: the lifespan-held registries and settings, and the optional bearer-token check."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from quietframe.service.errors import NotReady, Unauthorized
from quietframe.service.guard import token_matches
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


_bearer = HTTPBearer(
    auto_error=False, description="QUIETFRAME_AUTH_TOKEN, when the server sets one"
)


def require_auth(
    request: Request,
    settings: SettingsDep,
    _: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    """With QUIETFRAME_AUTH_TOKEN set, /v1 needs `Authorization: Bearer <token>`. The request
    guard (guard.py) checks it before any body is read; this dependency documents the scheme
    in the OpenAPI and checks again for an app mounted without the guard."""
    if settings.auth_token is None:
        return
    authorization = request.headers.get("authorization", "")
    if not token_matches(authorization, settings.auth_token.get_secret_value()):
        raise Unauthorized(
            "missing or wrong bearer token (header 'Authorization: Bearer <token>')",
            headers={"WWW-Authenticate": 'Bearer realm="quietframe"'},
        )
