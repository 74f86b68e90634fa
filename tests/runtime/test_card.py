"""The model card (runtime/card.py): every shipped model's metadata reads into a card and back
unchanged, compositions become explicit stages, measurements are kept per renderer, and model
choice reads a renderer's table from the card."""

from __future__ import annotations

import json
from dataclasses import replace

import onnx
import pytest

from quietframe.runtime import installed_models
from quietframe.runtime.card import (
    CARD_VERSION,
    DEFAULT_RENDERER,
    PREFIX,
    GraphStage,
    Measurements,
    ModelCard,
    OIDNStage,
    SppRow,
    StateSpec,
    prepass_stage,
)
from quietframe.runtime.receptive import Tiling
from quietframe.service.model_profiles import ModelProfile


def shipped_props(path) -> dict[str, str]:
    return {p.key: p.value for p in onnx.load(str(path), load_external_data=False).metadata_props}


def parsed(value: str):
    return json.loads(value) if value[:1] in "[{" else value


@pytest.mark.parametrize("path", installed_models(), ids=lambda p: p.stem)
def test_shipped_metadata_reads_and_writes_back_unchanged(path):
    props = shipped_props(path)
    card = ModelCard.from_props(props, path.stem)
    # models exported before the card have no version key (0); later exports write the card's
    assert card.card_version == int(props.get(PREFIX + "card", 0)) and card.name == path.stem
    assert card.tiling is not None  # every shipped model has a tiling rule
    written = card.to_props()
    assert written[PREFIX + "card"] == str(CARD_VERSION)
    for key, value in props.items():
        if key == PREFIX + "state":  # `scale` is now always written (default 1)
            assert [StateSpec(**{"scale": 1, **s}) for s in json.loads(value)] == list(card.state)
            continue
        assert parsed(written[key]) == parsed(value), key
    assert replace(ModelCard.from_props(written), card_version=card.card_version) == card


def test_compositions_are_explicit_stages():
    cards = {p.stem: ModelCard.from_props(shipped_props(p), p.stem) for p in installed_models()}
    accumulation = GraphStage("accumulation.onnx", "color_from")  # sessions' stored names
    assert cards["oidn-acc"].stages == (accumulation, OIDNStage("high"), GraphStage())
    assert cards["oidn-fast-acc"].stages[1].quality == "fast"
    assert cards["oidn-frame"].stages == (OIDNStage("high"), GraphStage())
    assert cards["affinity-h16-k5gc"].stages == (GraphStage(),)
    assert cards["oidn-acc"].prepass == OIDNStage("high")
    with pytest.raises(ValueError, match="ends with this file's graph"):
        ModelCard("x", stages=(GraphStage(), OIDNStage()))
    with pytest.raises(ValueError, match="namespace"):
        GraphStage("other.onnx")


def test_measurements_are_kept_per_renderer():
    card = ModelCard.from_props(shipped_props(installed_models()[0]))
    mitsuba = card.measured(DEFAULT_RENDERER)
    assert mitsuba.complete and card.measured("arnold") == mitsuba  # no table: the default's
    cycles = Measurements(by_spp=(SppRow(1, 20.5, 1.1), SppRow(4, 22.0, 0.9)), ms_720p=99.0)
    both = card.with_measurements("cycles", cycles)
    metrics = json.loads(both.to_props()[PREFIX + "metrics"])
    assert metrics["by_spp"] == [r.to_dict() for r in mitsuba.by_spp]  # the layout as shipped
    assert metrics["by_renderer"]["cycles"]["ms_720p"] == 99.0
    again = ModelCard.from_props(both.to_props())
    assert again.measured("cycles") == cycles and again.measured("mitsuba") == mitsuba
    profile = ModelProfile.from_card(again, "cycles")
    assert profile.ms_720p == 99.0 and profile.psnr_by_spp == ((1.0, 20.5), (4.0, 22.0))
    assert ModelProfile.from_card(again, "arnold").ms_720p == mitsuba.ms_720p  # fallback


def test_a_written_tiling_wins_over_the_family_rule_and_newer_cards_are_refused():
    props = shipped_props(next(p for p in installed_models() if p.stem == "nbg-2l-3g"))
    own = Tiling(radius=7, align=2, reach={"kernel_size": {3: 1}}, bytes_per_pixel=100)
    card = ModelCard.from_props({**props, PREFIX + "tiling": json.dumps(own.to_dict())})
    assert card.tiling == own and own.radius_for({"kernel_size": 3}) == 8
    assert own.radius_for({}) == 8  # an unlisted value counts as the widest
    with pytest.raises(ValueError, match="newer"):
        ModelCard.from_props({**props, PREFIX + "card": str(CARD_VERSION + 1)})


def test_exporters_build_the_card():
    pytest.importorskip("torch")
    from quietframe.export.affinity_export import input_metadata
    from quietframe.export.onnx_export import model_card
    from quietframe.model.affinity import VARIANTS as AFFINITY
    from quietframe.model.oidn_temporal import OIDN_ONLY_VARIANTS

    config = AFFINITY["affinity-h16-k5gc"]
    card = model_card(config, "3", [{"name": "affinity", "channels": 18, "scale": 1}],
                      {"dropout": 0}, {"step": 5, "by_spp": [{"spp": 1, "psnr": 20.0}]},
                      inputs=input_metadata(5))
    assert card.tiling.reach["kernel_size"][13] == 6 * 31 and card.tiling.align == 8
    assert card.notes == {"step": 5} and card.measured().by_spp == (SppRow(1, 20.0),)
    assert ModelCard.from_props(card.to_props()) == card
    only = model_card(OIDN_ONLY_VARIANTS["oidn-acc"], "1", [], {}, {},
                      roles=(("color",), ("albedo", "normal")),
                      prepass=OIDN_ONLY_VARIANTS["oidn-acc"].prepass())
    shipped = ModelCard.from_props(shipped_props(
        next(p for p in installed_models() if p.stem == "oidn-acc")))
    assert only.stages == shipped.stages and only.tiling == shipped.tiling


def test_oidn_stage_keeps_a_separate_aux_prefilter_quality():
    stage = OIDNStage(quality="high", prefilter_aux=True, aux_quality="fast")
    spec = {"oidn": stage.oidn_dict(), "input": "oidn"}
    assert spec["oidn"]["aux_quality"] == "fast"
    assert prepass_stage(json.loads(json.dumps(spec))) == stage
    assert "aux_quality" not in OIDNStage(prefilter_aux=True).oidn_dict()  # as before
    # and through a card's stage list, which is what the runtime builds its OIDN pass from
    card = ModelCard("m", stages=(stage, GraphStage()))
    assert ModelCard.from_props(card.to_props()).prepass == stage
    with pytest.raises(ValueError, match="quality"):
        OIDNStage(prefilter_aux=True, aux_quality="best")


def test_card_metadata_is_strict_json_without_infinities():
    """A fine-tune without a validation split scores -inf; the card carries it as null, since
    readers other than Python's refuse `-Infinity`."""
    card = ModelCard(name="m", notes={"val_psnr_1spp_last_frame": float("-inf"), "step": 4},
                     training={"lr": float("nan"), "steps": 4})
    props = card.to_props()

    def strict(text: str):
        return json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in card JSON"))

    assert strict(props[PREFIX + "metrics"])["val_psnr_1spp_last_frame"] is None
    assert strict(props[PREFIX + "training"]) == {"lr": None, "steps": 4}
    assert ModelCard.from_props(props).notes["step"] == 4


@pytest.mark.parametrize("path", installed_models(), ids=lambda p: p.stem)
def test_shipped_cards_are_strict_json(path):
    def refuse(constant: str):
        pytest.fail(f"{path.name}: {constant} in its card's JSON")

    for value in shipped_props(path).values():
        if value[:1] in "[{":
            json.loads(value, parse_constant=refuse)
