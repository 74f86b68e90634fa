"""Does a frame's memory reservation cover what the frame really holds? Peak RSS of the service's
frame path against the admission's reservation, per model and frame size.

    python -m quietframe.bench.admission_memory [--models oidn-frame ...] [--sizes 1080p 4k]
        [--frames 2] [--threads 2]

Each (model, size) runs in its own process, so its peak RSS (VmHWM) is that frame path's alone:
a Cycles-style multi-layer EXR (half-float Combined, Noisy Image and albedo; float normal,
depth and Vector; ZIP) read from disk into the body, `admission.frame_need` from its header
(what the service reserves before the body buffer exists), then `frame_path.process_frame`
(decode, denoise, encode) `frames` times with the history carried. Memory the session keeps
between frames is the history budget's, not the frame's: the comparison is

    peak RSS growth  vs  reservation + the history the frame reads

and the target is growth <= 1.1 x that (docs/reliability.md). Prints a Markdown table and, with
--json, the rows.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from quietframe.bench import cli_args
from quietframe.bench.large_frames import SIZES, buffers
from quietframe.runtime import Denoiser, find_model, installed_models
from quietframe.runtime.motion_evidence import history_nbytes
from quietframe.runtime.stream import Stream
from quietframe.service import admission
from quietframe.service import frames as frame_io
from quietframe.service.frame_context import frame_context
from quietframe.service.frame_path import process_frame
from quietframe.service.session_spec import SessionSpec
from quietframe.service.settings import Settings
from quietframe.wire.protocol import Reset

TARGET_RATIO = 1.1
MIB = 2**20


def cycles_channels(planes: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The channels Blender's Cycles writes for a denoising-data view layer, as (H, W) arrays."""
    layer = "ViewLayer."
    out: dict[str, np.ndarray] = {}
    alpha = np.ones(planes["color"].shape[1:], np.float16)
    for pass_name in ("Combined", "Noisy Image"):
        for i, c in enumerate("RGB"):
            out[f"{layer}{pass_name}.{c}"] = planes["color"][i].astype(np.float16)
        out[f"{layer}{pass_name}.A"] = alpha
    for i, c in enumerate("RGB"):
        out[f"{layer}Denoising Albedo.{c}"] = planes["albedo"][i].astype(np.float16)
    for i, c in enumerate("XYZ"):
        out[f"{layer}Denoising Normal.{c}"] = planes["normal"][i]
    out[f"{layer}Depth.Z"] = planes["depth"][0]
    for i, c in enumerate("XYZW"):  # Cycles' Vector: backward X, Y, forward Z, W (pixels)
        out[f"{layer}Vector.{c}"] = planes["motion"][i % 2] * (1 if i < 2 else -1)
    return out


def write_frame(path: Path, width: int, height: int, seed: int) -> None:
    import OpenEXR

    channels = cycles_channels(buffers(width, height, seed))
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, channels).write(str(path))


def _status_bytes(field: str) -> int:
    with open("/proc/self/status") as f:
        line = next(line for line in f if line.startswith(field + ":"))
    return int(line.split()[1]) * 1024


def measure(model: str, width: int, height: int, frames: int, threads: int) -> dict:
    """One process's measurement (run by `main` in a child process)."""
    settings = Settings()
    denoiser = Denoiser(find_model(model), threads=threads)
    spec = SessionSpec(model=model, width=width, height=height, precision="input",
                       compression="input", channels=None, motion_scale=(1.0, 1.0))
    info = denoiser.info
    stream = Stream(denoiser)  # the session's: its OIDN filters are kept between frames
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        files = [Path(tmp) / f"frame_{i}.exr" for i in range(frames)]
        for i, path in enumerate(files):
            write_frame(path, width, height, seed=i)
        state = None
        for i, path in enumerate(files):
            # what the session holds between frames (the history budget): state, kept filters
            held = stream.kept_bytes + (0 if state is None
                                        else sum(v.nbytes for v in state.values()))
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")  # VmHWM := VmRSS
            base = _status_bytes("VmRSS")
            body = path.read_bytes()
            header = frame_io.read_header(body, settings.max_width, settings.max_height,
                                          settings.max_header_bytes)
            need = admission.frame_need(header, len(body), [denoiser])
            context = frame_context(header, spec, info, None)
            start = time.perf_counter()
            done = process_frame(stream, spec, i, body, context,
                                 Reset.FIRST_FRAME if state is None else Reset.NONE, state)
            seconds = time.perf_counter() - start
            peak = _status_bytes("VmHWM") - base
            state = done.state
            del body, done
            # What the frame left behind beyond the state it returned (allocator and arenas)
            kept = (_status_bytes("VmRSS") - base - sum(v.nbytes for v in state.values())
                    - stream.kept_bytes + held)
            rows.append({"frame": i, "seconds": round(seconds, 2), "peak_growth_mib":
                         round(peak / MIB), "kept_mib": round(kept / MIB),
                         "reserved_mib": round(need / MIB),
                         "history_mib": round(held / MIB),
                         "state_mib": round(history_nbytes(info.state_specs, height, width) / MIB)})
    worst = max(rows, key=lambda r: r["peak_growth_mib"] / (r["reserved_mib"] + r["history_mib"]))
    return {"model": model, "size": f"{width}x{height}", "frames": rows,
            "ratio": round(worst["peak_growth_mib"] / (worst["reserved_mib"]
                                                       + worst["history_mib"]), 3)}


def shipped_models() -> list[str]:
    """Every installed model (all of them are served)."""
    return [path.stem for path in installed_models()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--models", nargs="*", help="default: every shipped model")
    parser.add_argument("--sizes", nargs="*", default=["1080p", "4k"], choices=SIZES)
    parser.add_argument("--frames", type=int, default=2)
    cli_args.add_threads(parser)
    cli_args.add_json(parser)
    parser.add_argument("--one", nargs=2, metavar=("MODEL", "SIZE"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        width, height = SIZES[args.one[1]]
        print(json.dumps(measure(args.one[0], width, height, args.frames, args.threads)))
        return
    results = []
    print("| model | size | peak RSS growth | reservation + history | ratio | s/frame |")
    print("|---|---|---|---|---|---|")
    for model in args.models or shipped_models():
        for size in args.sizes:
            child = subprocess.run(
                [sys.executable, "-m", "quietframe.bench.admission_memory", "--one", model, size,
                 "--frames", str(args.frames), "--threads", str(args.threads)],
                capture_output=True, text=True, check=False)
            if child.returncode:
                print(f"| {model} | {size} | failed: {child.stderr.strip()[-200:]} | | | |")
                continue
            result = json.loads(child.stdout.strip().splitlines()[-1])
            results.append(result)
            worst = max(result["frames"], key=lambda r: r["peak_growth_mib"])
            print(f"| {model} | {size} | {worst['peak_growth_mib']} MiB | "
                  f"{worst['reserved_mib'] + worst['history_mib']} MiB | {result['ratio']:.2f} "
                  f"{'ok' if result['ratio'] <= TARGET_RATIO else 'OVER'} | "
                  f"{np.median([r['seconds'] for r in result['frames']]):.1f} |", flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
