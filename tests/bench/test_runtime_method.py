"""bench/harness.RuntimeMethod runs a model as a session naming it does: on frames whose header
states no spp, a model reading the spp gets the shot's estimate, made at the shot's first frame
and kept until the next reset (service/shot_choice.estimate_for_shot); a stated spp or a
session option leaves it unestimated."""

from __future__ import annotations

import numpy as np

from quietframe.bench.harness import RuntimeMethod
from quietframe.runtime import find_model
from quietframe.service.noise_estimate import load_calibration, shot_samples

H, W = 48, 64


def planes(amplitude: float, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:H, 0:W]
    smooth = np.stack([0.5 + 0.3 * x / W, 0.4 + 0.2 * y / H, 0.3 + 0 * x])
    color = np.maximum(smooth * (1 + amplitude * rng.standard_normal((1, H, W))), 0)
    normal = np.zeros((3, H, W))
    normal[2] = 1.0
    return {"color": color.astype(np.float32), "albedo": np.full((3, H, W), 0.5, np.float32),
            "normal": normal.astype(np.float32), "depth": np.full((1, H, W), 5.0, np.float32),
            "motion": np.zeros((2, H, W), np.float32)}


def estimate(p: dict[str, np.ndarray]) -> float:
    spp = shot_samples(p["color"], p["albedo"], load_calibration())
    assert spp is not None
    return spp


def test_a_model_reading_the_spp_gets_the_shots_estimate_until_a_reset():
    clean, grainy = planes(0.01, 1), planes(1.0, 2)
    assert estimate(clean) != estimate(grainy)
    method = RuntimeMethod(find_model("nbg-2l-3g"), threads=1)
    method(clean)
    assert method.shot_spp == estimate(clean)
    method(grainy)  # the shot's estimate stays
    assert method.shot_spp == estimate(clean)
    method.reset()
    out = method(grainy)
    assert method.shot_spp == estimate(grainy)
    told = RuntimeMethod(find_model("nbg-2l-3g"), threads=1, options={"spp": estimate(grainy)})
    np.testing.assert_allclose(out, told(grainy), rtol=1e-5, atol=1e-6)
    assert told.shot_spp is None  # the option states it


def test_a_stated_spp_or_a_model_without_one_is_not_estimated():
    stated = RuntimeMethod(find_model("nbg-2l-3g"), threads=1)
    stated.header_spp = 64
    stated(planes(1.0, 2))
    plain = RuntimeMethod(find_model("nbg-2l-1g"), threads=1)
    plain(planes(1.0, 2))
    assert stated.shot_spp is None and plain.shot_spp is None
