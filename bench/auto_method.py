"""`model=auto` as a method of quietframe-eval: the service's choice, made the service's way.

At a sequence's first frame and at every cut (the harness resets the method there), the choice
(service/choice_policy.choose) is made from that frame among the installed models the service
offers (not the internal stages other models compose: runtime/loaded_models.py), with their
tables for the evaluated renderer and the default quality; the chosen model then denoises the
shot through the runtime. The frame's spp is what its header would state where the renderer
writes one (Cycles: `header_spp`, set by the evaluation loop), else the reference-free
estimate, as in service/sessions.py. Its time is that of the models it picks, so it is not
timed at 720p on its own.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from quietframe.bench.harness import Planes, RuntimeMethod
from quietframe.runtime import Denoiser, default_model_path
from quietframe.runtime.loaded_models import composed_stages
from quietframe.service.choice_policy import choose
from quietframe.service.model_profiles import profile_of
from quietframe.service.noise_estimate import NoiseLevel, estimate_spp, load_calibration


class AutoMethod:
    chooses = True  # bench/evaluate.py: no 720p time of its own

    def __init__(self, models: Mapping[str, Path], threads: int, renderer: str | None,
                 quality: str | None = None) -> None:
        self.denoisers = {name: Denoiser(path, threads=threads) for name, path in models.items()}
        for stage in composed_stages(self.denoisers):  # never chosen by the service either
            del self.denoisers[stage]
        self.profiles = [profile_of(name, d, renderer) for name, d in self.denoisers.items()]
        self.default = default_model_path().stem
        self.calibration = load_calibration()
        self.quality = quality
        self.renderer = renderer  # the row order an OIDN stage sees follows it
        self.header_spp: float | None = None  # what the frame header states, where it does
        self.choices: Counter[str] = Counter()  # model -> shots it was chosen for
        self.current: RuntimeMethod | None = None

    def reset(self) -> None:
        self.current = None

    def __call__(self, planes: Planes) -> np.ndarray:
        if self.current is None:
            stated = None if self.header_spp is None else NoiseLevel(self.header_spp, "header")
            noise = estimate_spp(planes["color"], planes.get("albedo"), self.calibration,
                                 header=stated)
            _, h, w = planes["color"].shape
            pick = choose(tuple(planes), noise, self.profiles, self.default,
                          quality=self.quality, pixels=h * w)
            self.choices[pick.model] += 1
            self.current = RuntimeMethod(self.denoisers[pick.model], renderer=self.renderer)
            self.current.header_spp = pick.spp  # what the service gives a model that takes it
        return self.current(planes)
