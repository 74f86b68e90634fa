#!/usr/bin/env python3
"""Submit a Blender render and its quietframe denoise to Deadline (Thinkbox) as two jobs: the
render (Deadline's Blender plugin), then a denoise job (the stock CommandLine plugin) that
depends on it frame by frame, so each denoise task starts as soon as its frames are rendered.

    python3 submit_render_denoise.py --blend /shots/sh010/sh010.blend \\
        --render-output /shots/sh010/render/sh010.####.exr --out /shots/sh010/denoised \\
        --frames 1001-1100 --chunk-size 12 --pre-roll 4 --server http://denoise:8000

The denoise job is frame dependent (IsFrameDependent) with its start offset set back by the
pre-roll (FrameDependencyOffsetStart=-N) and, with `--lookahead K`, its end offset forward by
the post-roll (FrameDependencyOffsetEnd=K): a task for 1013-1024 with pre-roll 4 and look-ahead
2 waits for the render of 1009-1026, the frames it reads, and never for the whole render. Each
task runs `quietframe denoise ... --strict`, so a frame the render did not write fails the task
instead of being denoised across; `--cut` at the job's first frame starts the history there (the
frames before it are not this job's renders, so the first chunk has no pre-roll to wait for),
and with a look-ahead `--cut` at the frame after the job's last ends the last chunk's post-roll
(`--post-roll K`: frames sent only for the look-ahead of the chunk's last frames, not written).

Failures: Deadline fails a task on any non-zero exit and requeues it until its error limits,
whatever the code. So each denoise task runs under deploy/farm/retry_on_75.py (`--retry-wrapper`,
copied to the Workers): exit 75 (server unavailable or busy) is retried in place with growing
waits (the rerun resumes), while 2 (configuration) and 3 (input) end the task at once with what
to fix in its log; the denoise job's own task error limit (`--task-errors`, 3: Deadline's
OverrideTaskFailureDetection / FailureDetectionTaskErrors job keys) then fails such a task after
a few quick errors instead of the repository's limit.

`--write-only DIR` writes the four job files into DIR and prints the deadlinecommand lines
instead of submitting (the denoise job then names the render job `<render job id>`). The
.blend must write multilayer EXR with the Denoising Data passes (docs/farm.md). Standard
library only: it runs wherever deadlinecommand does.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from pathlib import Path

RENDER_JOB_PLACEHOLDER = "<render job id>"


def frame_list(text: str) -> str:
    """Deadline's frame list from a Blender or farm range: `1001..1100` -> `1001-1100`."""
    frames = text.replace("..", "-").replace(" ", "")
    if not re.fullmatch(r"\d+(-\d+)?(,\d+(-\d+)?)*", frames):
        raise argparse.ArgumentTypeError(f"expected frames like 1001-1100 or 1001..1100, got "
                                         f"{text!r}")
    return frames


def render_job(args: argparse.Namespace) -> dict[str, str]:
    return {
        "Plugin": "Blender",
        "Name": f"{args.name} render",
        "BatchName": args.name,
        "Frames": args.frames,
        "ChunkSize": str(args.chunk_size),
        "OutputDirectory0": str(Path(args.render_output).parent),
        "OutputFilename0": Path(args.render_output).name,
    }


def render_plugin(args: argparse.Namespace) -> dict[str, str]:
    return {
        "SceneFile": args.blend,
        # Blender adds the extension itself (the plugin passes -x 1).
        "OutputFile": re.sub(r"\.exr$", "", args.render_output, flags=re.I),
        "Threads": "0",
    }


def denoise_job(args: argparse.Namespace, render_id: str) -> dict[str, str]:
    """Frame dependent on the render: each task waits for its frames, its pre-roll and (with a
    look-ahead) its post-roll."""
    job = {
        "Plugin": "CommandLine",
        "Name": f"{args.name} denoise",
        "BatchName": args.name,
        "Frames": args.frames,
        "ChunkSize": str(args.chunk_size),
        "JobDependencies": render_id,
        "IsFrameDependent": "true",
        "FrameDependencyOffsetStart": str(-args.pre_roll),
        "FrameDependencyOffsetEnd": str(args.lookahead),  # the post-roll's frames
        "ResumeOnCompleteDependencies": "true",
        "OutputDirectory0": args.out,
    }
    if args.task_errors:  # a task failing 2/3 fails after these errors, not the repository's
        job.update({"OverrideTaskFailureDetection": "true",
                    "FailureDetectionTaskErrors": str(args.task_errors)})
    return job


def denoise_plugin(args: argparse.Namespace) -> dict[str, str]:
    numbers = [int(n) for n in re.findall(r"\d+", args.frames)]
    arguments = ["denoise", "--server", args.server, quoted(args.render_output),
                 "--out", quoted(args.out), "--frames", "<STARTFRAME>-<ENDFRAME>",
                 "--pre-roll", str(args.pre_roll), "--cut", str(min(numbers)), "--model",
                 args.model, "--strict"]
    if args.lookahead:  # the post-roll ends at the frame after the job's last
        arguments += ["--lookahead", str(args.lookahead), "--post-roll", str(args.lookahead),
                      "--cut", str(max(numbers) + 1)]
    executable = args.quietframe
    if args.retry_wrapper:  # python3 retry_on_75.py -- quietframe denoise ...
        arguments = [quoted(args.retry_wrapper), "--", quoted(args.quietframe), *arguments]
        executable = args.python
    return {"Executable": executable, "Arguments": " ".join(arguments), "Shell": "default"}


def quoted(path: str) -> str:
    """A path as one argument of the CommandLine plugin's line (double quotes: every OS)."""
    return f'"{path}"' if " " in path else path


def write_info(path: Path, fields: dict[str, str]) -> Path:
    path.write_text("".join(f"{key}={value}\n" for key, value in fields.items()))
    return path


def submit(deadlinecommand: str, job: Path, plugin: Path) -> str:
    """The new job's ID, from deadlinecommand's `JobID=...` line; SystemExit on failure."""
    done = subprocess.run([deadlinecommand, str(job), str(plugin)], capture_output=True,
                          text=True)
    found = re.search(r"^JobID=(\S+)", done.stdout, re.M)
    if done.returncode != 0 or found is None:
        sys.exit(f"deadlinecommand {job.name} failed ({done.returncode}):\n{done.stdout}"
                 f"{done.stderr}")
    return found.group(1)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    parser.add_argument("--blend", required=True, help="the .blend to render (on the Workers)")
    parser.add_argument("--render-output", required=True,
                        help="rendered frames as a pattern: /shots/sh010/render/sh010.####.exr")
    parser.add_argument("--out", required=True, help="folder for the denoised frames")
    parser.add_argument("--frames", required=True, type=frame_list,
                        help="1001-1100 (or Blender's 1001..1100)")
    parser.add_argument("--chunk-size", type=int, default=12, help="frames per task")
    parser.add_argument("--pre-roll", type=int, default=4,
                        help="frames sent before each chunk to warm the history (not written)")
    parser.add_argument("--lookahead", type=int, default=0,
                        help="later frames (0-4) each frame's denoise also uses; each task "
                        "then reads as many frames after its chunk (post-roll, not written)")
    parser.add_argument("--server", default="http://denoise:8000", help="quietframe server")
    parser.add_argument("--model", default="auto", help="quietframe model, or auto")
    parser.add_argument("--name", help="job name (default: the .blend's name)")
    parser.add_argument("--quietframe", default="/opt/quietframe/bin/quietframe",
                        help="the quietframe client on the Workers")
    parser.add_argument("--retry-wrapper", default="/opt/quietframe/bin/retry_on_75.py",
                        help="deploy/farm/retry_on_75.py on the Workers: retries exit 75, "
                        "ends the task at once on 2/3; '' runs quietframe directly")
    parser.add_argument("--python", default="/usr/bin/python3",
                        help="the Python 3 that runs --retry-wrapper on the Workers")
    parser.add_argument("--task-errors", type=int, default=3,
                        help="errors after which a denoise task fails (0: the repository's "
                        "limit)")
    parser.add_argument("--deadlinecommand", default="deadlinecommand")
    parser.add_argument("--write-only", metavar="DIR", type=Path,
                        help="write the job files into DIR and print the commands; submit "
                        "nothing")
    args = parser.parse_args(argv)
    if "#" not in args.render_output:
        parser.error("--render-output needs a frame field (####)")
    if args.chunk_size < 1 or args.pre_roll < 0 or args.task_errors < 0:
        parser.error("--chunk-size takes a count >= 1, --pre-roll and --task-errors ones >= 0")
    if not 0 <= args.lookahead <= 4:
        parser.error(f"--lookahead takes 0 to 4 frames, got {args.lookahead}")
    args.name = args.name or Path(args.blend).stem
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    folder = args.write_only or Path(tempfile.mkdtemp(prefix="quietframe-deadline-"))
    folder.mkdir(parents=True, exist_ok=True)
    render = (write_info(folder / "render_job.txt", render_job(args)),
              write_info(folder / "render_plugin.txt", render_plugin(args)))
    if args.write_only:
        render_id = RENDER_JOB_PLACEHOLDER
    else:
        render_id = submit(args.deadlinecommand, *render)
    denoise = (write_info(folder / "denoise_job.txt", denoise_job(args, render_id)),
               write_info(folder / "denoise_plugin.txt", denoise_plugin(args)))
    if args.write_only:
        for job, plugin in (render, denoise):
            print(f"{args.deadlinecommand} {job} {plugin}")
        return 0
    denoise_id = submit(args.deadlinecommand, *denoise)
    print(f"render job {render_id}, denoise job {denoise_id} (frame dependent on it)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
