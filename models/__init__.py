"""Shipped, trained ONNX models and their model cards (data files in this folder)."""

from pathlib import Path

MODELS_DIR = Path(__file__).resolve().parent
