"""experiments/output_history.OutputHistory: history in output space over a per-frame method."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")
from quietframe.experiments.output_history import OutputHistory  # noqa: E402
from quietframe.model import metrics  # noqa: E402


class Passthrough:
    """A 'denoiser' that returns its input, so the history's effect is all there is."""

    def reset(self) -> None:
        pass

    def __call__(self, planes):
        return planes["color"]


def frames(n: int, motion: float = 0.0, seed: int = 0) -> list[dict[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    h = w = 12
    normal = np.zeros((3, h, w), np.float32)
    normal[2] = 1
    return [{"color": rng.gamma(2.0, 0.25, (3, h, w)).astype(np.float32),
             "depth": np.full((1, h, w), 2.0, np.float32), "normal": normal,
             "motion": np.full((2, h, w), motion, np.float32)} for _ in range(n)]


def run(method, sequence) -> np.ndarray:
    method.reset()
    return np.stack([method(p) for p in sequence])


def test_static_history_lowers_flicker_and_starts_from_the_frame():
    seq = frames(8)
    out = run(OutputHistory(Passthrough()), seq)
    np.testing.assert_array_equal(out[0], seq[0]["color"])  # no history yet
    np.testing.assert_allclose(out[1], (seq[0]["color"] + seq[1]["color"]) / 2, rtol=1e-6)
    inputs = np.stack([p["color"] for p in seq])
    hwc = lambda x: x.transpose(0, 2, 3, 1)  # noqa: E731
    assert metrics.flicker(hwc(out[2:])) < 0.6 * metrics.flicker(hwc(inputs[2:]))


def test_sharp_only_uses_no_history_under_sub_pixel_motion():
    seq = frames(4, motion=0.5)
    out = run(OutputHistory(Passthrough(), sharp_only=True), seq)
    np.testing.assert_array_equal(out, np.stack([p["color"] for p in seq]))
    blended = run(OutputHistory(Passthrough()), seq)  # nearest reprojection reuses it
    assert not np.allclose(blended[1:], out[1:])


def test_clamp_keeps_the_output_within_the_frame_neighbourhood():
    seq = frames(5)
    seq[0]["color"][:] = 100.0  # a bright history the current frames do not support
    out = run(OutputHistory(Passthrough(), clamp=True), seq)
    for t in range(1, 5):
        assert out[t].max() <= seq[t]["color"].max() + 1e-5
    assert run(OutputHistory(Passthrough()), seq)[1].max() > 40


def test_accumulated_oidn_is_the_shipped_oidn_acc_and_aligned_drops_sub_pixel_history():
    pytest.importorskip("pyoidn")
    from quietframe.bench.harness import RuntimeMethod
    from quietframe.experiments.output_history import accumulated_oidn
    from quietframe.runtime import find_model

    rng = np.random.default_rng(3)
    seq = frames(3, motion=0.5)
    for p in seq:
        p["albedo"] = rng.uniform(0.2, 0.8, p["color"].shape).astype(np.float32)
    shipped = run(RuntimeMethod(find_model("oidn-acc"), threads=1), seq)
    np.testing.assert_allclose(run(accumulated_oidn(False, 1), seq), shipped, atol=1e-4)
    single = np.stack([run(accumulated_oidn(False, 1), [p])[0] for p in seq])
    np.testing.assert_array_equal(run(accumulated_oidn(True, 1), seq), single)
    assert not np.allclose(shipped[1:], single[1:], atol=1e-3)  # the shipped one kept history


def test_hybrid_takes_the_exact_pixel_when_aligned_and_a_clamped_fetch_otherwise():
    still = frames(3)
    exact = run(OutputHistory(Passthrough()), still)
    np.testing.assert_allclose(run(OutputHistory(Passthrough(), resample="hybrid"), still),
                               exact, rtol=1e-6)
    moving = frames(3, motion=0.5)
    moving[0]["color"][:] = 100.0
    out = run(OutputHistory(Passthrough(), resample="hybrid"), moving)
    assert out[1].max() <= moving[1]["color"].max() + 1e-5  # the fetch was clamped
    assert run(OutputHistory(Passthrough(), resample="bicubic"), moving)[1].max() > 40


def test_the_bench_scores_every_row_on_a_split(tmp_path, capsys):
    """main() over a tiny Mitsuba-format split whose camera slides by whole pixels: every row
    scored, and the pixel-aligned accumulation keeps its history there."""
    pytest.importorskip("pyoidn")
    import json

    from dataset_support import write_sequence

    from quietframe.experiments.output_history import CANDIDATES, main
    from quietframe.scenes.generator import GENERATOR_VERSION

    write_sequence(tmp_path / GENERATOR_VERSION / "test", 41, frames=3, levels=(1,), noise=0.5)
    out = tmp_path / "rows.json"
    assert main(["--data", str(tmp_path), "--renderer", "mitsuba", "--split", "test",
                 "--spp", "1", "--threads", "1", "--json", str(out)]) == 0
    rows = {r["method"]: r for r in json.loads(out.read_text())}
    assert {"oidn-frame", "oidn-acc", "aligned-acc+hybrid", *CANDIDATES} <= set(rows)
    assert all(np.isfinite(r["psnr"]) for r in rows.values())
    assert rows["acc-torch"]["psnr"] == pytest.approx(rows["oidn-acc"]["psnr"], abs=1e-3)
    assert rows["aligned-acc"]["psnr"] == pytest.approx(rows["acc-torch"]["psnr"], abs=1e-6)
    assert rows["aligned-acc"]["psnr"] != pytest.approx(rows["oidn-frame"]["psnr"], abs=1e-3)
    assert "| aligned-acc+hybrid | 1 |" in capsys.readouterr().out
