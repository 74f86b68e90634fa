"""A frame's memory reservation covers what its path really holds: peak RSS of decode, denoise
and encode (service.sessions.process_frame) against admission.frame_need, each case in a
process of its own (bench/admission_memory.py measures it). In the suite: an OIDN stage
(filters and scratch) at 720p, which the reservation once left out. The whole matrix, every
installed model at 1080p and 4K, is ~40 CPU-minutes:
QUIETFRAME_MEMORY_MATRIX=1 runs it here (or `python -m quietframe.bench.admission_memory`)."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from quietframe.bench.admission_memory import TARGET_RATIO, shipped_models


def measured(model: str, size: str, frames: int = 1) -> dict:
    child = subprocess.run(
        [sys.executable, "-m", "quietframe.bench.admission_memory", "--one", model, size,
         "--frames", str(frames), "--threads", "2"],
        capture_output=True, text=True, check=True, timeout=1800)
    return json.loads(child.stdout.strip().splitlines()[-1])


def check_within_reservation(result: dict) -> None:
    for row in result["frames"]:
        bound = TARGET_RATIO * (row["reserved_mib"] + row["history_mib"])
        assert row["peak_growth_mib"] <= bound, (result["model"], result["size"], row)


def test_oidn_stage_memory_is_reserved_and_released_after_the_frame():
    result = measured("oidn-frame", "720p")
    check_within_reservation(result)
    for row in result["frames"]:
        # OIDN's filters and scratch (~0.5 GiB at 720p) do not outlive the frame (kept per
        # worker thread they were ~0.9 of the peak): what stays is the allocator's slack.
        assert row["kept_mib"] < 0.4 * row["peak_growth_mib"], row


@pytest.mark.skipif(os.environ.get("QUIETFRAME_MEMORY_MATRIX") != "1",
                    reason="~40 CPU-minutes: QUIETFRAME_MEMORY_MATRIX=1 runs it")
@pytest.mark.parametrize("size", ["1080p", "4k"])
@pytest.mark.parametrize("model", shipped_models())
def test_every_model_stays_within_its_reservation(model: str, size: str):
    check_within_reservation(measured(model, size, frames=2))  # the second reads a history


def test_an_auto_session_reserves_for_the_model_it_chose():
    """Once `auto` has chosen, a 4K frame reserves for that model (oidn-history here), not the
    largest installed one; a frame that may choose again (a cut) reserves for any."""
    import numpy as np
    from conftest import write_exr
    from test_service_reliability import app_client, new_session

    from quietframe.service import admission, frames
    from quietframe.service.choice_policy import Choice

    width, height = 3840, 2160
    plane = np.zeros((height, width), np.float16)
    body = write_exr({f"{p}.{c}": plane for p in ("albedo", "normal") for c in "RGB"}
                     | {c: plane for c in "RGB"}, dtype=np.float16)
    with app_client() as c:
        sid = new_session(c, model="auto", width=width, height=height)
        registry = c.app.state.sessions
        session = registry.sessions[sid]
        header = frames.read_header(body, width, height, len(body))
        every = admission.frame_need(header, len(body),
                                     [registry.models.denoiser(n) for n in registry.models.names])
        assert registry.frame_need(session, header, len(body)) == every  # first frame
        session.choice = Choice("oidn-history", "test", 4.0, "header", ("color",))
        session.last_index = 0
        chosen = admission.frame_need(header, len(body),
                                      [registry.models.denoiser("oidn-history")])
        assert registry.frame_need(session, header, len(body)) == chosen < every
        assert registry.frame_need(session, header, len(body), cut=True) == every


def _multipart_exr(parts: int) -> bytes:
    """A valid EXR of `parts` parts, each one 64x48 half channel (the 2026-12-06 audit's R4-14)."""
    import tempfile

    import OpenEXR

    with tempfile.TemporaryDirectory() as tmp:
        path = f"{tmp}/parts.exr"
        OpenEXR.File([OpenEXR.Part({"compression": OpenEXR.ZIP_COMPRESSION,
                                    "type": OpenEXR.scanlineimage},
                                   {f"p{k}.R": np.zeros((48, 64), np.float16)}, name=f"p{k}")
                      for k in range(parts)]).write(path)
        with open(path, "rb") as f:
            return f.read()


def test_a_header_of_too_many_parts_is_refused_and_each_part_is_charged():
    from quietframe.runtime.exr_header import MAX_PARTS, read_header
    from quietframe.runtime.frame_errors import UnsupportedExr
    from quietframe.service.admission import PART_OVERHEAD_BYTES, frame_need

    few, many = _multipart_exr(4), _multipart_exr(MAX_PARTS + 1)
    with pytest.raises(UnsupportedExr, match=f"over {MAX_PARTS} parts"):
        read_header(many, max_width=64, max_height=48)
    header = read_header(few, max_width=64, max_height=48)
    assert header.parts == 4
    from quietframe.runtime import Denoiser, find_model

    models = [Denoiser(find_model("nbg-2l-3g"), threads=1)]
    one = dataclasses.replace(header, parts=1)
    assert (frame_need(header, len(few), models) - frame_need(one, len(few), models)
            == 3 * PART_OVERHEAD_BYTES)
