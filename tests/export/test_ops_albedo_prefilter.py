"""ai.quietframe::AlbedoPrefilter (export/ops/albedo_prefilter.cc) against its PyTorch
reference quietframe.model.albedo_prefilter.albedo_blur, to float rounding: random albedo at
spp 1-4096, one spp or one per image, NaN or sub-1 spp (as 1), odd and 1-pixel sizes; a flat
albedo stays flat, energy is kept, high spp leave the albedo nearly as it is; the thread count
changes no bit; bad shapes and attributes are errors."""

from __future__ import annotations

import numpy as np
import pytest
from ops_support import make_session, op_model

from quietframe.runtime.ops_library import ops_library_path

torch = pytest.importorskip("torch")
prefilter = pytest.importorskip("quietframe.model.albedo_prefilter")

SIGMA = 1.0


def prefilter_model(sigma: float = SIGMA, exponent: float = prefilter.SIGMA_EXPONENT,
                    radius: int = prefilter.RADIUS) -> bytes:
    return op_model("AlbedoPrefilter", sigma_at_one_spp=sigma, exponent=exponent, radius=radius)


@pytest.fixture(scope="module")
def run():
    sessions = {}

    def run(albedo: np.ndarray, spp: np.ndarray, threads: int = 2) -> np.ndarray:
        if threads not in sessions:
            sessions[threads] = make_session(str(ops_library_path()), prefilter_model(), threads)
        return sessions[threads].run(None, {"albedo": albedo, "spp": spp})[0]

    return run


def reference(albedo: np.ndarray, spp: np.ndarray, sigma: float = SIGMA) -> np.ndarray:
    return prefilter.albedo_blur(torch.from_numpy(albedo), torch.from_numpy(spp), sigma,
                                 prefilter.SIGMA_EXPONENT, prefilter.RADIUS).numpy()


def albedo(n: int, h: int, w: int, seed: int, channels: int = 3) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0, 1, (n, channels, h, w)).astype(np.float32)


@pytest.mark.parametrize(("n", "h", "w", "seed"), [
    (1, 1, 1, 0), (1, 2, 3, 1), (2, 7, 13, 2), (1, 48, 64, 3), (3, 33, 5, 4)])
@pytest.mark.parametrize("spp", [1.0, 2.0, 4.0, 11.0, 64.0, 4096.0])
def test_matches_reference(run, n: int, h: int, w: int, seed: int, spp: float) -> None:
    a = albedo(n, h, w, seed)
    s = np.array([spp], np.float32)
    expected = reference(a, s)
    np.testing.assert_allclose(run(a, s), expected, rtol=0, atol=2e-6)
    if h * w > 100:  # it blurs, and less the higher the spp
        change = np.abs(expected - a).mean()
        if spp <= 4:
            assert change > 0.05
        if spp >= 4096:  # sigma 1/16 px: the identity
            assert change < 1e-6


def test_one_spp_per_image_nan_and_below_one(run) -> None:
    a = albedo(4, 20, 17, seed=9)
    a[0], a[1] = a[2], a[2]
    per_image = np.array([0.25, np.nan, 1.0, 64.0], np.float32)
    got = run(a, per_image)
    np.testing.assert_allclose(got, reference(a, per_image), rtol=0, atol=2e-6)
    # below 1 and NaN count as 1 spp: the widest blur, as image 2's
    np.testing.assert_allclose(got[0], got[2], rtol=0, atol=2e-6)
    np.testing.assert_allclose(got[1], got[2], rtol=0, atol=2e-6)
    assert np.isfinite(got).all()


def test_flat_stays_flat_and_energy_is_kept(run) -> None:
    flat = np.full((1, 3, 9, 11), 0.37, np.float32)
    np.testing.assert_allclose(run(flat, np.array([1.0], np.float32)), flat, rtol=0, atol=1e-7)
    a = albedo(1, 40, 40, seed=3)
    a[:, :, :4], a[:, :, -4:], a[:, :, :, :4], a[:, :, :, -4:] = 0.5, 0.5, 0.5, 0.5
    blurred = run(a, np.array([1.0], np.float32))  # edges flat: nothing lost at the border
    assert blurred.mean() == pytest.approx(a.mean(), abs=1e-5)


def test_threads_change_no_bit(run) -> None:
    a = albedo(2, 70, 37, seed=7)
    spp = np.array([2.0], np.float32)
    np.testing.assert_array_equal(run(a, spp, threads=1), run(a, spp, threads=3))


def test_bad_inputs_are_errors() -> None:
    session = make_session(str(ops_library_path()), prefilter_model(), 1)
    a = albedo(2, 4, 4, seed=1)
    with pytest.raises(Exception, match="AlbedoPrefilter: spp must hold 1 or N = 2 values"):
        session.run(None, {"albedo": a, "spp": np.ones(3, np.float32)})
    with pytest.raises(Exception, match="AlbedoPrefilter"):
        session.run(None, {"albedo": a[0], "spp": np.ones(1, np.float32)})
    for bad in ({"sigma": 0.0}, {"exponent": -1.0}, {"radius": 0}, {"radius": 17}):
        with pytest.raises(Exception,
                           match="AlbedoPrefilter: (sigma_at_one_spp|exponent|radius) must"):
            make_session(str(ops_library_path()), prefilter_model(**bad), 1).run(
                None, {"albedo": a, "spp": np.ones(1, np.float32)})
