"""The loaded models: one shared onnxruntime session (Denoiser) per installed model."""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from quietframe.runtime import (
    BUFFER_CHANNELS,
    Denoiser,
    ModelInfo,
    default_model_path,
    installed_models,
)
from quietframe.runtime.card import SAMPLES_INPUT
from quietframe.runtime.denoiser import check_options
from quietframe.runtime.oidn_prepass import PrepassUnavailable
from quietframe.service.errors import InvalidModelOptions, ModelUnavailable, UnknownModel
from quietframe.service.model_choice import ModelProfile, load_calibration, profile_of
from quietframe.service.schemas import BufferSpec, ModelOption, ModelPublic
from quietframe.service.settings import Settings

log = logging.getLogger("quietframe.service")

AUTO = "auto"


def options_for(info: ModelInfo, options: Mapping[str, float | int],
                samples: float | None = None) -> dict[str, float | int]:
    """The session options a model takes: those it declares (model=auto switches between
    models, and one without an option ignores it). A model that takes the frame's spp
    (SAMPLES_INPUT) gets `samples` (the header's count or auto's estimate, at least 1) unless
    the session set it."""
    names = {spec.name for spec in info.inputs}
    chosen = {name: value for name, value in options.items() if name in names}
    if SAMPLES_INPUT in names and SAMPLES_INPUT not in chosen and samples is not None \
            and math.isfinite(samples):
        chosen[SAMPLES_INPUT] = max(1.0, float(samples))
    return chosen


class ModelRegistry:
    def __init__(self, settings: Settings) -> None:
        paths = list(installed_models())
        if settings.models_dir is not None:
            paths += sorted(Path(settings.models_dir).glob("*.onnx"))
        if not paths:
            raise LookupError("no models installed (quietframe.models) and none in models_dir")
        self._denoisers: dict[str, Denoiser] = {}
        self._aliases: dict[str, str] = {}  # file stem -> model name
        # Installed models this server cannot run (a prepass without its package): name and
        # file stem -> why, so that asking for one says what to install.
        self._unavailable: dict[str, str] = {}
        for path in paths:
            try:
                denoiser = Denoiser(path, threads=settings.model_threads)
            except PrepassUnavailable as exc:
                log.warning("model %s at %s not offered: %s", exc.model or path.stem, path, exc)
                self._unavailable.update({path.stem: str(exc), (exc.model or path.stem): str(exc)})
                continue
            name = denoiser.info.name
            if name in self._denoisers:
                log.warning("model %s at %s shadows an earlier one with that name", name, path)
            self._denoisers[name] = denoiser
            self._aliases[path.stem] = name
        wanted = settings.default_model
        self.default = self.resolve(wanted) if wanted else self._runtime_default(paths)
        self.profiles = self.profiles_for(None)
        self.calibration = load_calibration()  # spp from a frame's noise (model_choice.py)
        self.ready = False

    def profiles_for(self, renderer: str | None) -> list[ModelProfile]:
        """What `auto` knows of each model for frames of `renderer` (None: the default
        renderer's tables); a composition is chosen on its own card's table."""
        return [profile_of(name, d, renderer) for name, d in self._denoisers.items()]

    def _runtime_default(self, paths: list[Path]) -> str:
        try:
            default = default_model_path()
        except LookupError:
            default = paths[0]
        return self._aliases.get(default.stem, next(iter(self._denoisers)))

    @property
    def names(self) -> list[str]:
        return sorted(self._denoisers)

    def requested(self, name: str) -> str:
        """A session's model as created: 'auto' (chosen per shot) or an installed name."""
        return AUTO if name == AUTO else self.resolve(name)

    def resolve(self, name: str) -> str:
        """Model name for a request's `model` ('auto' = the default, a name or a file stem)."""
        if name == AUTO:
            return self.default
        if name in self._denoisers:
            return name
        if name in self._aliases:
            return self._aliases[name]
        if name in self._unavailable:
            raise ModelUnavailable(f"model {name!r} is installed but not offered by this server: "
                                   f"{self._unavailable[name]}")
        raise UnknownModel(f"unknown model {name!r}; installed: {self.names} or 'auto'")

    def check_options(self, model: str, options: Mapping[str, float | int]) -> None:
        """InvalidModelOptions unless the session's model (a name `requested` returned) takes
        every option. For 'auto' each option must be declared by some installed model, with a
        value that every model declaring it takes (any of them may be chosen for a shot)."""
        if not options:
            return
        infos = [d.info for d in self._denoisers.values()]
        declared: dict[str, list[str]] = {}  # option -> the models that have it
        for info in infos:
            for spec in info.inputs:
                declared.setdefault(spec.name, []).append(info.name)
        try:
            if model != AUTO:
                check_options(self.denoiser(model).info, options)
                return
            unknown = sorted(set(options) - set(declared))
            if unknown:
                raise ValueError(f"no installed model has option {', '.join(unknown)} (model "
                                 "'auto' gives an option to the models that have it)")
            for info in infos:
                check_options(info, options_for(info, options))
        except ValueError as exc:
            hint = self._options_hint(model, options, declared)
            raise InvalidModelOptions(f"model_options: {exc}; {hint}") from None

    def _options_hint(
        self, model: str, options: Mapping[str, float | int], declared: dict[str, list[str]]
    ) -> str:
        """How to fix refused options: which models have them, or that none has any."""
        if not declared:
            return "no installed model takes run-time options: leave model_options out"
        own = set(declared) if model == AUTO else {
            spec.name for spec in self.denoiser(model).info.inputs}
        hints = [f"models with {name}: {', '.join(declared[name])}"
                 for name in sorted(options) if name in declared and name not in own]
        if model == AUTO and set(options) - set(declared):
            hints.append(f"options of the installed models: {', '.join(sorted(declared))}")
        return "; ".join([*hints, "GET /v1/models lists each model's options and allowed values"])

    def denoiser(self, name: str) -> Denoiser:
        """The loaded model of a name that `resolve` returned."""
        return self._denoisers[name]

    def buffers(self) -> dict[str, tuple[tuple[str, ...], tuple[str, ...]]]:
        """Model name -> (required, optional) buffers, for errors that name a model to use."""
        return {
            name: (tuple(d.info.required_buffers), tuple(d.info.optional_buffers))
            for name, d in self._denoisers.items()
        }

    def warm_up(self) -> None:
        """Run one tiny frame through every model: loads the custom ops, allocates kernels."""
        for denoiser in self._denoisers.values():
            info = denoiser.info
            planes = {
                b: np.zeros((BUFFER_CHANNELS[b], 16, 16), np.float32)
                for b in (*info.required_buffers, *info.optional_buffers)
            }
            denoiser.denoise(planes, None)
        self.ready = True

    def public(self) -> list[ModelPublic]:
        return [
            ModelPublic(
                name=name,
                version=d.info.version,
                file=d.info.path.name,
                default=name == self.default,
                architecture=dict(d.card.architecture) or None,
                required_buffers=list(d.info.required_buffers),
                optional_buffers=list(d.info.optional_buffers),
                state=[BufferSpec(name=s.name, channels=s.channels) for s in d.info.state_specs],
                options=[
                    ModelOption(name=i.name, default=i.default, doc=i.doc, minimum=i.minimum,
                                allowed=list(i.allowed) if i.allowed is not None else None)
                    for i in d.info.inputs
                ],
                metrics=d.info.metrics,
                training=d.info.training,
            )
            for name, d in self._denoisers.items()
        ]
