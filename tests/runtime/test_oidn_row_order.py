"""OIDN sees a Cycles frame's rows bottom-up, as Blender's own denoise does: checked on a file
Cycles wrote with its denoiser on (`Noisy Image` beside the denoised `Combined`)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest

from quietframe.model import metrics
from quietframe.runtime import Denoiser
from quietframe.runtime.oidn_prepass import OIDNPrepass, OIDNSettings, rows_bottom_up

pytest.importorskip("pyoidn")
OpenEXR = pytest.importorskip("OpenEXR")

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "blender" / "blender_denoised.0002.exr"
MODELS = Path(__file__).resolve().parents[2] / "models"
LAYER = "ViewLayer."


def passes(data: bytes | Path) -> dict[str, np.ndarray]:
    """(3, H, W) float32 planes of a Cycles file: the runtime's buffers and Blender's own
    `Combined`."""
    source = str(data) if isinstance(data, Path) else io.BytesIO(data)
    exr = OpenEXR.File(source, separate_channels=True)
    ch = exr.channels()

    def plane(name: str, comps: str) -> np.ndarray:
        return np.stack([ch[f"{LAYER}{name}.{c}"].pixels for c in comps]).astype(np.float32)

    return {"color": plane("Noisy Image", "RGB"), "albedo": plane("Denoising Albedo", "RGB"),
            "normal": plane("Denoising Normal", "XYZ"), "depth": plane("Depth", "Z"),
            "blender": plane("Combined", "RGB")}


def psnr_to(planes: np.ndarray, target: np.ndarray) -> float:
    """Tone-mapped PSNR of (3, H, W) planes, rounded to half as Blender stores its output."""
    half = planes.astype(np.float16).astype(np.float32)
    return metrics.psnr(half.transpose(1, 2, 0), target.transpose(1, 2, 0))


def test_only_cycles_frames_are_given_bottom_up():
    assert rows_bottom_up("cycles")
    assert not rows_bottom_up(None) and not rows_bottom_up("mitsuba")


def test_bottom_up_stage_is_blenders_denoise_and_top_down_is_not():
    """Blender's prefilter Accurate and quality High: both aux images denoised at high, then
    the main filter with cleanAux. Only the row order separates the two results."""
    frame = passes(FIXTURE)
    stage = OIDNPrepass(OIDNSettings("high", True), num_threads=1)
    try:
        planes = {k: frame[k] for k in ("color", "albedo", "normal")}
        bottom_up = stage(planes, "cycles")[0]
        top_down = stage(planes)[0]
        flipped = stage({k: v[:, ::-1] for k, v in planes.items()})[0][:, ::-1]
    finally:
        stage.close()
    np.testing.assert_array_equal(bottom_up, flipped)  # the same calls on reversed rows
    assert psnr_to(bottom_up, frame["blender"]) > 80  # 85.8 measured: half rounding alone
    assert psnr_to(top_down, frame["blender"]) < 50  # 44.5 measured


def test_service_gives_oidn_the_rows_its_header_names(live_server):
    """The header's `cycles.<layer>.samples` names the renderer: the served frame is the
    runtime's bottom-up result, not its top-down one."""
    from quietframe.client import Client

    frame = passes(FIXTURE)
    model = "oidn-history-cleanaux"
    with Client(live_server.url) as client:
        created = client.create_session(64, 36, model=model)
        try:
            result = client.send_frame(created["id"], 0, FIXTURE.read_bytes())
        finally:
            client.delete_session(created["id"])
    served = passes(result.exr)["blender"]  # the service writes its output into Combined
    runtime = Denoiser(MODELS / f"{model}.onnx", threads=1)
    planes = {k: frame[k] for k in ("color", "albedo", "normal", "depth")}
    expected = {r: runtime.denoise(planes, None, renderer=r).color for r in (None, "cycles")}
    half = {r: c.astype(np.float16).astype(np.float32) for r, c in expected.items()}
    np.testing.assert_allclose(served, half["cycles"], rtol=2e-3, atol=1e-4)
    assert np.abs(served - half[None]).max() > 0.01
