"""The models shipped in the package (quietframe.models: *.onnx with their model cards)."""

from __future__ import annotations

from pathlib import Path

from quietframe.models import MODELS_DIR

# The best general-purpose model shipped: what a caller that names none gets.
DEFAULT_MODEL = "nbg-2l-3g"


def installed_models() -> list[Path]:
    return sorted(MODELS_DIR.glob("*.onnx"))


def find_model(name: str) -> Path:
    """Path of an installed model by name (file stem), or a path to an .onnx file."""
    candidate = Path(name)
    if candidate.suffix == ".onnx" and candidate.is_file():
        return candidate
    for path in installed_models():
        if path.stem == name:
            return path
    known = [p.stem for p in installed_models()]
    raise LookupError(f"unknown model {name!r}; installed: {known}")


def default_model_path() -> Path:
    models = installed_models()
    if not models:
        raise LookupError(f"no models installed in {MODELS_DIR}")
    return next((p for p in models if p.stem == DEFAULT_MODEL), models[0])
