"""The served models: what the runtime loaded (runtime/loaded_models.py), by the names a session
asks for, with the service's refusals, `auto`'s profiles and the /v1/models listing."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from quietframe.client.session_fields import AUTO
from quietframe.runtime import BUFFER_CHANNELS, Denoiser
from quietframe.runtime.denoiser import check_options
from quietframe.runtime.loaded_models import LoadedModels
from quietframe.runtime.stream import options_for
from quietframe.service.errors import InvalidModelOptions, ModelUnavailable, UnknownModel
from quietframe.service.model_profiles import ModelProfile, profile_of
from quietframe.service.noise_estimate import load_calibration
from quietframe.service.schemas import ModelPublic
from quietframe.service.settings import Settings


class ModelRegistry:
    def __init__(self, settings: Settings) -> None:
        self.loaded = LoadedModels.load(settings.models_dir, settings.model_threads,
                                        settings.oidn_memory_mb)
        self._denoisers = self.loaded.denoisers
        wanted = settings.default_model
        self.default = self.resolve(wanted) if wanted else self.loaded.runtime_default
        self.profiles = self.profiles_for(None)
        self.calibration = load_calibration()  # spp from a frame's noise (noise_estimate.py)
        self.ready = False

    def profiles_for(self, renderer: str | None) -> list[ModelProfile]:
        """What `auto` knows of each model for frames of `renderer` (None: the default
        renderer's tables); a composition is chosen on its own card's table."""
        return [profile_of(name, self._denoisers[name], renderer) for name in self.loaded.offered]

    @property
    def names(self) -> list[str]:
        """The models offered (listed, and `auto`'s candidates): not the internal stages, which
        a session gets only where it names one."""
        return sorted(self.loaded.offered)

    def requested(self, name: str) -> str:
        """A session's model as created: 'auto' (chosen per shot) or an installed name."""
        return AUTO if name == AUTO else self.resolve(name)

    def resolve(self, name: str) -> str:
        """Model name for a request's `model` ('auto' = the default, a name or a file stem)."""
        if name == AUTO:
            return self.default
        found = self.loaded.find(name)
        if found is not None:
            return found
        if name in self.loaded.unavailable:
            raise ModelUnavailable(f"model {name!r} is installed but not offered by this server: "
                                   f"{self.loaded.unavailable[name]}")
        raise UnknownModel(f"unknown model {name!r}; installed: {self.names} or 'auto'")

    def shot_model(self, name: str) -> str:
        """A frame's `shot_model` (the model another chunk's auto chose for the shot): one of
        the models auto chooses from, never 'auto' itself nor an internal stage (UnknownModel:
        a record that names one was not written by auto)."""
        found = None if name == AUTO else self.loaded.find(name)
        if found is None or found not in self.loaded.offered:
            raise UnknownModel(f"shot_model {name!r} is not a model auto chooses from; those "
                               f"are {self.names}")
        return found

    def check_options(self, model: str, options: Mapping[str, float | int]) -> None:
        """InvalidModelOptions unless the session's model (a name `requested` returned) takes
        every option. For 'auto' each option must be declared by some installed model, with a
        value that every model declaring it takes (any of them may be chosen for a shot)."""
        if not options:
            return
        infos = [self._denoisers[name].info for name in self.loaded.offered]  # auto's choices
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
        infos = {name: self._denoisers[name].info for name in self.loaded.offered}
        return {name: (tuple(i.required_buffers), tuple(i.optional_buffers))
                for name, i in infos.items()}

    def close(self) -> None:
        """Release every model's OIDN devices (one a worker thread each; each holds one of the
        process's ~1000 pthread keys, so a process that starts many servers runs out without
        this). No frame may be running."""
        for denoiser in self._denoisers.values():
            if denoiser.prepass is not None:
                denoiser.prepass.close()

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
        listing = self.loaded.listing(self.default)
        return [ModelPublic(**entry) for entry in listing["models"]]
