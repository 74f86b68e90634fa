"""The Cycles training corpus's shot list (scenes/corpus_shots.py, no bpy): its size and format,
the share of each kind of camera work and content, reproducibility, and what it holds out (the
zoo's shots and sets, the g2 and zoo seeds, the scenes kept for evaluation)."""

from __future__ import annotations

import json
from collections import Counter

import pytest

from quietframe.scenes import corpus_shots as corpus
from quietframe.scenes.corpus_shots import corpus_shots, describe, draw_shot
from quietframe.scenes.layout import CYCLES_SPLIT_BASE, SPLIT_BASE
from quietframe.scenes.zoo_shots import SHOTS as ZOO_SHOTS

SHOTS = corpus_shots()
TRAIN = corpus_shots("train")
DESCRIPTIONS = {s.name: describe(s) for s in SHOTS}


def test_corpus_is_at_least_120_sequences_of_8_square_frames_at_the_farm_levels():
    assert len(SHOTS) >= 120 and len({s.name for s in SHOTS}) == len(SHOTS)
    for s in SHOTS:
        w, h = s.size
        assert s.frames == 8 and w == h and 128 <= w <= 192, s.name
        assert s.spp_levels == (1, 4, 16, 64), s.name
        assert s.reference_spp >= max(s.spp_levels), s.name


def test_splits_are_disjoint_by_sequence_and_validation_is_small():
    train, validation = corpus_shots("train"), corpus_shots("validation")
    assert {s.seed for s in train}.isdisjoint(s.seed for s in validation)
    assert 8 <= len(validation) <= 0.15 * len(SHOTS)
    assert all(s.split == "train" for s in train) and all(s.split == "validation"
                                                           for s in validation)
    with pytest.raises(ValueError, match="corpus split 'test'"):
        draw_shot("test", 0)


def test_a_seed_draws_the_same_scene_and_another_attempt_redraws_it():
    s = SHOTS[5]
    assert draw_shot(s.split, s.seed - corpus.SPLIT_BASE[s.split]) == s
    assert describe(s) == describe(s)
    assert json.loads(json.dumps(DESCRIPTIONS[s.name])) == DESCRIPTIONS[s.name]
    again = describe(s, attempt=1)
    assert again["attempt"] == 1 and again["props"] != DESCRIPTIONS[s.name]["props"]
    assert again["stage"] == s.stage  # the stage and camera work keep the folder's name


def test_camera_work_and_effects_are_spread_as_planned():
    share = {k: sum(getattr(s, k) for s in SHOTS) / len(SHOTS)
             for k in ("motion_blur", "dof", "zero_first_motion")}
    assert 0.18 <= share["motion_blur"] <= 0.32, share
    assert 0.14 <= share["dof"] <= 0.28, share
    assert set(corpus.CAMERAS) <= {s.camera for s in TRAIN}
    assert set(corpus.STAGES) <= {s.stage for s in TRAIN}
    assert any(s.cut_at is not None for s in TRAIN)
    for s in SHOTS:
        if s.camera == "pan":
            assert 1 <= abs(s.speed) <= 14, s.name
        if s.camera == "shake":
            assert 0 < s.speed < 1.5, s.name
        if s.dof:
            assert 1.4 <= s.fstop <= 4, s.name


def test_content_covers_the_zoo_kinds_of_parts():
    counts = Counter(t for s in TRAIN for t in DESCRIPTIONS[s.name]["tags"])
    for tag in ("foliage", "thin geometry", "distant background", "fine texture", "glossy",
                "caustics", "text", "object motion", "hdri", "sky", "LEDs"):
        assert counts[tag] >= 0.1 * len(TRAIN), (tag, counts[tag])
    kinds = Counter(p["kind"] for s in TRAIN for p in DESCRIPTIONS[s.name]["props"])
    for kind in ("fence", "railing", "bars", "cables", "trees", "wire", "comb", "shelf",
                 "roller", "poster", "sign", "page"):
        assert kinds[kind] > 0, kind


def test_a_locked_off_shot_has_nothing_that_moves():
    """Its frames share one reference, so its true image must be constant."""
    locked = [s for s in SHOTS if s.locked_off]
    assert locked
    for s in locked:
        d = DESCRIPTIONS[s.name]
        assert not s.motion_blur and s.cut_at is None and not s.zero_first_motion, s.name
        assert not any(p["kind"] == "roller" or p.get("spin") for p in d["props"]), s.name
        assert "object motion" not in d["tags"], s.name


def test_nothing_held_out_is_in_the_corpus():
    zoo = {(z.set, z.camera, z.seed) for z in ZOO_SHOTS}
    assert not zoo & {(s.camera_shot().set, s.camera, s.seed) for s in SHOTS}
    assert not {z.set for z in ZOO_SHOTS} & {s.camera_shot().set for s in SHOTS}
    seeds = {s.seed for s in SHOTS}
    assert not seeds & {z.seed for z in ZOO_SHOTS}
    for base in (*SPLIT_BASE.values(), *CYCLES_SPLIT_BASE.values()):  # g2's ranges
        assert not any(base <= seed < base + 500_000 for seed in seeds), base
    text = json.dumps([[s.record() for s in SHOTS], DESCRIPTIONS]).lower()
    for name in corpus.HELD_OUT_NAMES:
        assert name not in text, name
