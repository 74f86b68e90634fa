"""Motion estimated from the aux (runtime/aux_motion.py): it finds known shifts of real Cycles
aux, the motion of a real motion-blurred pan whose renderer wrote no vectors, zero on a
locked-off shot, and marks what it cannot trust so that no history is read there; a camera
switch along the estimate is a cut."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from quietframe.runtime import aux_motion as am
from quietframe.runtime.motion_evidence import PROBE_STATE, probe

SEQUENCES = Path(__file__).resolve().parents[1] / "fixtures" / "blender_sequences"
PAN_PX = 3.0  # the fixtures' pan, pixels a frame (manifest.json)


def aux(name: str, t: int) -> dict[str, np.ndarray]:
    """(C, H, W) planes of a fixture frame: colour, albedo, normal."""
    import OpenEXR

    with OpenEXR.File(str(SEQUENCES / f"{name}.{t:04d}.exr")) as f:
        channels = f.channels()

        def plane(layer: str, n: int = 3) -> np.ndarray:
            return np.asarray(channels[f"ViewLayer.{layer}"].pixels, np.float32
                              ).transpose(2, 0, 1)[:n]

        normal = np.stack([np.asarray(channels[f"ViewLayer.Denoising Normal.{c}"].pixels,
                                      np.float32) for c in "XYZ"])
        return {"color": plane("Combined"), "albedo": plane("Denoising Albedo"),
                "normal": normal}


@pytest.mark.parametrize("shift", [(0.5, 0.0), (1.5, 0.3), (-2.2, 1.0)])
def test_a_known_shift_of_real_aux_is_found_to_a_tenth_of_a_pixel(shift):
    previous = probe(aux("locked_off", 3))
    flow = np.zeros((2, *previous.shape[1:]), np.float32)
    flow[0], flow[1] = shift
    current = am.warp(previous, flow)  # current(p) = previous(p + shift): backward motion
    found = am.probe_flow(previous, current)[:, 4:-4, 4:-4]  # away from the clamped border
    np.testing.assert_allclose(np.median(found, axis=(1, 2)), shift, atol=0.1)


def test_a_motion_blurred_pan_without_vectors_moves_three_pixels_a_frame():
    for t in range(2, 7):
        previous, current = probe(aux("motion_blur", t - 1)), probe(aux("motion_blur", t))
        estimated = am.estimate(previous, current, 72, 128)
        assert estimated.share > 0.75, (t, estimated.share)
        vx, vy = np.median(estimated.motion[:, estimated.trusted], axis=1)
        assert abs(abs(vx) - PAN_PX) < 0.2 and abs(vy) < 0.2, (t, vx, vy)


def test_a_locked_off_shot_stays_put():
    for t in range(2, 7):
        estimated = am.estimate(probe(aux("locked_off", t - 1)), probe(aux("locked_off", t)),
                                72, 128)
        assert estimated.share > 0.9
        assert np.abs(np.median(estimated.motion[:, estimated.trusted], axis=1)).max() < 0.1


def test_untrusted_pixels_point_outside_the_frame_and_trusted_ones_inside():
    previous, current = probe(aux("motion_blur", 2)), probe(aux("motion_blur", 3))
    current[:, 10:20, 20:40] = 0.5  # a patch the previous frame never showed
    estimated = am.estimate(previous, current, 72, 128)
    assert not estimated.trusted[22:38, 42:78].any()
    outside = estimated.motion[0][~estimated.trusted] + np.arange(128)[None].repeat(72, 0)[
        ~estimated.trusted]
    assert (outside > 127).all()
    np.testing.assert_array_equal(estimated.motion[:, estimated.trusted],
                                  estimated.estimate[:, estimated.trusted])


def test_the_stream_follows_the_estimate_and_starts_afresh_at_a_switch_of_camera():
    """Through runtime.Stream (a stand-in denoiser: the gate and the estimate are the stream's):
    a moving frame without vectors keeps its history along the estimate; a frame whose aux
    changed everywhere along it (the same set seen upside down) is a cut."""
    from quietframe.runtime.stream import Stream

    class StandIn:
        prepass = None

        class info:  # noqa: N801 - the ModelInfo fields the stream reads
            state_specs = ("accumulation",)
            inputs = ()

        def denoise(self, planes, state, options, renderer, oidn=None):
            from quietframe.runtime.denoiser import DenoiseResult

            self.seen = (planes.get("motion"), state)
            return DenoiseResult(color=planes["color"], state={"accumulation": planes["color"]},
                                 sanitized={}, missing=())

    model = StandIn()
    stream = Stream(model)  # type: ignore[arg-type]
    first = stream.step(aux("motion_blur", 1), None)
    second = stream.step(aux("motion_blur", 2), first.state)
    motion, history = model.seen
    assert second.estimated is not None and second.history_verdict is None
    assert history is not None and PROBE_STATE not in history
    np.testing.assert_array_equal(motion, second.estimated.motion)
    flipped = {k: np.ascontiguousarray(v[:, ::-1, ::-1]) for k, v in aux("motion_blur", 3).items()}
    third = stream.step(flipped, second.state)
    assert third.history_verdict == "cut" and third.estimated is None
    assert model.seen[1] is None
    off = Stream(model, motion="rendered-only")  # type: ignore[arg-type]
    dropped = off.step(aux("motion_blur", 2), first.state)
    assert dropped.history_verdict == "moving" and dropped.estimated is None
