"""Files written by Blender itself (Cycles, bpy 4.5) through the service's frame I/O.

The fixtures in tests/fixtures/blender/ are rendered by tools/render_blender_fixtures.py and
committed, so these tests need no bpy; the tests that ask Blender to read quietframe's output
run Blender in its own venv (tests/cycles_support.py) and are skipped without one. What a
Blender farm needs (complete outputs, Noisy Image written back as Combined, the sky's depth,
an all-zero Vector reported missing, colour-only frames told what would work, the CLI's view
layers) is plain tests.
"""

from __future__ import annotations

import io
import json
import re
from pathlib import Path

import numpy as np
import pytest
from cycles_support import blender_json, require_cycles

from quietframe.runtime.frame_errors import AmbiguousChannels, MissingChannels
from quietframe.service import frames

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures" / "blender"
MANIFEST = json.loads((FIXTURES / "manifest.json").read_text())
VARIANTS = MANIFEST["variants"]
FILES = [(name, file) for name, v in VARIANTS.items() for file in v["files"]]
REQUIRED = ("color", "albedo", "normal", "depth")
OPTIONAL = ("motion",)
HALF, FLOAT = 1, 2  # EXR pixel types

# Blender's pass names and their channel suffixes, as measured in the fixtures.
PASSES = {
    "Combined": "RGBA",
    "Noisy Image": "RGBA",
    "Denoising Albedo": "RGB",
    "Denoising Normal": "XYZ",
    "Denoising Depth": "Z",
    "Depth": "Z",
    "Vector": "XYZW",
}
ALL_PASSES = (
    "Combined",
    "Denoising Albedo",
    "Denoising Normal",
    "Denoising Depth",
    "Depth",
    "Vector",
)
# Only these follow the file's half/float setting; Blender writes the others as float always.
COLOUR_PASSES = ("Combined", "Noisy Image", "Denoising Albedo")
SKY_RGB = (0.35, 0.55, 0.9)  # the world colour in the render script
BACKGROUND_Z = 1e10  # what Blender's Depth pass holds where a ray hits nothing


def layer_channels(layer: str, *passes: str) -> set[str]:
    return {f"{layer}.{p}.{c}" for p in passes for c in PASSES[p]}


def expected_channels(variant: str) -> set[str]:
    if variant == "plain_rgba":
        return {"R", "G", "B", "A"}
    if variant == "no_vector":
        return layer_channels("ViewLayer", *ALL_PASSES[:4])
    expected = layer_channels("ViewLayer", *ALL_PASSES)
    if variant == "two_view_layers":
        expected |= layer_channels("Objects", *ALL_PASSES)
    if variant == "blender_denoised":
        expected |= layer_channels("ViewLayer", "Noisy Image")
    return expected


def read(file: str) -> bytes:
    return (FIXTURES / file).read_bytes()


def load(data: bytes, mapping=None, scale=(1.0, 1.0), required=REQUIRED, optional=OPTIONAL):
    """header, sources and the decoded frame, its planes shown as (H, W, C) / (H, W) images."""
    header = frames.read_header(data, 8192, 8192)
    sources = frames.resolve(header.channels, required, optional, mapping, scale)
    decoded = frames.decode(data, sources)
    decoded.buffers = {k: image(v) for k, v in decoded.buffers.items()}
    return header, sources, decoded


def image(planes: np.ndarray) -> np.ndarray:
    return planes[0] if planes.shape[0] == 1 else planes.transpose(1, 2, 0)


def pixels(data: bytes) -> dict[str, np.ndarray]:
    """Every channel as float64, straight from OpenEXR (for the measured facts)."""
    import OpenEXR

    exr = OpenEXR.File(io.BytesIO(data), separate_channels=True)
    return {k: np.asarray(v.pixels, np.float64) for k, v in exr.channels().items()}


def read_back(data: bytes) -> tuple[dict, dict[str, np.ndarray]]:
    import OpenEXR

    exr = OpenEXR.File(io.BytesIO(data), separate_channels=True)
    return dict(exr.header()), {k: v.pixels for k, v in exr.channels().items()}


def roundtrip(
    data: bytes, mapping=None, scale=(1.0, 1.0), layer=None, **encode
) -> tuple[np.ndarray, bytes]:
    """The service's path (sessions.process_frame): decode, a stand-in denoiser (colour x 0.5,
    so the output differs from every input layer), encode."""
    header = frames.read_header(data, 8192, 8192)
    sources = frames.resolve(header.channels, REQUIRED, OPTIONAL, mapping, scale, layer=layer)
    decoded = frames.decode(data, sources)
    denoised = decoded.buffers["color"] * np.float32(0.5)  # (3, H, W), the runtime's layout
    precision = "half" if decoded.color_half else "float"
    out = frames.encode(denoised, decoded, sources["color"].channels, precision, **encode)
    return image(denoised), out


def sky_mask(channels: dict[str, np.ndarray], layer: str = "ViewLayer") -> np.ndarray:
    """Pixels whose every sample saw the background (Denoising Depth 0, Depth at 1e10)."""
    depth = channels[f"{layer}.Depth.Z"]
    return (depth == np.float32(BACKGROUND_Z)) & (channels[f"{layer}.Denoising Depth.Z"] == 0)


def mapping_for(layer: str) -> dict:
    return {
        "color": f"{layer}.Combined",
        "albedo": f"{layer}.Denoising Albedo",
        "normal": f"{layer}.Denoising Normal",
        "depth": f"{layer}.Denoising Depth.Z",
        "motion": [f"{layer}.Vector.X", f"{layer}.Vector.Y"],
    }


# ---- what Blender writes (measured facts, kept true by these tests) -------------------------


def test_manifest_lists_every_fixture():
    on_disk = {p.name for p in FIXTURES.glob("*.exr")}
    assert on_disk == {file for _, file in FILES}
    assert MANIFEST["blender"].startswith("4.5") and MANIFEST["resolution"] == [64, 36]
    total = sum(p.stat().st_size for p in FIXTURES.iterdir())
    assert total < 3 * 2**20, f"fixtures grew to {total} bytes"


@pytest.mark.parametrize(("variant", "file"), FILES)
def test_channel_names_pixel_types_and_compression(variant, file):
    import OpenEXR

    v = VARIANTS[variant]
    header = frames.read_header(read(file), 8192, 8192)
    assert (header.width, header.height, header.parts) == (64, 36, 1)
    assert set(header.channels) == expected_channels(variant)
    file_type = HALF if v["depth"] == "16" else FLOAT
    for name, info in header.channels.items():
        colour = "." not in name or name.split(".")[1] in COLOUR_PASSES
        assert info.pixel_type == (file_type if colour else FLOAT), name
    codec = getattr(OpenEXR, f"{v['codec']}_COMPRESSION")
    assert header.attributes["compression"][1] == bytes([int(codec)])


@pytest.mark.parametrize(("variant", "file"), FILES)
def test_header_attributes_blender_writes(variant, file):
    v = VARIANTS[variant]
    attributes = frames.read_header(read(file), 8192, 8192).attributes
    string = {k: value.decode() for k, (kind, value) in attributes.items() if kind == "string"}
    frame = int(file.split(".")[1])
    assert string["Frame"] == str(frame) and string["Camera"] == "camera"
    assert string["Scene"] == "Scene" and string["Time"] == f"00:00:00:{frame:02d}"
    assert {"Date", "File", "RenderTime"} <= set(string) and "xDensity" in attributes
    layers = ["ViewLayer", "Objects"] if v["second_view_layer"] else ["ViewLayer"]
    for layer in layers:
        assert string[f"cycles.{layer}.samples"] == str(v["samples"])
        for timing in ("render_time", "synchronization_time", "total_time"):
            assert f"cycles.{layer}.{timing}" in string
    # Only the multilayer writer marks its files.
    assert ("BlenderMultiChannel" in string) == v["multilayer"]


@pytest.mark.parametrize(
    ("variant", "file"), [f for f in FILES if f[0] not in ("two_view_layers", "plain_rgba")]
)
def test_single_view_layer_files_resolve_and_decode(variant, file):
    v = VARIANTS[variant]
    header, sources, decoded = load(read(file))
    beauty = "Noisy Image" if v["blender_denoiser"] else "Combined"
    assert sources["color"].channels == tuple(f"ViewLayer.{beauty}.{c}" for c in "RGB")
    assert sources["albedo"].channels[0] == "ViewLayer.Denoising Albedo.R"
    assert sources["normal"].channels == tuple(f"ViewLayer.Denoising Normal.{c}" for c in "XYZ")
    assert sources["depth"].channels == ("ViewLayer.Denoising Depth.Z",)
    if v["vector"]:
        assert sources["motion"].channels == ("ViewLayer.Vector.X", "ViewLayer.Vector.Y")
        assert sources["motion"].motion_scale == (1.0, -1.0)
    else:
        assert "motion" not in sources and "motion" not in decoded.buffers
    assert decoded.color_half == (v["depth"] == "16")
    for name, array in decoded.buffers.items():
        assert array.shape[:2] == (36, 64) and array.dtype == np.float32, name
        # depth: +inf where no ray hit (the runtime's sanitising rule makes it the farthest)
        assert (np.isfinite(array) | (name == "depth") & np.isposinf(array)).all(), name
    assert decoded.buffers["color"].max() > 1.0  # HDR: the lamp is well above 1


def test_two_view_layers_are_ambiguous_without_a_mapping():
    header = frames.read_header(read("two_view_layers.0002.exr"), 8192, 8192)
    with pytest.raises(AmbiguousChannels, match="Objects.Combined.R"):
        frames.resolve(header.channels, REQUIRED, OPTIONAL)


def test_two_view_layers_each_decode_with_a_mapping():
    data = read("two_view_layers.0002.exr")
    channels = pixels(data)
    decoded = {}
    for layer in ("ViewLayer", "Objects"):
        _, sources, decoded[layer] = load(data, mapping_for(layer), (1.0, -1.0))
        assert sources["color"].channels[0] == f"{layer}.Combined.R"
    # 'Objects' excludes the floor: more of its frame is background, and its colour differs.
    assert sky_mask(channels, "Objects").sum() > sky_mask(channels).sum() + 200
    assert not np.allclose(
        decoded["Objects"].buffers["color"], decoded["ViewLayer"].buffers["color"]
    )


def test_plain_rgba_is_colour_only():
    data = read("plain_rgba.0002.exr")
    header = frames.read_header(data, 8192, 8192)
    with pytest.raises(MissingChannels) as err:
        frames.resolve(header.channels, REQUIRED, OPTIONAL)
    assert "'albedo'" in err.value.detail and "Denoising Albedo" in err.value.detail
    _, sources, decoded = load(data, required=("color",), optional=())
    assert sources["color"].channels == ("R", "G", "B") and decoded.color_half


def test_background_pixels_what_each_pass_holds():
    """Sky pixels: Denoising Depth 0 (as near as it gets), Depth 1e10, no motion, albedo = the
    world colour, normal 0. Edge pixels can hold Depth 1e10 with Denoising Depth > 0: Depth is
    not a filtered average of the samples, Denoising Depth is."""
    channels = pixels(read("passes_float_zip.0002.exr"))
    sky = sky_mask(channels)
    assert sky.mean() > 0.2  # the top rows
    depth = channels["ViewLayer.Depth.Z"]
    edge = (depth == np.float32(BACKGROUND_Z)) & ~sky
    assert edge.sum() > 10 and (channels["ViewLayer.Denoising Depth.Z"][edge] > 0).all()
    foreground = depth < BACKGROUND_Z
    assert (
        depth[foreground].max() < 30
        and channels["ViewLayer.Denoising Depth.Z"][foreground].min() > 1
    )
    for c in "XYZW":
        assert (channels[f"ViewLayer.Vector.{c}"][sky] == 0).all()  # Cycles: background is static
    for c in "XYZ":
        assert (channels[f"ViewLayer.Denoising Normal.{c}"][sky] == 0).all()
    for c, value in zip("RGB", SKY_RGB, strict=True):
        np.testing.assert_allclose(
            channels[f"ViewLayer.Denoising Albedo.{c}"][sky], value, atol=1e-5
        )
        np.testing.assert_allclose(channels[f"ViewLayer.Combined.{c}"][sky], value, atol=1e-5)


def test_transparent_film_zeroes_alpha_and_albedo_on_the_sky():
    channels = pixels(read("transparent.0002.exr"))
    sky = sky_mask(channels)
    assert sky.mean() > 0.2 and (channels["ViewLayer.Combined.A"][sky] == 0).all()
    assert (channels["ViewLayer.Combined.A"][~sky] > 0).all()
    assert (channels["ViewLayer.Denoising Albedo.G"][sky] == 0).all()


def test_vector_halves_point_to_previous_and_next_frame():
    """XY: towards frame t-1, ZW: towards t+1. The camera is still before frame 1 and after
    frame 3 (constant extrapolation), so XY is zero on frame 1 and ZW zero on frame 3."""
    first, middle, last = (pixels(read(f"passes_float_zip.000{i}.exr")) for i in (1, 2, 3))
    assert np.abs(first["ViewLayer.Vector.X"]).max() == 0
    assert np.abs(first["ViewLayer.Vector.Y"]).max() < 1e-5
    assert (
        np.abs(last["ViewLayer.Vector.Z"]).max() == 0
        and np.abs(last["ViewLayer.Vector.W"]).max() == 0
    )
    fg = middle["ViewLayer.Depth.Z"] < BACKGROUND_Z
    # Constant camera speed: both halves equal in the middle frame (within sub-pixel jitter).
    for back, ahead in (("X", "Z"), ("Y", "W")):
        diff = middle[f"ViewLayer.Vector.{back}"][fg] - middle[f"ViewLayer.Vector.{ahead}"][fg]
        assert np.median(np.abs(diff)) < 0.05


def test_blender_denoiser_keeps_the_raw_beauty_as_noisy_image():
    """Same render as passes_half_piz with the denoiser on: Noisy Image is that Combined bit for
    bit, Combined is the denoised one, every other pass is unchanged."""
    denoised, plain = (
        pixels(read("blender_denoised.0002.exr")),
        pixels(read("passes_half_piz.0002.exr")),
    )
    for c in "RGBA":
        np.testing.assert_array_equal(
            denoised[f"ViewLayer.Noisy Image.{c}"], plain[f"ViewLayer.Combined.{c}"]
        )
    assert np.abs(denoised["ViewLayer.Combined.R"] - plain["ViewLayer.Combined.R"]).mean() > 0.05
    for name in plain:
        if ".Combined." not in name:
            np.testing.assert_array_equal(denoised[name], plain[name], err_msg=name)


def test_denoising_albedo_of_an_emitter_adds_its_emission():
    """The lamp sphere (base colour = emission colour (1, 0.6, 0.2), strength 4): about
    (1 + 4) x the colour, far above 1 (the sanitising rule does not clamp albedo)."""
    channels = pixels(read("passes_float_zip.0002.exr"))
    albedo = np.stack([channels[f"ViewLayer.Denoising Albedo.{c}"] for c in "RGB"], -1)
    lamp = albedo.reshape(-1, 3)[np.argmax(albedo[..., 0])]
    np.testing.assert_allclose(lamp, [5.0, 3.0, 1.0], atol=0.1)  # measured (5.0, 3.03, 1.06)


def test_dwaa_is_lossy_on_channels_named_y_too():
    """DWA compresses channels it takes for colour (R, G, B and luminance Y) lossily, so in a
    DWAA file Vector.Y and Denoising Normal.Y lose precision while X, Z, W stay exact. The
    render is the same as the PIZ variant's (same seed and settings), so PIZ is the reference."""
    dwaa, piz = pixels(read("passes_half_dwaa.0002.exr")), pixels(read("passes_half_piz.0002.exr"))
    for name in ("Vector.X", "Vector.Z", "Vector.W", "Denoising Normal.X", "Depth.Z"):
        np.testing.assert_array_equal(dwaa[f"ViewLayer.{name}"], piz[f"ViewLayer.{name}"])
    for name in ("Vector.Y", "Denoising Normal.Y", "Combined.G"):
        error = np.abs(dwaa[f"ViewLayer.{name}"] - piz[f"ViewLayer.{name}"]).max()
        assert 0 < error < 1.5, name


@pytest.mark.parametrize("file", VARIANTS["motion_blur"]["files"])
def test_motion_blur_writes_an_all_zero_vector(file):
    channels = pixels(read(file))
    assert all((channels[f"ViewLayer.Vector.{c}"] == 0).all() for c in "XYZW")
    # Found, but all zero over the whole frame: left out, so the runtime reports it missing.
    _, sources, decoded = load(read(file))
    assert "motion" in sources and "motion" not in decoded.buffers


# ---- motion sign, checked by warping the rendered frames ------------------------------------


def backward_warp(previous: np.ndarray, motion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """previous sampled at p + motion(p) (bilinear), and where that point lies in the frame."""
    height, width = previous.shape[:2]
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    sx, sy = x + motion[..., 0], y + motion[..., 1]
    inside = (sx >= 0) & (sx <= width - 1) & (sy >= 0) & (sy <= height - 1)
    sx, sy = np.clip(sx, 0, width - 1), np.clip(sy, 0, height - 1)
    x0 = np.minimum(np.floor(sx).astype(int), width - 2)
    y0 = np.minimum(np.floor(sy).astype(int), height - 2)
    fx, fy = (sx - x0)[..., None], (sy - y0)[..., None]
    top = previous[y0, x0] * (1 - fx) + previous[y0, x0 + 1] * fx
    bottom = previous[y0 + 1, x0] * (1 - fx) + previous[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy, inside


@pytest.mark.parametrize("frame", [2, 3])
def test_decoded_motion_warps_previous_frame_onto_this_one(frame):
    """quietframe's convention: pixel p of frame t was at p + motion in frame t-1 (x right,
    y down). Compared on the albedo (nearly noise-free) over surfaces (the sky has no motion in
    Cycles' Vector although the camera turns), the decoded motion must beat no motion and every
    other sign combination by far."""
    previous = load(read(f"passes_float_zip.{frame - 1:04d}.exr"))[2].buffers["albedo"]
    data = read(f"passes_float_zip.{frame:04d}.exr")
    current = load(data)[2]
    albedo, motion = current.buffers["albedo"], current.buffers["motion"]
    candidates = {
        "decoded": motion,
        "zero": np.zeros_like(motion),
        "opposite": -motion,
        "x flipped": motion * [-1, 1],
        "y flipped": motion * [1, -1],
    }
    warped = {name: backward_warp(previous, m) for name, m in candidates.items()}
    mask = pixels(data)["ViewLayer.Depth.Z"] < BACKGROUND_Z
    for _, inside in warped.values():
        mask &= inside
    assert mask.sum() > 800
    error = {name: float(np.abs(w - albedo)[mask].mean()) for name, (w, _) in warped.items()}
    best_other = min(v for k, v in error.items() if k != "decoded")
    assert error["decoded"] < 0.3 * best_other, error


def test_decoded_motion_matches_the_camera_turn():
    """The camera yaws right and pitches up by a fixed step per frame: content moves left and
    down, so p was to the right (+x) and above (-y) in frame t-1, by f * tan(step) pixels."""
    camera = MANIFEST["camera"]
    focal_px = 64 * camera["lens_mm"] / camera["sensor_width_mm"]
    expected_x = focal_px * np.tan(np.radians(-camera["yaw_deg_per_frame"]))
    expected_y = -focal_px * np.tan(np.radians(camera["pitch_deg_per_frame"]))
    data = read("passes_float_zip.0002.exr")
    motion = load(data)[2].buffers["motion"]
    fg = pixels(data)["ViewLayer.Depth.Z"] < BACKGROUND_Z
    np.testing.assert_allclose(np.median(motion[fg][:, 0]), expected_x, rtol=0.1)
    np.testing.assert_allclose(np.median(motion[fg][:, 1]), expected_y, rtol=0.1)


# ---- what comes back -------------------------------------------------------------------------


def test_output_keeps_blenders_header_attributes():
    import OpenEXR

    _, out = roundtrip(read("passes_half_piz.0002.exr"), extra={"quietframe.frame": "2"})
    header, channels = read_back(out)
    assert header["cycles.ViewLayer.samples"] == "4" and header["Frame"] == "2"
    assert header["BlenderMultiChannel"] == "Blender V2.55.1 and newer"
    assert header["quietframe.frame"] == "2"
    assert header["compression"] == OpenEXR.PIZ_COMPRESSION
    assert channels["ViewLayer.Combined.R"].dtype == np.float16
    given = frames.read_header(read("passes_half_piz.0002.exr"), 8192, 8192).attributes
    assert set(given) - {"chunkCount"} <= set(header)


@pytest.mark.parametrize(
    ("file", "layer", "how"),
    [
        ("passes_half_piz.0002.exr", None, None),
        ("passes_float_zip.0002.exr", None, None),
        ("transparent.0002.exr", None, None),
        ("no_vector.0002.exr", None, None),
        ("two_view_layers.0002.exr", "Objects", "mapping"),
        ("two_view_layers.0002.exr", "Objects", "layer"),
        ("two_view_layers.0002.exr", "ViewLayer", "layer"),
    ],
)
def test_output_keeps_every_channel_with_its_pixel_type(file, layer, how):
    data = read(file)
    mapping = mapping_for(layer) if how == "mapping" else None
    denoised, out = roundtrip(data, mapping, (1.0, -1.0), layer if how == "layer" else None)
    given = frames.read_header(data, 8192, 8192).channels
    returned = frames.read_header(out, 8192, 8192).channels
    assert {k: v.pixel_type for k, v in returned.items()} == {
        k: v.pixel_type for k, v in given.items()
    }
    beauty = f"{layer or 'ViewLayer'}.Combined"
    before, after = pixels(data), pixels(out)
    for name in given:
        if name in (f"{beauty}.R", f"{beauty}.G", f"{beauty}.B"):
            continue
        np.testing.assert_array_equal(after[name], before[name], err_msg=name)  # alpha included
    for i, c in enumerate("RGB"):
        np.testing.assert_allclose(after[f"{beauty}.{c}"], denoised[..., i], rtol=1e-3, atol=1e-6)


def test_precision_applies_to_the_denoised_colour_only():
    """A float session on a half file: the denoised R, G, B are float, every other channel
    (alpha and the colour-typed passes included) keeps its own type."""
    data = read("passes_half_piz.0002.exr")  # half colour, float data passes
    given = frames.read_header(data, 8192, 8192).channels
    _, sources, decoded = load(data)
    planes = np.ascontiguousarray(decoded.buffers["color"].transpose(2, 0, 1))
    out = frames.encode(planes, decoded, sources["color"].channels, "float")
    returned = frames.read_header(out, 8192, 8192).channels
    assert given["ViewLayer.Combined.R"].pixel_type == HALF
    for name, info in given.items():
        colour = name in {f"ViewLayer.Combined.{c}" for c in "RGB"}
        assert returned[name].pixel_type == (FLOAT if colour else info.pixel_type), name


def test_noisy_image_comes_back_denoised_as_combined():
    """Blender's denoiser ran: quietframe denoises Noisy Image and writes it as Combined (the
    pass Blender shows); Noisy Image stays as it was, Combined keeps its alpha."""
    data = read("blender_denoised.0002.exr")
    denoised, out = roundtrip(data)
    before, channels = pixels(data), pixels(out)
    assert set(channels) == set(before)
    for i, c in enumerate("RGB"):
        np.testing.assert_allclose(
            channels[f"ViewLayer.Combined.{c}"], denoised[..., i], rtol=1e-3, atol=1e-6
        )
    for name in before:
        if name not in {f"ViewLayer.Combined.{c}" for c in "RGB"}:
            np.testing.assert_array_equal(channels[name], before[name], err_msg=name)


@pytest.mark.parametrize("file", ["blender_denoised.0002.exr", "passes_half_piz.0002.exr"])
def test_denoised_layer_option_keeps_the_noisy_beauty(file):
    data = read(file)
    denoised, out = roundtrip(data, denoised_layer="Denoised")
    before, after = pixels(data), pixels(out)
    added = {f"ViewLayer.Denoised.{c}" for c in "RGB"}
    assert set(after) == set(before) | added
    for name in before:
        np.testing.assert_array_equal(after[name], before[name], err_msg=name)
    for i, c in enumerate("RGB"):
        np.testing.assert_allclose(
            after[f"ViewLayer.Denoised.{c}"], denoised[..., i], rtol=1e-3, atol=1e-6
        )
    types = frames.read_header(out, 8192, 8192).channels
    assert types["ViewLayer.Denoised.R"].pixel_type == types["ViewLayer.Combined.R"].pixel_type


def test_lossy_input_comes_back_lossless_unless_the_session_asks():
    """DWAA damages channels named R, G, B and Y (Vector.Y, Denoising Normal.Y): recompressing
    what passes through would damage them again, so `compression: input` writes a lossy input
    back with ZIP (every passed-through value as decoded); a session that asks for dwaa gets it."""
    import OpenEXR

    data = read("passes_half_dwaa.0002.exr")
    before = pixels(data)
    beauty = {f"ViewLayer.Combined.{c}" for c in "RGB"}
    _, kept = roundtrip(data)
    header, _ = read_back(kept)
    assert header["compression"] == OpenEXR.ZIP_COMPRESSION
    after = pixels(kept)
    for name in set(before) - beauty:
        np.testing.assert_array_equal(after[name], before[name], err_msg=name)
    _, small = roundtrip(data, compression="dwaa")
    header, _ = read_back(small)
    assert header["compression"] == OpenEXR.DWAA_COMPRESSION and len(small) < len(kept)
    lossy = pixels(small)
    np.testing.assert_array_equal(lossy["ViewLayer.Vector.X"], before["ViewLayer.Vector.X"])
    assert not np.array_equal(lossy["ViewLayer.Vector.Y"], before["ViewLayer.Vector.Y"])


def test_depth_on_the_sky_is_farther_than_every_surface():
    """Denoising Depth is 0 on the sky: the runtime's sanitising rule reads it as "no hit" and
    makes it the frame's farthest depth, as for every renderer's background."""
    from quietframe.runtime.sanitize import sanitize_buffer

    data = read("passes_float_zip.0002.exr")
    channels = pixels(data)
    depth = load(data)[2].buffers["depth"]
    sky, surfaces = sky_mask(channels), channels["ViewLayer.Depth.Z"] < BACKGROUND_Z
    clean, replaced = sanitize_buffer("depth", depth[None])
    assert clean[0][sky].min() >= clean[0][surfaces].max()  # as far as the farthest surface
    assert clean[0][sky].min() > np.median(clean[0][surfaces])
    misses = channels["ViewLayer.Denoising Depth.Z"] == 0
    assert replaced == misses.sum() >= sky.sum()
    assert (clean[0][misses] == clean[0][~misses].max()).all()
    np.testing.assert_array_equal(clean[0][surfaces], depth[surfaces])  # ray distances kept


def test_depth_pass_background_is_no_hit_too():
    """Blender's Depth pass (planar Z, 1e10 on the sky) when it is the depth used."""
    data = read("passes_float_zip.0002.exr")
    mapping = {"depth": "ViewLayer.Depth.Z"}
    from quietframe.runtime.sanitize import sanitize_buffer

    depth = load(data, mapping)[2].buffers["depth"]
    background = pixels(data)["ViewLayer.Depth.Z"] >= BACKGROUND_Z
    clean, replaced = sanitize_buffer("depth", depth[None])
    assert replaced == background.sum() > 0
    assert (clean[0][background] == depth[~background].max()).all()
    np.testing.assert_array_equal(clean[0][~background], depth[~background])


def test_all_zero_vector_is_reported_missing():
    _, sources, decoded = load(read("motion_blur.0002.exr"))
    # Left out of the buffers, the runtime fills it and X-Quietframe-Missing names it.
    assert "motion" not in decoded.buffers
    # A moving camera: Vector is 0 on the sky only, and the motion is kept.
    _, _, moving = load(read("passes_float_zip.0002.exr"))
    assert "motion" in moving.buffers and (moving.buffers["motion"] == 0).any()


def test_colour_only_file_is_told_which_model_accepts_it():
    header = frames.read_header(read("plain_rgba.0002.exr"), 8192, 8192)
    with pytest.raises(MissingChannels) as err:
        frames.resolve(header.channels, REQUIRED, OPTIONAL)
    assert re.search(r"colou?r[- ]only", err.value.detail)
    installed = {"nbg": (REQUIRED, OPTIONAL)}
    with pytest.raises(MissingChannels) as err:
        frames.resolve(header.channels, REQUIRED, OPTIONAL, model="nbg", installed=installed)
    detail = err.value.detail
    assert "No installed model accepts colour-only input" in detail
    assert "'albedo', 'normal', 'depth'" in detail and "--channels" in detail
    installed["colour"] = (("color",), ())
    with pytest.raises(MissingChannels, match=r"accept the buffers found: \['colour'\]"):
        frames.resolve(header.channels, REQUIRED, OPTIONAL, model="nbg", installed=installed)


def test_view_layer_restricts_the_alias_table():
    header = frames.read_header(read("two_view_layers.0002.exr"), 8192, 8192)
    for layer in ("ViewLayer", "Objects"):
        sources = frames.resolve(header.channels, REQUIRED, OPTIONAL, layer=layer)
        assert all(c.startswith(layer + ".") for s in sources.values() for c in s.channels)
        assert sources["motion"].motion_scale == (1.0, -1.0)  # the alias, not a mapping
    with pytest.raises(MissingChannels, match=r"view layers are \['Objects', 'ViewLayer'\]"):
        frames.resolve(header.channels, REQUIRED, OPTIONAL, layer="Nope")


def test_cli_takes_a_view_layer_and_a_channel_mapping(tmp_path):
    from quietframe.client.cli import build_parser, session_options

    mapping = tmp_path / "map.json"
    mapping.write_text('{"albedo": "alb"}')
    argv = ["denoise", "shot/", "--out", "out/", "--layer", "Objects", "--channels", "{}"]
    args = build_parser().parse_args(argv)
    assert args.layer == "Objects" and session_options(args)["channels"] is None
    args = build_parser().parse_args([*argv[:-1], f"@{mapping}", "--quality", "fast"])
    assert session_options(args)["channels"] == {"albedo": "alb"}
    assert session_options(args)["quality"] == "fast"


# ---- Blender reads quietframe's output (needs bpy; the fixtures above do not) ----------------


_PASSES_IN_BLENDER = """
import json, sys
import bpy
path, layers = sys.argv[1], sys.argv[2:]
scene = bpy.context.scene
scene.use_nodes = True
image = bpy.data.images.load(path, check_existing=False)
image.reload()
node = scene.node_tree.nodes.new("CompositorNodeImage")
node.image = image
found = {}
for layer in layers:
    try:
        node.layer = layer
    except TypeError:  # not one of the image's view layers
        continue
    found[layer] = [o.name for o in node.outputs if o.enabled]
print("@@" + json.dumps(found))
"""


def blender_passes(path: Path, layers: list[str]) -> dict[str, list[str]]:
    """View layer -> pass names, as Blender's compositor Image node lists them for the file
    (the way a compositor artist sees it); a layer Blender does not find is left out. Runs in
    the Cycles venv (tests/cycles_support.py)."""
    return blender_json(_PASSES_IN_BLENDER, str(path), *layers)


def test_blender_reads_quietframe_output(tmp_path):
    """Blender finds in the output every pass it wrote (the Image node always offers an Alpha
    socket, whether or not the file has alpha)."""
    require_cycles()
    given = tmp_path / "given.exr"
    given.write_bytes(read("passes_half_piz.0002.exr"))
    _, out = roundtrip(given.read_bytes())
    returned = tmp_path / "returned.exr"
    returned.write_bytes(out)
    passes = [
        "Combined",
        "Alpha",
        "Depth",
        "Vector",
        "Denoising Albedo",
        "Denoising Depth",
        "Denoising Normal",
    ]
    assert blender_passes(given, ["ViewLayer"]) == {"ViewLayer": passes}
    assert blender_passes(returned, ["ViewLayer"]) == {"ViewLayer": passes}


@pytest.mark.parametrize(
    ("file", "layer"),
    [
        ("passes_half_piz.0002.exr", None),
        ("blender_denoised.0002.exr", None),
        ("two_view_layers.0002.exr", "Objects"),
    ],
)
def test_blender_finds_every_pass_of_the_input_in_the_output(tmp_path, file, layer):
    require_cycles()
    given = tmp_path / "given.exr"
    given.write_bytes(read(file))
    _, out = roundtrip(given.read_bytes(), mapping_for(layer) if layer else None, (1.0, -1.0))
    returned = tmp_path / "returned.exr"
    returned.write_bytes(out)
    layers = ["ViewLayer", "Objects"]
    assert blender_passes(returned, layers) == blender_passes(given, layers)


def test_blender_finds_the_denoised_layer(tmp_path):
    require_cycles()
    _, out = roundtrip(read("passes_half_piz.0002.exr"), denoised_layer="Denoised")
    returned = tmp_path / "returned.exr"
    returned.write_bytes(out)
    assert "Denoised" in blender_passes(returned, ["ViewLayer"])["ViewLayer"]
