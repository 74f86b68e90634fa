"""What `quietframe denoise` tells its reader: a progress bar on a terminal, one line per frame
in a log (stdout not a terminal), or one JSON object per line (`--json`) for scripts.

Every message is an event (`kind` + fields); the three outputs are three ways of writing the
same events, so a script sees exactly what a person sees. Errors also go to stderr as text.
"""

from __future__ import annotations

import json
import statistics
import sys
import time
from collections import defaultdict
from typing import TextIO

from tqdm import tqdm

from quietframe.client.preflight import format_numbers
from quietframe.wire.protocol import Reset, parse_estimated_motion

# What each sanitised buffer's count means, said once per run in the summary.
SANITIZED_WORDS = {
    "depth": "no-hit depths (sky or background written as 0 or 1e10) set to the farthest "
             "depth: expected for Blender, harmless",
    "color": "NaN/Inf/negative colour values set to 0: check the render for bad samples",
    "albedo": "NaN/Inf/negative albedo values set to 0",
    "normal": "NaN/Inf normals set to 0",
    "motion": "NaN/Inf motion vectors set to 0",
    "denoised": "output values clamped to the half-float range",
}


class Reporter:
    def __init__(self, mode: str, total: int, done: int = 0, stream: TextIO | None = None,
                 errors: TextIO | None = None) -> None:
        """`mode`: "bar" (terminal), "lines" (a log), "json" or "quiet" (errors only)."""
        self.mode, self.total, self.done = mode, total, done
        self.out = stream or sys.stdout
        self.err = errors or sys.stderr
        self.sanitized: dict[str, list[int]] = defaultdict(list)  # buffer -> count per frame
        self.warnings: list[str] = []
        self.no_motion: list[int] = []  # frames whose history was not used (no usable motion)
        # frames whose history followed motion estimated from the aux -> share of the frame
        self.estimated: dict[int, float] = {}
        # Server-Timing totals of this run's frames per model name: the time measured on this
        # server, which is what a farm plans with (the tables' figures come from elsewhere)
        self.server_ms: dict[str, list[float]] = defaultdict(list)
        self.below_input: set[str] = set()  # models whose X-Quietframe-Warning was said
        self.estimated_spp: set[str] = set()  # models whose X-Quietframe-Samples was said
        self.bar = None
        if mode == "bar":
            self.bar = tqdm(total=total, initial=done, unit="frame", dynamic_ncols=True,
                            file=self.err)

    def resume(self, done: int) -> None:
        """Count `done` frames as finished before this run (resumed, or kept by --force)."""
        self.done = done
        if self.bar is not None:
            self.bar.n = done
            self.bar.refresh()

    def measured_ms(self, model: str | None = None) -> float | None:
        """Median server time per frame so far on this server (of `model`, a name, if given)."""
        times = self.server_ms.get(model, []) if model else [
            ms for per_model in self.server_ms.values() for ms in per_model]
        return statistics.median(times) if times else None

    # ---- events --------------------------------------------------------------------------

    def event(self, kind: str, line: str, /, **fields) -> None:
        """One event: a JSON line, or `line` as a line of the log / above the bar."""
        if self.mode == "json":
            record = {"event": kind, "time": round(time.time(), 3), **fields}
            self.out.write(json.dumps(record, default=str) + "\n")
            self.out.flush()
        elif self.mode == "bar" and self.bar is not None:
            self.bar.write(line, file=self.err)
        elif self.mode == "lines":
            self.out.write(line + "\n")
            self.out.flush()

    def note(self, text: str) -> None:
        self.event("note", f"quietframe: {text}", message=text)

    def warn(self, text: str) -> None:
        self.warnings.append(text)
        self.event("warning", f"quietframe: warning: {text}", message=text)
        if self.mode == "quiet":
            self.err.write(f"quietframe: warning: {text}\n")

    def warn_retry(self, text: str) -> None:
        """A retry under way: said at once, even when quiet (a silent wait looks like a hang)."""
        if self.mode == "json":
            self.event("retry", text, message=text)
            return
        if self.bar is not None:
            self.bar.write(f"quietframe: {text}", file=self.err)
        else:
            self.err.write(f"quietframe: {text}\n")
            self.err.flush()

    def frame(self, index: int, name: str, result, reply_to: int | None = None,
              finished: bool = False) -> None:
        """Frame `index`'s output written; with look-ahead it came with the reply to frame
        `reply_to`, or from a finish call (`finished`) at the end of the run."""
        for buffer, count in result.sanitized_buffers.items():
            self.sanitized[buffer].append(count)
        if result.reset == Reset.NO_MOTION.value:
            self.no_motion.append(index)
        share = parse_estimated_motion(result.motion or "")
        if share is not None:
            self.estimated[index] = share
        self._below_input(index, result)
        self._estimated_samples(index, result)
        self.done += 1
        ms = result.timings_ms.get("total")
        if ms is not None:
            self.server_ms[result.model.split(" ")[0]].append(ms)
        fields = {"frame": index, "file": name, "reset": result.reset,
                  "missing": list(result.missing), "model": result.model,
                  "server_ms": ms, "replayed": result.replayed,
                  "sanitized": result.sanitized_buffers, "done": self.done, "total": self.total,
                  "reply_to": index if reply_to is None and not finished else reply_to,
                  "finished": finished}
        if self.mode == "bar" and self.bar is not None:
            self.bar.update(1)
            notes = [] if result.reset == "none" else [f"new history: {result.reset}"]
            self.bar.set_postfix_str(" ".join(notes))
            return
        notes = "" if result.reset == "none" else f", new history ({result.reset})"
        if finished:
            notes += ", finished at the end of the run"
        timing = f", {ms:.0f} ms" if ms is not None else ""
        self.event("frame", f"frame {index} {name} done [{self.done}/{self.total}]{timing}"
                   f"{notes}", **fields)

    def _below_input(self, index: int, result) -> None:
        """The server's warning that the model asked for is below its own noisy input at the
        frame's spp: once per model and run (every frame at that spp has it), as a warning."""
        model = result.model.split(" ")[0]
        if not result.warning or model in self.below_input:
            return
        self.below_input.add(model)
        self.warn(f"frame {index}: {result.warning} (said once per run)")

    def _estimated_samples(self, index: int, result) -> None:
        """A model named in the run reads the frame's spp and neither the frames' header nor
        --model-option states it: the server estimated it per shot (X-Quietframe-Samples);
        said once per model and run, as a warning, with how to state it instead."""
        model = result.model.split(" ")[0]
        if not result.samples or model in self.estimated_spp:
            return
        self.estimated_spp.add(model)
        spp = result.samples.split(";")[0]
        self.warn(f"frame {index}: {model} reads the frame's samples per pixel and neither the "
                  f"file's header nor --model-option states it; the server estimated {spp} spp "
                  "for the shot from its first frame (an estimate, often 1-2 stops off): pass "
                  "--model-option spp=N with the render's samples (said once per run)")

    def held(self, index: int, name: str) -> None:
        """A frame the server holds back for its look-ahead: its output comes later."""
        if self.bar is not None:
            self.bar.set_postfix_str(f"held for look-ahead: {name}")
        self.event("held", f"frame {index} {name} sent; held back for its look-ahead (written "
                   "when a later frame's reply carries it)", frame=index, file=name)

    def post_roll(self, index: int, name: str) -> None:
        if self.bar is not None:
            self.bar.set_postfix_str(f"post-roll: {name}")
        self.event("post-roll", f"frame {index} {name} sent for the look-ahead of the frames "
                   "before it (not written)", frame=index, file=name)

    def warm(self, index: int, name: str) -> None:
        if self.bar is not None:
            self.bar.set_postfix_str(f"warming history: {name}")
        self.event("warmup", f"frame {index} {name} sent to warm the history (not written)",
                   frame=index, file=name)

    def error(self, message: str, advice: str, code: int) -> None:
        self.close()
        if self.mode == "json":
            self.event("error", message, message=message, advice=advice, exit_code=code)
        self.err.write(f"quietframe: error: {message}\n")
        if advice:
            self.err.write(f"quietframe: {advice}\n")
        self.err.flush()

    def summary(self, written: int, out_dir) -> None:
        self.close()
        notes = [f"{buffer}: {max(counts)} per frame at most, in {len(counts)} frame(s): "
                 f"{SANITIZED_WORDS.get(buffer, 'values replaced')}"
                 for buffer, counts in sorted(self.sanitized.items()) if any(counts)]
        for line in notes:
            self.event("sanitized", f"quietframe: sanitised {line}", message=line)
        if self.no_motion:  # the temporal model ran as its per-frame stage there
            self.warn(f"{len(self.no_motion)} frame(s) moved without usable motion vectors "
                      f"(an all-zero or missing Vector pass: motion blur on?), so the "
                      f"temporal history was not used on them (denoised frame by frame, no "
                      f"ghosting): frames {format_numbers(self.no_motion)}; if the camera "
                      f"is locked off and nothing moves, --locked-off keeps the history "
                      f"(docs/service.md, 'Motion evidence')")
        if self.estimated:
            shares = sorted(self.estimated.values())
            line = (f"{len(self.estimated)} frame(s) moved without motion vectors: their "
                    f"history followed motion estimated from the aux, on {100 * shares[0]:.0f}"
                    f"-{100 * shares[-1]:.0f}% of each frame (the rest denoised frame by "
                    f"frame): frames {format_numbers(sorted(self.estimated))}; --motion "
                    f"rendered-only turns it off")
            self.event("motion", f"quietframe: {line}", message=line,
                       frames=sorted(self.estimated),
                       shares=[round(self.estimated[i], 3) for i in sorted(self.estimated)])
        text = f"{written} frame(s) written to {out_dir}"
        measured = self.measured_ms()
        if measured is not None:
            text += f"; {measured:.0f} ms per frame on this server (median Server-Timing)"
        if self.warnings:
            text += f"; {len(self.warnings)} warning(s): " + "; ".join(self.warnings)
        if self.mode == "json":
            self.event("summary", text, written=written, out=str(out_dir),
                       warnings=self.warnings, server_ms_median=measured)
        elif self.mode != "quiet":
            self.out.write(text + "\n")
            self.out.flush()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None
