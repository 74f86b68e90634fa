"""The Blender fixtures (files written by Cycles) through a real server and the `quietframe`
CLI: what comes back, the view-layer options, the Blender rules seen from the wire."""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from quietframe.client import Client, QuietframeError
from quietframe.client.cli import main

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures" / "blender"
SIZE = (64, 36)
LAYERS = ("ViewLayer", "Objects")


def channels_of(data: bytes) -> dict[str, np.ndarray]:
    import OpenEXR

    exr = OpenEXR.File(io.BytesIO(data), separate_channels=True)
    return {k: v.pixels for k, v in exr.channels().items()}


def beauty(layer: str) -> set[str]:
    return {f"{layer}.Combined.{c}" for c in "RGB"}


def shot(tmp_path: Path, name: str, frames=(2, 3)) -> Path:
    """A folder of frames copied from one fixture (the same pixels as frames 2, 3, ...)."""
    src = tmp_path / "in"
    src.mkdir()
    for frame in frames:
        shutil.copy(FIXTURES / name, src / f"shot.{frame:04d}.exr")
    return src


def denoise(live_server, src: Path, out: Path, *options: str) -> int:
    args = ["denoise", "--server", live_server.url, str(src), "--out", str(out), "--quiet"]
    return main([*args, *options])


def test_layer_all_denoises_every_view_layer_into_one_file(tmp_path, live_server):
    src = shot(tmp_path, "two_view_layers.0002.exr")
    given = channels_of((src / "shot.0003.exr").read_bytes())
    assert denoise(live_server, src, tmp_path / "all", "--layer", "all") == 0
    for layer in LAYERS:
        assert denoise(live_server, src, tmp_path / layer, "--layer", layer) == 0
    both = channels_of((tmp_path / "all" / "shot.0003.exr").read_bytes())
    assert set(both) == set(given)
    assert all(both[n].dtype == given[n].dtype for n in given)
    for layer in LAYERS:
        alone = channels_of((tmp_path / layer / "shot.0003.exr").read_bytes())
        for name in beauty(layer):  # each layer as its own session denoised it
            assert not np.array_equal(both[name], given[name]), name
            np.testing.assert_array_equal(both[name], alone[name], err_msg=name)
        other = beauty(LAYERS[1 - LAYERS.index(layer)])
        for name in other:  # a single-layer run leaves the other view layer alone
            np.testing.assert_array_equal(alone[name], given[name], err_msg=name)
    for name in set(given) - beauty("ViewLayer") - beauty("Objects"):
        np.testing.assert_array_equal(both[name], given[name], err_msg=name)
    job = json.loads((tmp_path / "all" / ".quietframe-job.json").read_text())
    assert set(job["sessions"]) == set(LAYERS)


def test_channel_mapping_from_a_file_equals_the_view_layer(tmp_path, live_server):
    src = shot(tmp_path, "two_view_layers.0002.exr", frames=(2,))
    mapping = tmp_path / "objects.json"
    mapping.write_text(
        json.dumps(
            {
                "color": "Objects.Combined",
                "albedo": "Objects.Denoising Albedo",
                "normal": "Objects.Denoising Normal",
                "depth": "Objects.Denoising Depth.Z",
                "motion": ["Objects.Vector.X", "Objects.Vector.Y"],
            }
        )
    )
    mapped_run = ["--channels", f"@{mapping}", "--motion-scale", "1", "-1"]
    assert denoise(live_server, src, tmp_path / "map", *mapped_run) == 0
    assert denoise(live_server, src, tmp_path / "layer", "--layer", "Objects") == 0
    mapped = channels_of((tmp_path / "map" / "shot.0002.exr").read_bytes())
    layered = channels_of((tmp_path / "layer" / "shot.0002.exr").read_bytes())
    assert set(mapped) == set(layered)
    for name in mapped:  # the same buffers found two ways: the same file
        np.testing.assert_array_equal(mapped[name], layered[name], err_msg=name)


def test_two_view_layers_without_a_choice_say_how_to_choose(tmp_path, live_server, capsys):
    src = shot(tmp_path, "two_view_layers.0002.exr", frames=(2,))
    assert denoise(live_server, src, tmp_path / "out") == 3  # an input error (exit codes)
    err = capsys.readouterr().err
    assert "ambiguous_channels" in err and "Objects.Combined.R" in err and "--layer" in err
    assert denoise(live_server, src, tmp_path / "x", "--channels", "[1]") == 2
    assert "JSON object" in capsys.readouterr().err
    assert denoise(live_server, src, tmp_path / "y", "--layer", "all", "--channels", "{}") == 0


def test_denoised_layer_over_the_cli(tmp_path, live_server):
    src = shot(tmp_path, "passes_half_piz.0002.exr", frames=(2,))
    assert denoise(live_server, src, tmp_path / "out", "--denoised-layer", "Denoised") == 0
    given = channels_of((src / "shot.0002.exr").read_bytes())
    out = channels_of((tmp_path / "out" / "shot.0002.exr").read_bytes())
    assert set(out) == set(given) | {f"ViewLayer.Denoised.{c}" for c in "RGB"}
    for name in given:
        np.testing.assert_array_equal(out[name], given[name], err_msg=name)


def frame(live_server, name: str, **session) -> tuple[dict, object]:
    data = (FIXTURES / name).read_bytes()
    with Client(live_server.url) as client:
        created = client.create_session(*SIZE, **session)
        try:
            return created, client.send_frame(created["id"], 0, data)
        finally:
            client.delete_session(created["id"])


def test_noisy_image_is_denoised_into_combined_over_http(live_server):
    given = channels_of((FIXTURES / "blender_denoised.0002.exr").read_bytes())
    _, result = frame(live_server, "blender_denoised.0002.exr")
    out = channels_of(result.exr)
    assert set(out) == set(given)
    for name in beauty("ViewLayer"):
        assert not np.array_equal(out[name], given[name]), name
    for name in set(given) - beauty("ViewLayer"):  # Noisy Image and Combined.A as they were
        np.testing.assert_array_equal(out[name], given[name], err_msg=name)


def test_all_zero_vector_is_missing_and_sky_depth_is_sanitized(live_server):
    # a model that reads motion reports it missing (auto chooses one that does not: the
    # usable-buffer rule, tests/service/test_cli_choice.py)
    _, blurred = frame(live_server, "motion_blur.0002.exr", model="nbg-2l-3g")
    assert blurred.missing == ("motion",)
    _, moving = frame(live_server, "passes_float_zip.0002.exr")
    assert moving.missing == ()
    given = channels_of((FIXTURES / "passes_float_zip.0002.exr").read_bytes())
    misses = int((given["ViewLayer.Denoising Depth.Z"] == 0).sum())
    assert moving.sanitized == misses > 0  # the sky's "no hit" depths, made the farthest


def test_colour_only_frame_is_served_or_gets_a_422_that_says_what_would_work(live_server):
    """A colour-only Cycles frame: `auto` serves it with a model that takes the colour alone
    (oidn-frame, or an NBG model trained with buffer dropout), reporting the optional buffers it
    lacks; a session on a model that needs them gets a 422 that names them, the models that
    would accept the frame, and the channel mapping."""
    created, result = frame(live_server, "plain_rgba.0002.exr")
    assert set(result.missing) >= {"albedo", "normal"}
    with pytest.raises(QuietframeError) as err:
        frame(live_server, "plain_rgba.0002.exr", model="accumulation")
    assert err.value.status == 422 and err.value.code == "missing_channels"
    detail = err.value.detail
    assert "colour-only" in detail and "Installed models that accept the buffers found" in detail
    assert result.model.split()[0] in detail  # the model auto chose for the frame
    assert "'albedo', 'normal', 'depth'" in detail and "channel mapping" in detail
