"""The card's `input_margin` (runtime/card.py): a model against its own noisy input on the
validation zoo, kept apart from the `zoo` rows, read back as written, and the spp from which the
worst shot is below the input."""

from __future__ import annotations

import json
import math

import pytest

from quietframe.runtime.card import (
    PREFIX,
    InputMarginRow,
    Measurements,
    ModelCard,
    SppRow,
    ZooRow,
    split_metrics,
    worse_than_input_from,
)

ROWS = (InputMarginRow(1, 5.37, 10.6, "garden-blur", 4),
        InputMarginRow(4, 0.86, 5.5, "garden-blur", 4),
        InputMarginRow(16, -5.02, 1.1, "garden-blur", 4))


def test_input_margin_round_trips_through_the_card_apart_from_the_zoo_rows():
    measured = {"commands": ["python -m quietframe.bench.zoo_eval ..."], "shots": ["a", "b"]}
    table = Measurements(by_spp=(SppRow(1, 25.0),), ms_720p=10.0,
                         zoo=(ZooRow(1, -1.0, -2.0, -0.5),), zoo_measured={"shots": ["z"]},
                         input_margin=ROWS, input_margin_measured=measured)
    card = ModelCard("m").with_measurements("cycles", table)
    metrics = json.loads(card.to_props()[PREFIX + "metrics"])
    section = metrics["by_renderer"]["cycles"]["input_margin"]
    assert section["by_spp"][2] == {"spp": 16, "worst_db": -5.02, "mean_db": 1.1,
                                    "worst_shot": "garden-blur", "shots": 4}
    assert section["measured"] == measured
    assert section["worse_than_input_from_spp"] == worse_than_input_from(ROWS)
    assert metrics["by_renderer"]["cycles"]["zoo"]["measured"] == {"shots": ["z"]}
    again = ModelCard.from_props(card.to_props()).measured("cycles")
    assert again == table
    # written again unchanged: the derived figure is recomputed, never read as a row
    assert ModelCard.from_props(card.to_props()).to_props() == card.to_props()


def test_a_table_of_only_an_input_margin_is_a_measurement_not_a_note():
    notes, tables = split_metrics({"input_margin": {"by_spp": [r.to_dict() for r in ROWS]},
                                   "val": 0.5})
    assert notes == {"val": 0.5}
    assert tables["mitsuba"].input_margin == ROWS


def test_worse_than_input_from_is_where_the_worst_shot_crosses_zero_in_log_spp():
    # 0.86 at 4 spp, -5.02 at 16: zero at log2 spp = 2 + 2 * 0.86 / 5.88
    assert worse_than_input_from(ROWS) == pytest.approx(2 ** (2 + 2 * 0.86 / 5.88), abs=0.01)
    assert worse_than_input_from(ROWS[:2]) is None  # never below
    assert worse_than_input_from(()) is None
    below_at_first = (InputMarginRow(1, -0.5, 1.0), InputMarginRow(4, 2.0, 3.0))
    assert worse_than_input_from(below_at_first) == 1.0
    exactly_zero = (InputMarginRow(1, 2.0, 2.0), InputMarginRow(4, 0.0, 1.0),
                    InputMarginRow(16, -1.0, 0.0))
    assert worse_than_input_from(exactly_zero) == pytest.approx(4.0)
    assert not math.isnan(worse_than_input_from(exactly_zero))
