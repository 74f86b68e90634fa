"""The models one process loads, by name: the installed ones (quietframe.models) and any *.onnx
of an extra folder. The server serves them (service/model_registry.py) and `quietframe models`
lists them without a server, both from here.

A model file that another loaded model composes as a graph stage (a prepass's `color_from`: the
accumulation under the OIDN tiers) is an internal stage, not a model of its own: it is loaded
(a session that names it still gets it), but not offered: not listed, never chosen by `auto`.
Where nothing that composes it loaded (a prepass without its package), it is offered again.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from quietframe.runtime.card import GraphStage
from quietframe.runtime.denoiser import Denoiser
from quietframe.runtime.oidn_prepass import PrepassUnavailable
from quietframe.runtime.registry import default_model_path, installed_models

log = logging.getLogger("quietframe.runtime")


@dataclass
class LoadedModels:
    denoisers: dict[str, Denoiser]  # by model name, internal stages too
    aliases: dict[str, str]  # file stem -> model name
    # Installed models this process cannot run (a prepass without its package): name and file
    # stem -> why, so that asking for one says what to install.
    unavailable: dict[str, str]
    stages: frozenset[str]  # names of the internal stages (module docstring)
    runtime_default: str  # the default model where no setting names one

    @classmethod
    def load(cls, folder: Path | None = None, threads: int = 1,
             oidn_memory_mb: float | None = None) -> LoadedModels:
        """Every installed model and those in `folder`; LookupError where there are none.
        `oidn_memory_mb`: OIDN stages' scratch cap (Denoiser)."""
        paths = list(installed_models())
        if folder is not None:
            paths += sorted(Path(folder).glob("*.onnx"))
        if not paths:
            raise LookupError("no models installed (quietframe.models) and none in models_dir")
        denoisers: dict[str, Denoiser] = {}
        aliases: dict[str, str] = {}
        unavailable: dict[str, str] = {}
        for path in paths:
            try:
                denoiser = Denoiser(path, threads=threads, oidn_memory_mb=oidn_memory_mb)
            except PrepassUnavailable as exc:
                log.warning("model %s at %s not offered: %s", exc.model or path.stem, path, exc)
                unavailable.update({path.stem: str(exc), (exc.model or path.stem): str(exc)})
                continue
            name = denoiser.info.name
            if name in denoisers:
                log.warning("model %s at %s shadows an earlier one with that name", name, path)
            denoisers[name] = denoiser
            aliases[path.stem] = name
        try:
            default = aliases.get(default_model_path().stem)
        except LookupError:
            default = aliases.get(paths[0].stem)
        return cls(denoisers, aliases, unavailable, composed_stages(denoisers),
                   default or next(iter(denoisers)))

    @property
    def offered(self) -> list[str]:
        """The models offered, in load order: every loaded one but the internal stages."""
        return [name for name in self.denoisers if name not in self.stages]

    def find(self, name: str) -> str | None:
        """The model name of a name or a file stem; None for neither."""
        return name if name in self.denoisers else self.aliases.get(name)

    def listing(self, default: str | None = None) -> dict:
        """What GET /v1/models answers (service/schemas.py ModelList): the offered models in
        load order, and the default (`default`, else the runtime's)."""
        default = default or self.runtime_default
        return {"models": [model_entry(name, self.denoisers[name], name == default)
                           for name in self.offered],
                "default": default}


def composed_stages(denoisers: dict[str, Denoiser]) -> frozenset[str]:
    """The names of loaded models whose file another loaded model composes as a graph stage."""
    composed = {(d.info.path.parent / stage.file).resolve() for d in denoisers.values()
                for stage in d.card.stages if isinstance(stage, GraphStage) and stage.file}
    return frozenset(name for name, d in denoisers.items() if d.info.path.resolve() in composed)


def model_entry(name: str, denoiser: Denoiser, default: bool) -> dict:
    """One model as the listing shows it (service/schemas.py ModelPublic), from its card."""
    info = denoiser.info
    return {
        "name": name,
        "version": info.version,
        "file": info.path.name,
        "default": default,
        "architecture": dict(denoiser.card.architecture) or None,
        "required_buffers": list(info.required_buffers),
        "optional_buffers": list(info.optional_buffers),
        "state": [{"name": s.name, "channels": s.channels} for s in info.state_specs],
        "options": [{"name": i.name, "default": i.default,
                     "allowed": list(i.allowed) if i.allowed is not None else None,
                     "minimum": i.minimum, "doc": i.doc} for i in info.inputs],
        "metrics": info.metrics,
        "training": info.training,
    }
