"""The model families' registry (model/families.py): a checkpoint's saved config is told apart,
and a variant found, in one place for training and export."""

from __future__ import annotations

import pytest

pytest.importorskip("torch")

from quietframe.model import families  # noqa: E402
from quietframe.model.output_history import VARIANTS as HISTORY_VARIANTS  # noqa: E402


@pytest.mark.parametrize("family", families.FAMILIES, ids=lambda f: f.name)
def test_every_variant_is_recognised_as_its_own_family(family):
    for name, config in family.variants.items():
        assert families.family_of_variant(name) is family
        assert families.family_of_checkpoint(config.to_dict()) is family
        assert family.from_saved(config.to_dict()).config == config


def test_variant_names_are_unique_across_families():
    names = [name for family in families.FAMILIES for name in family.variants]
    assert len(names) == len(set(names))


def test_an_unknown_variant_is_a_key_error():
    with pytest.raises(KeyError):
        families.family_of_variant("no-such-variant")
    with pytest.raises(KeyError):  # the output history has no checkpoint: the exporter's own
        families.family_of_variant(next(iter(HISTORY_VARIANTS)))


def test_flags_reach_only_the_fields_a_family_has():
    nbg = families.NBG.variant("nbg-2l-1g", width=8, kernel_size=5, outlier_sigmas=0.0)
    assert (nbg.config.width, nbg.config.outlier_sigmas) == (8, 0.0)
    oidn = families.OIDN_TEMPORAL.variant("oidn-temporal-fast", width=4, outlier_sigmas=0.0,
                                           kernel_size=9)
    assert (oidn.config.width, oidn.config.kernel_size) == (4, 3)  # kernel_size: affinity's flag
    name = next(iter(families.AFFINITY.variants))
    affinity = families.AFFINITY.variant(name, width=99, kernel_size=5)
    assert affinity.config.kernel_size == 5

