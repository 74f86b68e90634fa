"""/v1/models: what is installed, the buffers each model needs, its speed and error figures."""

from __future__ import annotations

from fastapi import APIRouter

from quietframe.service.deps import ModelsDep
from quietframe.service.routers.sessions import errors
from quietframe.service.schemas import ModelList

router = APIRouter(prefix="/models", tags=["models"])


@router.get("", response_model=ModelList, responses=errors(401), summary="Installed models")
async def list_models(models: ModelsDep) -> ModelList:
    """`metrics` and `training` come from each model's card (ONNX metadata); an untrained export
    has empty metrics."""
    return ModelList(models=models.public(), default=models.default)
