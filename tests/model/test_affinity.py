"""The affinity denoiser (model/affinity.py): the exported graph through the runtime matches
PyTorch over a sequence at two kernel sizes chosen at run time, the model honours reset and its
history, and quietframe-train learns it (loss falls on a fixed batch, a resumed run equals an
uninterrupted one)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from dataset_support import write_generator_splits
from sequence_support import moving_frame

torch = pytest.importorskip("torch")

from quietframe.export.affinity_export import export_affinity  # noqa: E402
from quietframe.export.onnx_export import example_inputs  # noqa: E402
from quietframe.model import affinity, families  # noqa: E402
from quietframe.model import train as qt  # noqa: E402
from quietframe.model.losses import bandwidth_regulariser  # noqa: E402
from quietframe.runtime import Denoiser, find_model, installed_models  # noqa: E402

HEIGHT, WIDTH, FRAMES = 32, 40, 3
NAMES = ("color", "albedo", "normal", "depth", "motion")


def frame_inputs(index: int) -> tuple:
    return moving_frame(index, HEIGHT, WIDTH)


# Each export path: the U-Net at full (f16) and half resolution without history (h16-single) and
# with it, with K = 5 kernels, the guide and the coarse-first order (h16-k5gc, the shipped one).
@pytest.fixture(scope="module", params=["affinity-f16", "affinity-h16-single",
                                      "affinity-h16-k5gc"])
def exported(request, tmp_path_factory):
    torch.manual_seed(0)
    model = affinity.AffinityDenoiser(affinity.VARIANTS[request.param]).eval()
    path = export_affinity(model, tmp_path_factory.mktemp("onnx") / f"{request.param}.onnx")
    return model, Denoiser(path, threads=2)


def run_both(model, runtime, kernel_size: int):
    """FRAMES frames through PyTorch and the runtime with the state carried."""
    torch_state, ort_state, pairs = model.initial_state(1, HEIGHT, WIDTH), None, []
    for index in range(FRAMES):
        buffers = frame_inputs(index)
        reset = torch.tensor([1.0 if index == 0 else 0.0])
        with torch.no_grad():
            expected, torch_state = model(*buffers, reset, torch_state, kernel_size=kernel_size)
        result = runtime.denoise({k: b[0].numpy() for k, b in zip(NAMES, buffers, strict=True)},
                                 ort_state, options={"kernel_size": kernel_size})
        ort_state = result.state
        pairs.append((expected[0].numpy(), result.color,
                      [t.numpy() for t in torch_state],
                      [ort_state["affinity"], ort_state["embedding"]]))
    return pairs, buffers, ort_state


@pytest.mark.parametrize("kernel_size", [5, 9])
def test_sequence_matches_pytorch_with_state_carried(exported, kernel_size):
    model, runtime = exported
    pairs, buffers, state = run_both(model, runtime, kernel_size)
    for expected, color, torch_states, ort_states in pairs:
        scale = float(np.abs(expected).max())
        np.testing.assert_allclose(color, expected, rtol=1e-4, atol=1e-4 * scale)
        for ours, theirs in zip(ort_states, torch_states, strict=True):
            np.testing.assert_allclose(ours, theirs, rtol=1e-4,
                                       atol=1e-4 * float(np.abs(theirs).max()))
    planes = {k: b[0].numpy() for k, b in zip(NAMES, buffers, strict=True)}
    fresh = runtime.denoise(planes, None, options={"kernel_size": kernel_size}).color
    used_history = np.abs(fresh - pairs[-1][1]).max() > 1e-3 * scale
    assert used_history == model.config.temporal


def test_kernel_size_is_a_run_time_input(exported, tmp_path):
    model, runtime = exported
    info = runtime.info
    assert [(i.name, i.default) for i in info.inputs] == [("kernel_size", 13)]
    scale = model.config.unet_scale
    assert [(s.name, s.channels, s.scale) for s in info.state_specs] == [
        ("affinity", 18, 1), ("embedding", 32, scale)]
    assert info.state_nbytes(5, 3) == 4 * (18 * 15 + 32 * (-(-5 // scale)) * (-(-3 // scale)))
    assert json.loads(info.metadata["quietframe.architecture"])["family"] == "affinity"
    planes = {k: b[0].numpy() for k, b in zip(NAMES, frame_inputs(0), strict=True)}
    by_size = {k: runtime.denoise(planes, None, options={"kernel_size": k}).color
               for k in (5, 13)}
    default = runtime.denoise(planes, None).color
    np.testing.assert_array_equal(default, by_size[13])
    assert np.abs(by_size[5] - by_size[13]).max() > 1e-4  # the input reaches the kernels
    session_seven = Denoiser(info.path, threads=1, options={"kernel_size": 7})
    with torch.no_grad():
        expected, _ = model(*frame_inputs(0), torch.ones(1), model.initial_state(
            1, HEIGHT, WIDTH), kernel_size=7)
    np.testing.assert_allclose(session_seven.denoise(planes, None).color, expected[0].numpy(),
                               rtol=1e-4, atol=1e-4 * float(expected.abs().max()))
    with pytest.raises(ValueError, match="one of"):
        runtime.denoise(planes, None, options={"kernel_size": 4})
    with pytest.raises(ValueError, match="no option"):
        runtime.denoise(planes, None, options={"kernel": 5})


def test_dynamic_sizes_and_missing_motion(exported):
    _, runtime = exported
    for height, width in [(1, 1), (5, 3), (37, 53)]:
        color, albedo, normal, depth, *_ = example_inputs(height, width, seed=1)
        planes = {"color": color[0].numpy(), "albedo": albedo[0].numpy(),
                  "normal": normal[0].numpy(), "depth": depth[0].numpy()}
        first = runtime.denoise(planes, None)
        low = -(-height // runtime.info.state_specs[1].scale)
        assert first.state["embedding"].shape[2] == low
        second = runtime.denoise(planes, first.state, options={"kernel_size": 5})
        assert second.color.shape == (3, height, width) and np.isfinite(second.color).all()
        assert second.missing == ("motion",)


def test_reset_drops_the_history():
    torch.manual_seed(1)
    model = affinity.AffinityDenoiser(affinity.VARIANTS["affinity-h8"]).eval()
    buffers = frame_inputs(1)
    with torch.no_grad():
        _, state = model(*frame_inputs(0), torch.ones(1), model.initial_state(1, HEIGHT, WIDTH))
        fresh, _ = model(*buffers, torch.ones(1), model.initial_state(1, HEIGHT, WIDTH))
        reset, _ = model(*buffers, torch.ones(1), state)
        carried, _ = model(*buffers, torch.zeros(1), state)
    torch.testing.assert_close(reset, fresh)
    assert (carried - fresh).abs().max() > 1e-4


def test_bandwidth_regulariser_is_eq_13():
    a = [torch.full((1, 1, 2, 2), 2.0), torch.tensor([[[[1.0, 3.0]]]])]
    b = torch.full((1, 1, 2, 2), 0.5)
    assert bandwidth_regulariser(a, b).item() == pytest.approx(4.0 + 5.0 + 0.25)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    write_generator_splits(root)
    return root


def config(data, **kw) -> qt.TrainConfig:
    base = dict(variant="affinity-h8", data=str(data), crop=24, frames=2, batch=2, steps=4,
                eval_every=2, log_every=1, threads=1, seed=5, kernel_size=5)
    return qt.TrainConfig(**{**base, **kw})


def test_loss_falls_on_a_fixed_batch(data):
    cfg = config(data)
    torch.manual_seed(cfg.seed)
    model = qt.build_model(cfg)
    batch = qt.TrainingBatches(cfg)(0)
    # The tiny dataset's reference is no albedo × irradiance product (random albedo texture):
    # white albedo makes it one, as rendered data is.
    batch["albedo"] = torch.ones_like(batch["albedo"])
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(8):
        penalties: list = []
        outputs = qt.unroll(model, batch, penalties)
        refs = [batch["reference"][:, i] for i in range(len(outputs))]
        loss = qt.sequence_loss(cfg, outputs, refs) + cfg.bandwidth_weight * torch.stack(
            penalties).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
        assert len(penalties) == cfg.frames
    assert min(losses[-3:]) < 0.9 * losses[0], losses


@pytest.mark.parametrize("sizes", ["", "3,5"])
def test_resumed_run_equals_uninterrupted_run(data, tmp_path, sizes):
    cfg = config(data, kernel_sizes=sizes)
    qt.train(cfg, tmp_path / "straight")
    qt.train(cfg, tmp_path / "paused", stop_at=2)
    paused = torch.load(tmp_path / "paused" / "checkpoint.pt", weights_only=False)
    qt.train(cfg, tmp_path / "paused")
    a = torch.load(tmp_path / "straight" / "checkpoint.pt", weights_only=False)
    b = torch.load(tmp_path / "paused" / "checkpoint.pt", weights_only=False)
    assert a["step"] == b["step"] == cfg.steps and paused["step"] == 2
    for name, value in a["model"].items():
        assert torch.equal(value, b["model"][name]), name
    assert not torch.equal(a["model"]["unet.out.weight"], paused["model"]["unet.out.weight"])
    model, _ = families.load_checkpoint(str(tmp_path / "straight" / "best.pt"))
    assert model.config == dataclasses.replace(affinity.VARIANTS["affinity-h8"], kernel_size=5)
    for flag in ({"variant": "affinity-h16"}, {"kernel_size": 9}):
        with pytest.raises(ValueError, match="cannot change a checkpoint's model"):
            qt.resume_config(tmp_path / "straight", flag)


def test_kernel_size_drawn_per_step_is_a_function_of_seed_and_step(data):
    cfg = config(data, kernel_sizes="5,9,13")
    draws = [qt.step_kernel_size(cfg, step)["kernel_size"] for step in range(40)]
    assert draws == [qt.step_kernel_size(cfg, step)["kernel_size"] for step in range(40)]
    assert set(draws) == {5, 9, 13}
    assert qt.step_kernel_size(config(data), 3) == {}  # the model's own size


def test_export_cli_takes_an_affinity_checkpoint(data, tmp_path):
    from quietframe.export import cli

    run = tmp_path / "run"
    qt.train(config(data, steps=2), run)
    out = tmp_path / "trained.onnx"
    assert cli.main(["--checkpoint", str(run / "best.pt"), "--out", str(out)]) == 0
    info = Denoiser(out, threads=1).info
    assert info.name == "affinity-h8" and info.training["steps_done"] == 2
    assert [(i.name, i.default) for i in info.inputs] == [("kernel_size", 5)]  # trained size


def test_extra_inputs_come_from_metadata_alone():
    from pathlib import Path

    from quietframe.runtime.denoiser import read_model_info

    meta = {"quietframe.inputs": json.dumps([{"name": "strength", "dtype": "float32",
                                              "shape": [1], "default": 0.5, "allowed": None}]),
            "quietframe.state": json.dumps([{"name": "h", "channels": 2, "scale": 4}])}
    info = read_model_info(Path("m.onnx"), meta)
    (spec,) = info.inputs
    assert spec.array(spec.default).dtype == np.float32 and spec.array(3.0).tolist() == [3.0]
    assert info.state_specs[0].shape(9, 8) == (1, 2, 3, 2)  # ⌈9/4⌉ × ⌈8/4⌉
    assert read_model_info(Path("m.onnx"), {}).inputs == ()  # NBG files: nothing extra to feed


SHIPPED = [p.stem for p in installed_models() if p.stem.startswith("affinity")]


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_model_is_the_export_of_its_shipped_checkpoint(name):
    """models/<name>.onnx is what quietframe-export makes of models/training/<name>/best.pt with
    today's model code (a stale export fails), at its default and another kernel size, with the
    weightless settings the export put on it (families.export_settings)."""
    checkpoint_path = Path(__file__).resolve().parents[2] / "models" / "training" / name / "best.pt"
    runtime = Denoiser(find_model(name), threads=2)
    model, checkpoint = families.load_checkpoint(
        str(checkpoint_path), **families.export_settings(runtime.info.card.architecture))
    assert runtime.info.training["steps_done"] == checkpoint["training"]["steps_done"]
    default = next(i.default for i in runtime.info.inputs if i.name == "kernel_size")
    assert default == model.config.kernel_size
    for kernel_size in (default, 9):
        pairs, _, _ = run_both(model.eval(), runtime, kernel_size)
        for expected, color, _, _ in pairs:
            np.testing.assert_allclose(color, expected, rtol=1e-4,
                                       atol=1e-4 * float(np.abs(expected).max()))


def test_kernel_count_dilations_and_guide():
    # K kernels: dilations 1..2^(K-1) in the paper's order, reversed with coarse_first
    assert [affinity.kernel_dilation(k, 5, False) for k in range(5)] == [1, 2, 4, 8, 16]
    assert [affinity.kernel_dilation(k, 5, True) for k in range(5)] == [16, 8, 4, 2, 1]
    with pytest.raises(ValueError, match="kernels"):
        affinity.AffinityConfig(kernels=1)
    torch.manual_seed(0)
    model = affinity.AffinityDenoiser(affinity.VARIANTS["affinity-h16-k5gc"])
    assert model.unet.out.out_channels == 5 * affinity.PARAMS_PER_KERNEL + 2
    # the guide makes features differ across a one-pixel albedo edge the half-resolution
    # U-Net cannot see: only the guide's projection separates the two columns
    buffers = [b.clone() for b in frame_inputs(0)]
    buffers[1][..., :, 1::2] = 0.9  # albedo alternating per column
    buffers[1][..., :, 0::2] = 0.1
    guide = affinity.guide_inputs(*buffers[1:4])
    assert guide.shape[1] == affinity.GUIDE_CHANNELS
    extra = model.guide(guide)
    assert (extra[..., 1::2] - extra[..., 0::2]).abs().mean() > 0.1


def test_firefly_clamp_bounds_a_firefly_and_exports(data, tmp_path):
    """With the clamp (outlier_sigmas, floor × the frame's mean), a 5e4 firefly no longer
    reaches the output: PyTorch and the exported graph agree, the tiling knows the clamp's
    reach and frame statistic, and a fine-tune of a clamp-less run may switch it on."""
    color, albedo, normal, depth, motion = frame_inputs(0)
    fiery = color.clone()
    fiery[0, :, 10, 12] = 5e4  # below the runtime's 65504 (half max) input bound
    buffers = (fiery, albedo, normal, depth, motion, torch.ones(1))
    clamp = dict(outlier_sigmas=3.0, outlier_floor=128.0)
    outputs = {}
    for on in (False, True):
        torch.manual_seed(0)
        variant = affinity.VARIANTS["affinity-h16-k5gc"]
        model = affinity.AffinityDenoiser(dataclasses.replace(variant, **(clamp if on else {})))
        with torch.no_grad():
            outputs[on] = model.eval()(*buffers, model.initial_state(1, HEIGHT, WIDTH))[0]
    # clamp-less: the firefly's energy spreads into the output (~280 at init); clamped to the
    # floor (128 × the frame's mean luminance, which on this 32×40 frame the firefly itself
    # raises 30-fold) it leaves ~15
    assert outputs[False][0, :, 10, 12].max() > 10 * outputs[True][0, :, 10, 12].max()
    path = export_affinity(model, tmp_path / "clamped.onnx")
    runtime = Denoiser(path, threads=1)
    planes = {k: b[0].numpy() for k, b in zip(NAMES, buffers[:5], strict=True)}
    np.testing.assert_allclose(runtime.denoise(planes, None).color, outputs[True][0].numpy(),
                               rtol=1e-4, atol=1e-4 * float(outputs[True].abs().max()))
    tiling = runtime.card.tiling
    plain = affinity_tiling_of(affinity.VARIANTS["affinity-h16-k5gc"])
    assert tiling.radius == plain.radius + 2
    assert [s.name for s in tiling.statistics] == ["mean_depth", "mean_luminance"]
    # fine-tuning a clamp-less checkpoint with the clamp on (it has no weights); a resume may not
    qt.train(config(data, steps=1), tmp_path / "base")
    flags = {"init": str(tmp_path / "base" / "checkpoint.pt"), "data": str(data), "crop": 24,
             "frames": 2, "batch": 2, "steps": 1, "threads": 1, **clamp}
    cfg = qt.resume_config(tmp_path / "tuned", flags)
    qt.train(cfg, tmp_path / "tuned")
    tuned = torch.load(tmp_path / "tuned" / "checkpoint.pt", weights_only=False)
    assert (tuned["config"]["outlier_sigmas"], tuned["config"]["outlier_floor"]) == (3.0, 128.0)
    with pytest.raises(ValueError, match="outlier_sigmas"):
        qt.resume_config(tmp_path / "tuned", {"outlier_sigmas": 0.0})


def affinity_tiling_of(config):
    from quietframe.runtime.receptive import affinity_tiling

    return affinity_tiling(config.to_dict(), ())
