"""The OIDN stage split in two: its aux filters alone (`prefilter`, on a frame or a crop of one)
then its colour filter on those aux (`clean_aux`) give the stage's one-call output, in either
row order (experiments/aux_history.py builds its policies on the split)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pyoidn")

from quietframe.runtime.card import OIDNStage  # noqa: E402
from quietframe.runtime.oidn_prepass import OIDNPrepass  # noqa: E402


def test_prefilter_then_colour_filter_is_the_stage():
    rng = np.random.default_rng(0)
    planes = {"color": rng.exponential(0.5, (3, 40, 56)).astype(np.float32),
              "albedo": rng.uniform(0, 1, (3, 40, 56)).astype(np.float32),
              "normal": rng.normal(size=(3, 40, 56)).astype(np.float32)}
    stage = OIDNPrepass(OIDNStage(quality="high", prefilter_aux=True, aux_quality="fast"),
                        num_threads=1)
    for renderer in (None, "cycles"):
        whole = stage(planes, renderer)
        clean = stage.prefilter({k: planes[k] for k in ("albedo", "normal")}, renderer)
        assert set(clean) == {"albedo", "normal"}
        split = stage({"color": planes["color"], **clean}, renderer, clean_aux=True)
        np.testing.assert_allclose(split, whole, rtol=0, atol=1e-6)
        assert not np.allclose(stage({"color": planes["color"], **clean}, renderer), whole,
                               atol=1e-3)  # filtered twice: the split does not prefilter again
    flipped = stage.prefilter({k: planes[k][:, ::-1] for k in ("albedo", "normal")}, None)
    np.testing.assert_array_equal(flipped["albedo"][:, ::-1], clean["albedo"])
