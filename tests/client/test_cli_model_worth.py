"""What a user sees of where a learned tier is worth using: GET /v1/models carries each card's
`input_margin` (the model against its own noisy input on the validation zoo) with the spp from
which its worst shot is below the input, and `quietframe models` says it in the model's row."""

from __future__ import annotations

import httpx
import pytest

from quietframe.client.cli import main

LEARNED = ("nbg-2l-1g", "nbg-2l-3g", "nbg-7l-3g", "affinity-h16-k5gc")


def row_of(text: str, name: str) -> str:
    return next(line for line in text.splitlines() if line.startswith(f"{name} "))


def test_models_listing_and_table_say_from_which_spp_a_learned_tier_is_worse_than_its_input(
        live_server, capsys):
    models = {m["name"]: m for m in httpx.get(f"{live_server.url}/v1/models").json()["models"]}
    learned = [n for n in LEARNED if n in models]
    if not learned:
        pytest.skip("no learned tier installed")
    for renderer in ("cycles", "mitsuba"):  # the zoo's figure stands for every renderer's
        assert main(["models", "--server", live_server.url, "--renderer", renderer]) == 0
        text = capsys.readouterr().out
        for name in learned:
            margin = models[name]["metrics"]["by_renderer"]["cycles"]["input_margin"]
            worst = {r["spp"]: r["worst_db"] for r in margin["by_spp"]}
            # garden-blur (generator tiers, docs/zoo.md), a glossy studio (corpus tiers)
            assert worst[1] > 0 > worst[64], (name, worst)
            worse = margin["worse_than_input_from_spp"]
            assert 1 < worse < 64
            assert f"worth using below {worse:g} spp" in row_of(text, name)
        assert "worth using" not in row_of(text, "oidn-frame")  # never measured against it
