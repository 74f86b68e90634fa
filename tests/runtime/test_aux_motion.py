"""Motion estimated from the aux (runtime/aux_motion.py): it finds a known camera move of real
Cycles aux, the motion of a real motion-blurred pan whose renderer wrote no vectors, zero on a
locked-off shot, and marks what it cannot trust so that no history is read there; a camera
switch along the estimate is a cut, and a frame without depth gets no estimate."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from quietframe.runtime import aux_motion as am
from quietframe.runtime.motion_evidence import DEPTH_STATE, PROBE_STATE, probe

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
        depth = np.asarray(channels["ViewLayer.Denoising Depth.Z"].pixels, np.float32)[None]
        return {"color": plane("Combined"), "albedo": plane("Denoising Albedo"),
                "normal": normal, "depth": depth}


@pytest.mark.parametrize("params", [(0.0, 0.004, 0.0, 0.0, 0.0, 0.0),
                                    (0.0, 0.0, 0.0, 0.02, 0.0, -0.05),
                                    (0.002, -0.003, 0.001, 0.0, 0.01, 0.03)])
def test_a_known_camera_move_of_real_aux_is_found_to_a_tenth_of_a_pixel(params):
    """The previous frame's probe carried by a known rotation and translation (its own depth)
    is the current one: the fitted field matches the true one where it is trusted."""
    planes = aux("locked_off", 3)
    previous = probe(planes)
    _, h, w = planes["color"].shape
    focal = w / (2 * np.tan(np.radians(am.FOV_DEG) / 2))
    depth = am._ray_depth(planes["depth"])
    probe_depth = 1 / am._box(1 / depth[None], 2)[0]
    truth = am.motion_field(np.array(params), probe_depth, focal / 2)
    current, _ = am.warp(previous, truth)  # current(p) = previous(p + m): backward motion m
    estimated = am.estimate(previous, current, h, w, planes["depth"])
    full_truth = am.motion_field(np.array(params), depth, focal)
    error = np.hypot(*(estimated.estimate - full_truth))[estimated.trusted]
    assert estimated.share > 0.8 and np.median(error) < 0.1, (estimated.share, np.median(error))


def test_a_surface_the_previous_frame_saw_behind_something_nearer_is_not_trusted():
    """The forward-backward check: the previous frame's depth says a patch was nearer there (a
    post the camera trucked past), which the aux alone cannot show (they are the same on both
    sides here): the pixels fetched from it are untrusted, the rest keep their trust."""
    planes = aux("locked_off", 3)
    previous = probe(planes)
    _, h, w = planes["color"].shape
    focal = w / (2 * np.tan(np.radians(am.FOV_DEG) / 2))
    params = np.array((0.0, 0.0, 0.0, 0.02, 0.0, -0.05))
    inverse = am.depth_probe(planes["depth"])
    truth = am.motion_field(params, 1 / inverse[0], focal / 2)
    current, _ = am.warp(previous, truth)
    same = am.estimate(previous, current, h, w, planes["depth"], inverse)
    aux_only = am.estimate(previous, current, h, w, planes["depth"])
    assert same.share > 0.8 and same.share > aux_only.share - 0.05, (same.share, aux_only.share)
    nearer = inverse.copy()
    nearer[:, 12:24, 20:44] *= 5.0  # the previous frame saw something 5x nearer here
    occluded = am.estimate(previous, current, h, w, planes["depth"], nearer)
    fetched_from = np.zeros((h, w), bool)
    ys, xs = np.mgrid[0:h, 0:w]
    x, y = xs + same.estimate[0], ys + same.estimate[1]
    fetched_from[(x >= 44) & (x < 84) & (y >= 28) & (y < 44)] = True  # well inside the patch
    assert fetched_from.sum() > 200
    assert not occluded.trusted[fetched_from].any()
    away = same.trusted & ~np.isin(np.arange(h), range(16, 56))[:, None]
    assert occluded.trusted[away].mean() > 0.95


def test_a_motion_blurred_pan_without_vectors_moves_three_pixels_a_frame():
    for t in range(2, 7):
        previous, current = probe(aux("motion_blur", t - 1)), probe(aux("motion_blur", t))
        estimated = am.estimate(previous, current, 72, 128, aux("motion_blur", t)["depth"])
        assert estimated.share > 0.75, (t, estimated.share)
        vx, vy = np.median(estimated.motion[:, estimated.trusted], axis=1)
        # a pan about the vertical axis, keyed at 3 px a frame: sideways, ~0 vertically (no
        # vectors to compare with under motion blur: the zoo's twin shots measure the error)
        assert abs(abs(vx) - PAN_PX) < 0.5 and abs(vy) < 0.25, (t, vx, vy)


def test_a_locked_off_shot_stays_put():
    for t in range(2, 7):
        estimated = am.estimate(probe(aux("locked_off", t - 1)), probe(aux("locked_off", t)),
                                72, 128, aux("locked_off", t)["depth"])
        assert estimated.share > 0.9
        assert np.abs(np.median(estimated.motion[:, estimated.trusted], axis=1)).max() < 0.1


def test_untrusted_pixels_point_outside_the_frame_and_trusted_ones_inside():
    previous, current = probe(aux("motion_blur", 2)), probe(aux("motion_blur", 3))
    current[:, 10:20, 20:40] = 0.5  # a patch the previous frame never showed
    estimated = am.estimate(previous, current, 72, 128, aux("motion_blur", 3)["depth"])
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
    assert history is not None and PROBE_STATE not in history and DEPTH_STATE not in history
    # each frame without vectors keeps its depth for the next frame's forward-backward check
    assert first.state[DEPTH_STATE].shape == (1, 36, 64) and DEPTH_STATE in second.state
    np.testing.assert_array_equal(motion, second.estimated.motion)
    flipped = {k: np.ascontiguousarray(v[:, ::-1, ::-1]) for k, v in aux("motion_blur", 3).items()}
    third = stream.step(flipped, second.state)
    assert third.history_verdict == "cut" and third.estimated is None
    assert model.seen[1] is None
    off = Stream(model, motion="rendered-only")  # type: ignore[arg-type]
    dropped = off.step(aux("motion_blur", 2), first.state)
    assert dropped.history_verdict == "moving" and dropped.estimated is None
    no_depth = {k: v for k, v in aux("motion_blur", 2).items() if k != "depth"}
    assert am.estimate(first.state[PROBE_STATE], probe(no_depth), 72, 128, None) is None
    without = stream.step(no_depth, first.state)  # nothing to estimate with: a fresh history
    assert without.history_verdict == "moving" and without.estimated is None
