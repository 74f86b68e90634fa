"""EXR header check, the renderer alias table, motion-vector conventions, pixels in and out."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from conftest import LAYOUTS, frame_bytes, make_buffers, read_exr, write_exr

from quietframe.runtime.frame_errors import (
    AmbiguousChannels,
    BadExr,
    MissingChannels,
    ResolutionTooLarge,
    UnsupportedExr,
)
from quietframe.service import frames

REQUIRED = ("color", "albedo", "normal", "depth")
OPTIONAL = ("motion",)


def hwc(planes: np.ndarray) -> np.ndarray:
    """Decoded (C, H, W) planes as the (H, W, C) / (H, W) images of make_buffers."""
    return planes[0] if planes.shape[0] == 1 else planes.transpose(1, 2, 0)


def load(data: bytes, mapping=None, scale=(1.0, 1.0)):
    header = frames.read_header(data, 8192, 8192)
    sources = frames.resolve(header.channels, REQUIRED, OPTIONAL, mapping, scale)
    return header, sources, frames.decode(data, sources)


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_renderer_layouts_map_to_canonical_buffers(layout):
    expected = make_buffers(seed=1)
    data = write_exr(LAYOUTS[layout](expected))
    header, sources, decoded = load(data)
    assert (header.width, header.height) == (64, 48)
    assert set(decoded.buffers) == {"color", "albedo", "normal", "depth", "motion"}
    for name, array in expected.items():
        np.testing.assert_allclose(
            hwc(decoded.buffers[name]),
            array,
            rtol=0,
            atol=1e-6,
            err_msg=f"{layout}: {name} from {sources[name]}",
        )


def test_blender_view_layer_and_vector_sign():
    b = make_buffers(seed=2)
    data = write_exr(LAYOUTS["blender"](b))
    _, sources, decoded = load(data)
    assert sources["color"].channels == (
        "ViewLayer.Combined.R",
        "ViewLayer.Combined.G",
        "ViewLayer.Combined.B",
    )
    assert sources["depth"].channels == ("ViewLayer.Denoising Depth.Z",)
    assert sources["motion"].channels == ("ViewLayer.Vector.X", "ViewLayer.Vector.Y")
    # Vector.Y is raster-up: (1.5, -0.5) ours was written as (1.5, +0.5).
    assert decoded.buffers["motion"][:, 0, 0].tolist() == [1.5, -0.5]


def test_noisy_image_preferred_over_denoised_combined():
    _, sources, decoded = load(frame_bytes("blender-noisy-image"))
    assert sources["color"].channels[0] == "ViewLayer.Noisy Image.R"
    assert decoded.buffers["color"].max() < 7


def test_missing_motion_is_optional():
    _, sources, decoded = load(frame_bytes("arnold", motion=False))
    assert "motion" not in sources and "motion" not in decoded.buffers


def test_missing_required_buffer_names_found_and_expected():
    ch = LAYOUTS["plain-normal"](make_buffers())
    del ch["albedo.R"], ch["albedo.G"], ch["albedo.B"]
    header = frames.read_header(write_exr(ch), 8192, 8192)
    with pytest.raises(MissingChannels) as err:
        frames.resolve(header.channels, REQUIRED, OPTIONAL)
    assert "'albedo'" in err.value.detail and "normal.X" in err.value.detail
    assert "Denoising Albedo" in err.value.detail


def test_two_view_layers_are_ambiguous_unless_mapped():
    b = make_buffers()
    ch = {**LAYOUTS["blender"](b), **frames_prefixed(LAYOUTS["blender"](b), "Other")}
    data = write_exr(ch)
    header = frames.read_header(data, 8192, 8192)
    with pytest.raises(AmbiguousChannels):
        frames.resolve(header.channels, REQUIRED, OPTIONAL)
    mapping = {
        "color": "Other.Combined",
        "albedo": "Other.Denoising Albedo",
        "normal": "Other.Denoising Normal",
        "depth": "Other.Denoising Depth.Z",
        "motion": ["Other.Vector.X", "Other.Vector.Y"],
    }
    _, sources, decoded = load(data, mapping, scale=(1.0, -1.0))
    assert sources["color"].channels[0] == "Other.Combined.R"
    np.testing.assert_allclose(hwc(decoded.buffers["motion"]), b["motion"])


def frames_prefixed(channels, view_layer):
    return {k.replace("ViewLayer.", f"{view_layer}.", 1): v for k, v in channels.items()}


def test_mapping_to_absent_channels_is_refused():
    header = frames.read_header(frame_bytes(), 8192, 8192)
    with pytest.raises(MissingChannels, match="beauty"):
        frames.resolve(header.channels, REQUIRED, OPTIONAL, {"color": "beauty"})


def test_validate_mapping():
    frames.validate_mapping({"color": "beauty", "motion": ["u", "v"]})
    with pytest.raises(ValueError, match="unknown buffer"):
        frames.validate_mapping({"colour": "beauty"})
    with pytest.raises(ValueError, match="3 channel names"):
        frames.validate_mapping({"albedo": ["a", "b"]})


def test_header_is_read_without_pixels_and_size_checked_first():
    data = bytearray(frame_bytes())
    header = frames.read_header(bytes(data), 8192, 8192)
    assert header.parts == 1 and "albedo.G" in header.channels and not header.cut
    # Claim a 30000x20000 data window: refused from the header, long before any decoding.
    at = bytes(data).index(b"dataWindow\0box2i\0") + len(b"dataWindow\0box2i\0") + 4
    data[at : at + 16] = struct.pack("<iiii", 0, 0, 29999, 19999)
    with pytest.raises(ResolutionTooLarge, match="30000x20000"):
        frames.read_header(bytes(data[: header.header_bytes]), 8192, 8192)


@pytest.mark.parametrize("cut", [0, 50, 200, 400, -20, -1])
def test_truncated_exr_is_bad_request(cut):
    data = frame_bytes()
    with pytest.raises(BadExr):
        header = frames.read_header(data[:cut], 8192, 8192)
        sources = frames.resolve(header.channels, REQUIRED, OPTIONAL)
        frames.decode(data[:cut], sources)


def test_garbage_and_corrupt_chunks_are_bad_request():
    with pytest.raises(BadExr, match="magic"):
        frames.read_header(b"GIF89a" + bytes(100), 8192, 8192)
    data = bytearray(frame_bytes())
    header = frames.read_header(bytes(data), 8192, 8192)
    sources = frames.resolve(header.channels, REQUIRED, OPTIONAL)
    rng = np.random.default_rng(0)
    failures = 0
    for _ in range(30):  # flip bytes in the pixel data: decode fails cleanly or returns pixels
        corrupt = bytearray(data)
        for i in rng.integers(len(data) // 2, len(data), 8):
            corrupt[i] ^= 0xFF
        try:
            frames.decode(bytes(corrupt), sources)
        except BadExr:
            failures += 1
    assert failures > 0


def test_deep_and_subsampled_are_unsupported():
    data = bytearray(frame_bytes())
    data[5] |= 0x08  # non-image (deep) flag
    with pytest.raises(UnsupportedExr, match="deep"):
        frames.read_header(bytes(data), 8192, 8192)


def test_cut_attribute():
    assert frames.read_header(frame_bytes(header={"quietframe.cut": 1}), 8192, 8192).cut
    assert frames.read_header(frame_bytes(header={"quietframe.cut": "true"}), 8192, 8192).cut
    assert not frames.read_header(frame_bytes(header={"quietframe.cut": 0}), 8192, 8192).cut


def test_multipart_channels_are_merged():
    import io

    import OpenEXR

    b = make_buffers()
    ch = {k: np.ascontiguousarray(v) for k, v in LAYOUTS["plain-normal"](b).items()}
    parts = [
        OpenEXR.Part({}, {k: v for k, v in ch.items() if "." not in k}, "rgba"),
        OpenEXR.Part({}, {k: v for k, v in ch.items() if "." in k}, "aovs"),
    ]
    out = io.BytesIO()
    OpenEXR.File(parts).write(out)
    header, _, decoded = load(out.getvalue())
    assert header.parts == 2
    np.testing.assert_allclose(hwc(decoded.buffers["albedo"]), b["albedo"])


def test_encode_keeps_header_attributes_and_every_channel():
    import OpenEXR

    attrs = {
        "comment": "shot 12",
        "worldToCamera": np.eye(4, dtype=np.float32),
        "compression": OpenEXR.PIZ_COMPRESSION,
        "dataWindow": (np.array([4, 2], np.int32), np.array([67, 49], np.int32)),
        "displayWindow": (np.array([0, 0], np.int32), np.array([99, 99], np.int32)),
    }
    data = frame_bytes("blender", header=attrs)
    _, in_channels = read_exr(data)
    _, sources, decoded = load(data)
    color = decoded.buffers["color"] * 2
    for precision, dtype in (("half", np.float16), ("float", np.float32)):
        out = frames.encode(
            color, decoded, sources["color"].channels, precision, {"quietframe.frame": "3"}
        )
        header, channels = read_exr(out)
        assert sorted(channels) == sorted(in_channels)
        assert channels["ViewLayer.Combined.G"].dtype == dtype
        assert channels["ViewLayer.Combined.A"].dtype == np.float32  # as given
        assert header["comment"] == "shot 12" and header["quietframe.frame"] == "3"
        assert header["compression"] == OpenEXR.PIZ_COMPRESSION
        assert header["dataWindow"][0].tolist() == [4, 2]
        np.testing.assert_array_equal(header["worldToCamera"], np.eye(4))
        np.testing.assert_allclose(channels["ViewLayer.Combined.R"], color[0], rtol=1e-3)
        for name in set(in_channels) - {f"ViewLayer.Combined.{c}" for c in "RGB"}:
            np.testing.assert_array_equal(channels[name], in_channels[name], err_msg=name)


def test_multipart_input_comes_back_multipart():
    """Parts keep their names, channels and pixel types; the colour is replaced in its part."""
    import io

    import OpenEXR

    b = make_buffers()
    ch = LAYOUTS["plain-normal"](b)
    beauty = {k: np.ascontiguousarray(v, np.float16) for k, v in ch.items() if "." not in k}
    aovs = {k: np.ascontiguousarray(v, np.float32) for k, v in ch.items() if "." in k}
    aovs["id.V"] = np.arange(48 * 64, dtype=np.uint32).reshape(48, 64)
    parts = [
        OpenEXR.Part({"comment": "beauty part"}, dict(beauty), "rgba"),  # (it converts the dict)
        OpenEXR.Part({"compression": OpenEXR.PIZ_COMPRESSION}, dict(aovs), "aovs"),
    ]
    given = io.BytesIO()
    OpenEXR.File(parts).write(given)
    header, sources, decoded = load(given.getvalue())
    color = decoded.buffers["color"] * 3
    out = frames.encode(color, decoded, sources["color"].channels, "float")
    assert frames.read_header(out, 8192, 8192).parts == 2
    back = OpenEXR.File(io.BytesIO(out), separate_channels=True)
    assert [p.name() for p in back.parts] == ["rgba", "aovs"]
    assert back.parts[0].header["comment"] == "beauty part"
    assert back.parts[1].header["compression"] == OpenEXR.PIZ_COMPRESSION
    for part, expected in zip(back.parts, (beauty, aovs), strict=True):
        assert set(part.channels) == set(expected)
        for name, array in expected.items():
            got = part.channels[name].pixels
            colour = name in ("R", "G", "B")
            assert got.dtype == (np.float32 if colour else array.dtype), name
            if not colour:
                np.testing.assert_array_equal(got, array, err_msg=name)
    np.testing.assert_allclose(
        back.parts[0].channels["G"].pixels, color[1], rtol=1e-6
    )


def test_every_alias_is_documented():
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[2] / "docs" / "service.md").read_text()
    table = doc[doc.index("| buffer | aliases") :]
    for buffer, aliases in frames.ALIASES.items():
        for alias in aliases:
            if alias.layer:
                assert f"`{alias.layer}`" in table, (buffer, alias.layer)


def test_json_logs_carry_extra_fields(capsys):
    import json
    import logging

    from quietframe.service import logs

    root = logging.getLogger()
    saved = root.handlers[:], root.level
    try:
        logs.configure("info", as_json=True)
        logging.getLogger("quietframe.service").info("frame", extra={"session": "abc", "ms": 1.5})
        entry = json.loads(capsys.readouterr().err.strip().splitlines()[-1])
    finally:
        root.handlers[:], _ = saved[0], root.setLevel(saved[1])
    assert entry["msg"] == "frame" and entry["session"] == "abc" and entry["ms"] == 1.5
    assert entry["level"] == "info" and entry["ts"].endswith("Z")


def test_attribute_that_cannot_be_written_back_is_dropped_not_fatal():
    color = np.ones((3, 4, 4), np.float32)
    header = {"comment": "kept", "odd": object()}
    frame = frames.DecodedFrame({}, [frames.Part("", header, {})], color_half=True)
    out = frames.encode(color, frame, ["R", "G", "B"], "half")
    attributes, channels = read_exr(out)
    assert attributes["comment"] == "kept" and attributes["quietframe.dropped_attributes"] == "odd"
    assert sorted(channels) == ["B", "G", "R"]


def test_output_passes_benchmark_runs(capsys):
    """experiments/output_passes.py at a tiny size: complete outputs hold more than the beauty."""
    from quietframe.experiments import output_passes

    assert output_passes.main(["--width", "32", "--height", "18", "--repeats", "1",
                               "--warmup", "0", "--compression", "zip"]) == 0
    rows = [r for r in capsys.readouterr().out.splitlines() if r.startswith("| zip")]
    assert [r.split("|")[2].strip() for r in rows] == ["11", "39"]
