"""Extra scalar inputs of a graph (`quietframe.inputs` in its card; docs/model-interface.md):
fed from a default or a session / call option, checked here. Beside the card rather than in it
because the tiling rules (runtime/receptive.py), which the card reads, size tiles by them."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class InputSpec:
    """An extra scalar graph input (`quietframe.inputs`), fed from its default or a session /
    call option: e.g. the affinity model's `kernel_size`."""

    name: str
    dtype: str  # numpy dtype name, e.g. "int64"
    shape: tuple[int, ...]
    default: float | int
    allowed: tuple[float | int, ...] | None = None  # None: any value
    doc: str = ""
    minimum: float | None = None  # the smallest value it takes (None: no bound)

    def check(self, value: float | int) -> None:
        """ValueError for a value this input does not take."""
        if self.allowed is not None and value not in self.allowed:
            raise ValueError(f"{self.name} must be one of {list(self.allowed)}, got {value!r}")
        if not math.isfinite(float(value)):
            raise ValueError(f"{self.name} must be a finite number, got {value!r}")
        if self.minimum is not None and value < self.minimum:
            raise ValueError(f"{self.name} must be at least {self.minimum:g}, got {value!r}")
        if np.dtype(self.dtype).kind in "iu" and not float(value).is_integer():
            raise ValueError(f"{self.name} is an integer, got {value!r}")  # not truncated

    def array(self, value: float | int) -> np.ndarray:
        self.check(value)
        return np.full(self.shape, value, dtype=self.dtype)

    def describe(self) -> str:
        """E.g. 'kernel_size (one of [5, 7, 9], default 5)', for messages and listings."""
        values = f"one of {list(self.allowed)}, " if self.allowed is not None else ""
        if self.minimum is not None:
            values += f"at least {self.minimum:g}, "
        return f"{self.name} ({values}default {self.default})"

    def to_dict(self) -> dict:
        allowed = list(self.allowed) if self.allowed is not None else None
        return {"name": self.name, "dtype": self.dtype, "shape": list(self.shape),
                "default": self.default, "allowed": allowed, "doc": self.doc,
                **({} if self.minimum is None else {"minimum": self.minimum})}

    @classmethod
    def from_dict(cls, d: Mapping) -> InputSpec:
        allowed = tuple(d["allowed"]) if d.get("allowed") is not None else None
        return cls(d["name"], d["dtype"], tuple(d["shape"]), d["default"], allowed,
                   d.get("doc", ""), d.get("minimum"))
