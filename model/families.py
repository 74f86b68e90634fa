"""The model families quietframe trains (NBG, affinity, oidn-temporal): each one's named variants,
how a checkpoint's saved config is recognised as its own, and how its model is built. Training
(model/train.py) and the exporter (export/cli.py) both go through here, so the rule that tells
one family's checkpoint from another's lives in one place. The compositions without a learned
stage (the accumulation, OIDN alone, the output history) have no checkpoint: the exporter
builds those from their own variant tables."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from quietframe.model import affinity, nbg, oidn_temporal


@dataclass(frozen=True)
class Family:
    name: str
    config_type: Callable[..., Any]  # the config dataclass, rebuilt from a checkpoint's dict
    model_type: Callable[[Any], nn.Module]
    variants: Mapping[str, Any]  # variant name -> its config
    # The config fields a run's flags may set on a variant; other fields' flags do not apply
    # (an affinity model has no `width`, an oidn-temporal one no firefly clamp).
    tunable: tuple[str, ...]
    owns: Callable[[Mapping[str, Any]], bool]  # whether a checkpoint's config is of this family

    def tuned(self, overrides: Mapping[str, Any]) -> dict[str, Any]:
        return {k: v for k, v in overrides.items() if k in self.tunable}

    def variant(self, name: str, **overrides: Any) -> nn.Module:
        """The untrained model of variant `name`, with the tunable ones of `overrides`."""
        return self.model_type(dataclasses.replace(self.variants[name], **self.tuned(overrides)))

    def from_saved(self, saved: Mapping[str, Any], **overrides: Any) -> nn.Module:
        """The model of a checkpoint's saved config (weights not loaded), with the tunable ones
        of `overrides` (a fine-tune may switch the firefly clamp: it has no weights)."""
        return self.model_type(self.config_type(**{**saved, **self.tuned(overrides)}))


CLAMP = ("outlier_sigmas", "outlier_floor")
# The learned tiers' settings without weights beside the clamp: the resampled history's fade
# and the albedo's prefilter (NBGConfig / AffinityConfig).
WEIGHTLESS = ("resampled_weight_per_doubling", "albedo_prefilter")

AFFINITY = Family(
    name="affinity", config_type=affinity.AffinityConfig, model_type=affinity.AffinityDenoiser,
    variants=affinity.VARIANTS,
    tunable=("kernel_size", "noise_input", *WEIGHTLESS, *CLAMP),
    owns=lambda saved: saved.get("family") == "affinity",  # AffinityConfig.family
)
OIDN_TEMPORAL = Family(
    name="oidn-temporal", config_type=oidn_temporal.OIDNTemporalConfig,
    model_type=oidn_temporal.OIDNTemporal, variants=oidn_temporal.VARIANTS,
    tunable=("width", "net_scale"),
    owns=lambda saved: "quality" in saved,  # the OIDN prepass's quality: no other family's
)
NBG = Family(
    name="nbg", config_type=nbg.NBGConfig, model_type=nbg.NBGDenoiser, variants=nbg.VARIANTS,
    tunable=("width", "passthrough", "noise_blend", *WEIGHTLESS, *CLAMP),
    owns=lambda saved: True,  # the first family: its checkpoints carry no mark of their own
)
# In the order a checkpoint is tried against them: NBG, unmarked, last.
FAMILIES = (AFFINITY, OIDN_TEMPORAL, NBG)


def family_of_checkpoint(saved: Mapping[str, Any]) -> Family:
    """The family of a checkpoint's saved config (`checkpoint["config"]`)."""
    return next(f for f in FAMILIES if f.owns(saved))


def family_of_variant(variant: str) -> Family:
    """The family a variant name belongs to (KeyError for an unknown one)."""
    for family in FAMILIES:
        if variant in family.variants:
            return family
    raise KeyError(variant)


# Settings without weights that quietframe-export may put on a trained checkpoint
# (--resampled-weight-per-doubling, --albedo-prefilter): a shipped file may differ from its
# checkpoint in these.
EXPORT_SETTINGS = WEIGHTLESS


def export_settings(architecture: Mapping[str, Any]) -> dict[str, Any]:
    """The EXPORT_SETTINGS an exported file's architecture (its card's) holds: with them,
    load_checkpoint rebuilds the model the file was exported from."""
    return {k: architecture[k] for k in EXPORT_SETTINGS if k in architecture}


def load_checkpoint(path: str | Path, **overrides: Any) -> tuple[nn.Module, dict]:
    """Rebuild any family's model from a training checkpoint: {"config", "model", "training",
    "metrics"}; returns the model and the checkpoint. `overrides`: settings without weights
    of the family's `tunable` (others are ignored)."""
    checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    family = family_of_checkpoint(checkpoint["config"])
    model = family.from_saved(checkpoint["config"], **overrides)
    model.load_state_dict(checkpoint["model"])
    return model, checkpoint
