"""Non-network baselines on synthetic frames: a smooth scene (disc in front of a plane) with
exact aux buffers and multiplicative Gamma noise of mean 1 (an unbiased, renderer-like noise)."""

import numpy as np
import pytest

from quietframe.bench import baselines as bl
from quietframe.bench.timing import time_ms
from quietframe.model.metrics import psnr

H, W = 64, 96


def scene(shift_x: float = 0.0) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Aux buffers and clean radiance; the content is translated right by `shift_x` pixels."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    x = x - shift_x
    cx, cy, rad = W * 0.5, H * 0.5, H * 0.3
    d2 = ((x - cx) ** 2 + (y - cy) ** 2) / rad**2
    disc = (d2 < 1)[..., None]
    nz = np.sqrt(np.clip(1 - d2, 0, 1))
    normal = np.where(disc, np.stack([(x - cx) / rad, (y - cy) / rad, nz], -1), [0, 0, 1])
    texture = (0.8 + 0.2 * np.sin(x / 9))[..., None]
    albedo = np.where(disc, [0.8, 0.3, 0.2], [0.4, 0.5, 0.6]) * texture
    depth = np.where(disc[..., 0], 5.0 - nz, 10.0 + 0.01 * y)[..., None]
    light = (1.0 + 0.8 * np.sin(x / 20) * np.cos(y / 15))[..., None] * np.where(disc, 1.5, 1.0)
    aux = {"albedo": albedo, "normal": normal, "depth": depth}
    return {k: v.astype(np.float32) for k, v in aux.items()}, (albedo * light).astype(np.float32)


def noisy(clean: np.ndarray, rng: np.random.Generator, shape_k: float = 2.0) -> np.ndarray:
    return (clean * rng.gamma(shape_k, 1 / shape_k, clean.shape)).astype(np.float32)


def frame(rng: np.random.Generator, shift_x: float = 0.0, motion_x: float = 0.0):
    aux, clean = scene(shift_x)
    motion = np.zeros((H, W, 2), np.float32)
    motion[..., 0] = motion_x
    return {"color": noisy(clean, rng), "motion": motion, **aux}, clean


def run_static(baseline, frames: int, seed: int = 0) -> list[tuple[float, float]]:
    """(input PSNR, output PSNR) per frame of a static noisy sequence."""
    rng = np.random.default_rng(seed)
    scores = []
    for _ in range(frames):
        buffers, clean = frame(rng)
        out = baseline(buffers)
        assert out.shape == (H, W, 3) and out.dtype == np.float32 and np.isfinite(out).all()
        scores.append((psnr(buffers["color"], clean), psnr(out, clean)))
    return scores


def oidn_or_skip():
    pyoidn = pytest.importorskip("pyoidn", reason="pyoidn is not installed")
    if not pyoidn.Device.is_cpu_available():
        pytest.skip("pyoidn cannot create a CPU device on this machine (OIDN CPU backend)")


# --- shared temporal rule ---------------------------------------------------------------------
def test_constants_match_the_nbg_temporal_stage():
    pytest.importorskip("torch", reason="the NBG model (torch) is not installed")
    from quietframe.model import nbg, temporal

    assert bl.MIN_CURRENT_WEIGHT == temporal.MIN_CURRENT_WEIGHT == 0.2  # previous frame 0.8
    assert bl.DEPTH_REL_TOLERANCE == temporal.DEPTH_REL_TOLERANCE == 0.1
    assert bl.NORMAL_MIN_DOT == temporal.NORMAL_MIN_DOT == 0.9
    assert bl.STATE_CHANNELS == temporal.STATE_CHANNELS
    assert bl.ALBEDO_EPSILON == nbg.ALBEDO_EPSILON
    assert bl.ALBEDO_DEMODULATION_FLOOR == nbg.ALBEDO_DEMODULATION_FLOOR


def test_accumulation_is_a_twin_of_the_torch_prestage():
    # same sequence through model/temporal.accumulate (on demodulated radiance) and the numpy
    # TemporalAccumulation: subpixel motion, a disocclusion and a reset included
    torch = pytest.importorskip("torch", reason="the NBG model (torch) is not installed")
    from quietframe.model.temporal import accumulate

    rng = np.random.default_rng(9)
    acc, state = bl.TemporalAccumulation(), torch.zeros(1, bl.STATE_CHANNELS, H, W)
    nchw = lambda a: torch.from_numpy(np.ascontiguousarray(np.moveaxis(a, -1, 0)))[None]  # noqa: E731
    for t in range(6):
        buffers, _ = frame(rng, shift_x=0.7 * t, motion_x=-0.7)
        buffers["motion"][..., 1] = rng.uniform(-0.3, 0.3, (H, W))
        if t == 3:
            buffers["depth"] = buffers["depth"] * np.where(np.arange(W) < W // 3, 2, 1)[:, None]
        reset = t in (0, 4)
        if reset:
            acc.reset()
        safe = bl.safe_albedo(buffers["albedo"])
        with torch.no_grad():
            radiance, state = accumulate(
                nchw(buffers["color"] / safe),
                nchw(buffers["depth"]),
                nchw(buffers["normal"]),
                nchw(buffers["motion"]),
                torch.tensor([float(reset)]),
                state,
            )
        want = np.moveaxis(radiance[0].numpy(), 0, -1) * safe
        np.testing.assert_allclose(acc(buffers), want, rtol=1e-4, atol=1e-5)


def test_warp_integer_and_subpixel_motion():
    hist = np.random.default_rng(1).random((2, H, W)).astype(np.float32)
    motion = np.zeros((H, W, 2), np.float32)
    motion[..., 0], motion[..., 1] = -3, 2  # pixel p was at p + (-3, 2)
    warped, inside = bl.nearest_warp(hist, motion)
    np.testing.assert_array_equal(warped[:, : H - 2, 3:], hist[:, 2:, : W - 3])
    assert inside[: H - 2, 3:].all() and not inside[H - 2 :].any() and not inside[:, :3].any()
    motion[..., 0], motion[..., 1] = 0.4, -0.6  # nearest: (0, -1), never a blend of pixels
    warped, inside = bl.nearest_warp(hist, motion)
    np.testing.assert_array_equal(warped[:, 1:, :], hist[:, :-1, :])
    assert not inside[0].any() and inside[1:].all()  # y - 0.6 < -0.5 on the first row
    motion[5, 7] = np.nan
    assert not bl.nearest_warp(hist, motion)[1][5, 7]  # non-finite motion: no history


def test_history_valid_thresholds():
    z = np.full((1, 5), 10.0, np.float32)
    z_prev = np.array([[10.0, 10.9, 11.1, 10.0, 10.0]], np.float32)  # rel. diff 0, .09, .11, 0, 0
    n = np.zeros((3, 1, 5), np.float32)
    n[2] = 1
    n_prev = n.copy()
    n_prev[:, 0, 3] = [0.5, 0, 0.5]  # cos 0.707
    n_prev[:, 0, 4] = [0, 0, 0.85]  # a shorter (pixel-averaged) normal, same direction: cos 1
    assert bl.history_valid(z_prev, n_prev, z, n).tolist() == [[True, True, False, False, True]]


# --- TemporalAccumulation ---------------------------------------------------------------------
def test_accumulation_converges_on_a_static_sequence():
    scores = run_static(bl.TemporalAccumulation(), 12)
    gains = [out - inp for inp, out in scores]
    assert abs(gains[0]) < 1e-3  # first frame: nothing to accumulate
    assert gains[3] > 3.0 and gains[11] > gains[3] + 1.0  # error keeps falling
    # a mean over the first 5 frames, then an exponential average with weight 0.2, which keeps
    # 0.2 / (2 - 0.2) of the variance: at most 9.5 dB
    assert gains[11] < 10.5


def test_accumulation_follows_motion_and_rejects_disocclusion():
    rng = np.random.default_rng(2)
    acc = bl.TemporalAccumulation()
    for t in range(8):  # content moves right 1 px/frame: pixel p was at p - 1
        buffers, clean = frame(rng, shift_x=t, motion_x=-1.0)
        out = acc(buffers)
    assert acc.valid_fraction > 0.95  # the left column and the disc's trailing edge are new
    assert psnr(out, clean) > psnr(buffers["color"], clean) + 5
    buffers, _ = frame(rng, shift_x=8, motion_x=-1.0)
    buffers["depth"] = buffers["depth"] * 1.5  # everything moved away: history must go
    np.testing.assert_allclose(acc(buffers), buffers["color"], rtol=1e-5, atol=1e-6)
    assert acc.valid_fraction == 0.0


def test_accumulation_reset_drops_history():
    rng = np.random.default_rng(3)
    acc = bl.TemporalAccumulation()
    for _ in range(4):
        acc(frame(rng)[0])
    acc.reset()  # camera cut
    buffers, _ = frame(rng)
    np.testing.assert_allclose(acc(buffers), buffers["color"], rtol=1e-5, atol=1e-6)


# --- SVGF -------------------------------------------------------------------------------------
def test_svgf_denoises_and_improves_over_time():
    scores = run_static(bl.SVGFStyleFilter(), 6)
    gains = [out - inp for inp, out in scores]
    assert gains[0] > 10.0  # spatial filter alone, first frame
    assert gains[5] > gains[0] + 2.0  # temporal accumulation on top


def test_svgf_reset_and_threads_are_deterministic():
    rng = np.random.default_rng(4)
    buffers = [frame(rng, shift_x=t, motion_x=-1.0)[0] for t in range(3)]
    single, threaded = bl.SVGFStyleFilter(), bl.SVGFStyleFilter(num_threads=2)
    outs = [single(b) for b in buffers]
    np.testing.assert_array_equal(outs[-1], [threaded(b) for b in buffers][-1])  # bands disjoint
    threaded.close()
    single.reset()
    np.testing.assert_array_equal(single(buffers[0]), outs[0])  # camera cut = fresh filter


def test_svgf_young_pixels_gathered_or_banded_agree(monkeypatch):
    # the spatial variance of disoccluded pixels is computed on gathered pixels when they are few
    rng = np.random.default_rng(8)
    buffers = [frame(rng, shift_x=2 * t, motion_x=-2.0)[0] for t in range(6)]
    outs = {}
    for fraction in (0.0, 1.01):  # never / always gather
        monkeypatch.setattr(bl, "_GATHER_FRACTION", fraction)
        svgf = bl.SVGFStyleFilter()
        outs[fraction] = [svgf(b) for b in buffers]
    for a, b in zip(outs[0.0], outs[1.01], strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_svgf_keeps_depth_edges():
    # two planes at different depths, lit 1 and 4: without edge-stopping the columns next to the
    # step would be pulled towards each other (a blur would put them near 2.5)
    rng = np.random.default_rng(5)
    y = np.mgrid[0:H, 0:W][0].astype(np.float32)
    right = np.arange(W) >= W // 2
    clean = np.broadcast_to(np.where(right, 2.0, 0.5)[None, :, None], (H, W, 3)).astype(np.float32)
    normal = np.broadcast_to(np.float32([0, 0, 1]), (H, W, 3))
    buffers = {
        "color": noisy(clean, rng),
        "albedo": np.full((H, W, 3), 0.5, np.float32),
        "normal": normal,
        "depth": (np.where(right, 8.0, 2.0) + 0.01 * y)[..., None].astype(np.float32),
    }
    out = bl.SVGFStyleFilter()(buffers)
    for x in (W // 2 - 1, W // 2):
        assert out[:, x].mean() == pytest.approx(clean[0, x, 0], rel=0.1)


# --- OIDN -------------------------------------------------------------------------------------
@pytest.mark.parametrize("quality", ["fast", "high"])
def test_oidn_denoises(quality):
    oidn_or_skip()
    den = bl.OIDNDenoiser(quality)
    try:
        scores = run_static(den, 2)
        assert all(out - inp > 10.0 for inp, out in scores)
    finally:
        den.close()


def test_oidn_prefiltered_aux_and_resolution_change():
    oidn_or_skip()
    rng = np.random.default_rng(6)
    den = bl.OIDNDenoiser("balanced", prefilter_aux=True)
    try:
        buffers, clean = frame(rng)
        buffers["albedo"] = noisy(buffers["albedo"], rng, 8.0)  # what prefiltering is for
        out = den(buffers)
        assert np.isfinite(out).all() and psnr(out, clean) > psnr(buffers["color"], clean) + 8
        small = {k: v[: H // 2, : W // 2] for k, v in buffers.items()}  # rebuilds the filters
        assert den(small).shape == (H // 2, W // 2, 3)
        den.reset()  # single-frame: a no-op that keeps working
        assert den(buffers).shape == (H, W, 3)
    finally:
        den.close()


def test_bad_buffers_are_rejected():
    buffers, _ = frame(np.random.default_rng(0))
    with pytest.raises(ValueError, match="missing buffer 'albedo'"):
        bl.TemporalAccumulation()({k: v for k, v in buffers.items() if k != "albedo"})
    with pytest.raises(ValueError, match="normal has shape"):
        bl.SVGFStyleFilter()({**buffers, "normal": buffers["normal"][:, :, :2]})
    with pytest.raises(ValueError, match="quality"):
        bl.OIDNDenoiser("ultra")  # type: ignore[arg-type]


def test_time_ms_counts_and_orders():
    calls = []
    t = time_ms(lambda: calls.append(1), warmup=2, repeats=5)
    assert len(calls) == 7 and len(t.samples_ms) == 5
    assert t.min_ms <= t.median_ms <= t.max_ms and t.cpu_ms >= 0
