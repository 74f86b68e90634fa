"""Property tests (hypothesis) of the one sanitising rule and of the runtime's finiteness on
extreme inputs: whatever float32 values come in, what reaches a model is finite and within the
rule's range, and nothing non-finite comes out, in float or half. Bounded example counts."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from quietframe.runtime.buffers import BUFFERS, Rule
from quietframe.runtime.sanitize import MAX_VALUE, clamp_to_half, sanitize_buffer

EXTREMES = [0.0, -0.0, 1e-45, 1e-38, 0.5, 1.0, -1.0, 65504.0, 65520.0, 1e5, 1e30, -1e30,
            3.4e38, -3.4e38, np.inf, -np.inf, np.nan]
values = st.one_of(st.floats(width=32), st.sampled_from(EXTREMES))


def planes(channels: int, size: int = 6):
    return hnp.arrays(np.float32, (channels, size, size), elements=values)


@settings(max_examples=150, deadline=None)
@given(name=st.sampled_from(sorted(BUFFERS)), data=st.data())
def test_rule_output_is_finite_bounded_and_counted(name, data):
    raw = data.draw(planes(BUFFERS[name].channels))
    before = raw.copy()
    clean, count = sanitize_buffer(name, raw)
    np.testing.assert_array_equal(raw, before)  # the caller's array is untouched
    assert clean.dtype == np.float32 and np.isfinite(clean).all()
    changed = ~((clean == raw) | (np.isnan(clean) & np.isnan(raw)))
    assert count == int(np.count_nonzero(changed))
    rule = BUFFERS[name].rule
    if rule is Rule.RADIANCE:
        assert clean.min() >= 0 and clean.max() <= MAX_VALUE
    if rule is Rule.DISTANCE:
        assert clean.min() >= 0
    assert sanitize_buffer(name, clean)[1] == 0  # idempotent


@settings(max_examples=100, deadline=None)
@given(raw=hnp.arrays(np.float32, (3, 5, 5), elements=st.floats(width=32, allow_nan=False)))
def test_half_clamp_never_makes_inf(raw):
    clamped, count = clamp_to_half(raw)
    half = clamped.astype(np.float16)
    assert np.isfinite(half[np.isfinite(raw)]).all()
    assert count == int(np.count_nonzero(np.abs(raw) > 65504))


@pytest.fixture(scope="module")
def denoiser():
    from quietframe.runtime import Denoiser, default_model_path

    return Denoiser(default_model_path(), threads=1)


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.data())
def test_runtime_is_finite_on_extreme_values(denoiser, data):
    """Two frames with history, any values in any buffer: finite output and state, finite in
    half after the clamp."""
    size = 16
    state = None
    for _ in range(2):
        buffers = {
            name: data.draw(planes(BUFFERS[name].channels, size))
            for name in (*denoiser.info.required_buffers, *denoiser.info.optional_buffers)
        }
        result = denoiser.denoise(buffers, state)
        assert np.isfinite(result.color).all()
        assert all(np.isfinite(s).all() for s in result.state.values())
        assert np.isfinite(clamp_to_half(result.color)[0].astype(np.float16)).all()
        state = result.state
