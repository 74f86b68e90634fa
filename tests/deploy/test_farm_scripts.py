"""The render-and-denoise farm submissions in deploy/farm/: the Flamenco job type compiled with
node against a stand-in for Flamenco's job-author API (written from its documentation and its
3.8+ sources: `author.Task`, `author.Command(name, parameters, totalStepCount)`,
`task.addCommand`, `task.addDependency`, `job.addTask`, `frameChunker`, `frameCount`), its
denoise commands run as the Worker runs them (retry_on_75.py around the client) against a real
server once their renders are done; and the Deadline submission script's job files, written
(--write-only) and submitted through a stand-in deadlinecommand, their command line run per
chunk as the CommandLine plugin runs it. With a look-ahead each denoise task also waits for the
renders of its post-roll (the frames after its chunk): run as soon as its dependencies are done,
with only the frames they waited for on disk, against the look-ahead stand-in
(tests/lookahead_support.py), whose outputs are their own frames, and against the real server."""

from __future__ import annotations

import json
import shlex
import shutil
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest
from conftest import shot
from lookahead_support import FakeServer

FARM = Path(__file__).resolve().parents[2] / "deploy" / "farm"
FLAMENCO_SCRIPT = FARM / "flamenco" / "quietframe_render_denoise.js"
DEADLINE_SCRIPT = FARM / "deadline" / "submit_render_denoise.py"

# Flamenco's job-author API as its documentation describes it, recording what a script does.
# frameChunker follows the Manager's: explode "A-B" / "A..B" lists, chunk, merge runs back
# ("1001-1004"; a two-frame run as "1005,1006").
FLAMENCO_STAND_IN = """
function frameChunker(frames, size) {
  const numbers = new Set();
  for (const part of String(frames).split(",").map((p) => p.trim())) {
    const [a, b] = part.includes("..") ? part.split("..") : part.split("-");
    for (let n = Number(a); n <= Number(b === undefined ? a : b); n++) numbers.add(n);
  }
  const sorted = [...numbers].sort((x, y) => x - y);
  const chunks = [];
  for (let i = 0; i < sorted.length; i += size) chunks.push(merge(sorted.slice(i, i + size)));
  return chunks;
}
function merge(frames) {
  const runs = [];
  let start = frames[0], previous = frames[0];
  const close = (from, to) => {
    if (from === to) runs.push(String(from));
    else if (from + 1 === to) runs.push(String(from), String(to));
    else runs.push(`${from}-${to}`);
  };
  for (const frame of frames.slice(1)) {
    if (frame > previous + 1) { close(start, previous); start = frame; }
    previous = frame;
  }
  close(start, previous);
  return runs.join(",");
}
function print() {}
const author = {
  Task: (name, type) => ({
    name, type, commands: [], dependencies: [],
    addCommand(command) { this.commands.push(command); },
    addDependency(task) { this.dependencies.push(task.name); },
  }),
  // A Manager before 3.8 ignores the third argument (its JavaScript engine drops extra ones).
  Command: (name, parameters, totalStepCount) => ({ name, parameters,
                                                    steps: totalStepCount || 0 }),
};
"""
# Flamenco 3.8's frameCount: the frames of a chunk as frameChunker writes it.
FRAME_COUNT = """
function frameCount(chunk) {
  let count = 0;
  for (const part of chunk.split(",")) {
    const [a, b] = part.includes("..") ? part.split("..") : part.split("-");
    count += b === undefined ? 1 : Number(b) - Number(a) + 1;
  }
  return count;
}
"""
RETRY_WRAPPER = FARM / "retry_on_75.py"
QUIETFRAME = Path(sys.executable).with_name("quietframe")  # the client, as installed


def compile_flamenco_job(settings: dict, manager_3_8: bool = True) -> list[dict]:
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed")
    script = (FLAMENCO_STAND_IN + (FRAME_COUNT if manager_3_8 else "")
              + FLAMENCO_SCRIPT.read_text()
              + f"\nconst job = {{ settings: {json.dumps(settings)}, tasks: [],"
              " addTask(t) { this.tasks.push(t); } };\n"
              "compileJob(job); console.log(JSON.stringify(job.tasks));")
    compiled = subprocess.run([node, "-e", script], capture_output=True, text=True, timeout=60)
    assert compiled.returncode == 0, compiled.stderr
    return json.loads(compiled.stdout)


def flamenco_settings(tmp_path: Path, server_url: str, **overrides) -> dict:
    return {"frames": "1001-1010", "chunk_size": 4, "pre_roll": 2, "model": "nbg-2l-3g",
            "render_output": str(tmp_path / "render" / "sh010.####.exr"),
            "denoised_output": str(tmp_path / "denoised"), "server": server_url,
            "quietframe": "quietframe", "retry_wrapper": "/opt/quietframe/bin/retry_on_75.py",
            "python": "python3", "blendfile": "/shots/sh010/sh010.blend", "scene": "sh010_lit",
            **overrides}


def test_flamenco_denoise_tasks_wait_for_their_renders_and_run_strict(tmp_path):
    tasks = compile_flamenco_job(flamenco_settings(tmp_path, "http://denoise:8000"))
    by_name = {t["name"]: t for t in tasks}
    assert [t["name"] for t in tasks] == [
        "render-1001-1004", "render-1005-1008", "render-1009,1010",
        "denoise-1001-1004", "denoise-1005-1008", "denoise-1009,1010"]
    # each denoise task: its own chunk's render, and the render holding its 2 pre-roll frames
    assert by_name["denoise-1001-1004"]["dependencies"] == ["render-1001-1004"]
    assert by_name["denoise-1005-1008"]["dependencies"] == ["render-1001-1004",
                                                            "render-1005-1008"]
    assert by_name["denoise-1009,1010"]["dependencies"] == ["render-1005-1008",
                                                            "render-1009,1010"]
    (render,) = by_name["render-1005-1008"]["commands"]
    assert render["name"] == "blender-render" and by_name["render-1005-1008"]["type"] == "blender"
    assert render["parameters"]["args"][-2:] == ["--render-frame", "1005..1008"]
    for task in tasks:
        if task["name"].startswith("denoise-"):
            (command,) = task["commands"]
            assert command["name"] == "exec" and command["steps"] == 0  # one step: the command
            # python3 retry_on_75.py -- quietframe denoise ...: 75 retried in place, 2/3 at once
            assert command["parameters"]["exe"] == "python3"
            wrapper, separator, client, *args = command["parameters"]["args"]
            assert (wrapper, separator, client) == ("/opt/quietframe/bin/retry_on_75.py", "--",
                                                    "quietframe")
            assert args[0] == "denoise" and "--strict" in args
            chunk = task["name"].removeprefix("denoise-")
            assert args[args.index("--frames") + 1] == chunk
            assert args[args.index("--cut") + 1] == "1001"  # the job's first frame: no pre-roll


def test_flamenco_render_tasks_set_what_flamencos_own_job_type_sets(tmp_path):
    """The scene evaluated at submission, the file extension forced on (the output pattern has
    none), no placeholders; frames as the render command's steps on a 3.8+ Manager."""
    tasks = compile_flamenco_job(flamenco_settings(tmp_path, "http://denoise:8000"))
    renders = [t for t in tasks if t["type"] == "blender"]
    for task in renders:
        (render,) = task["commands"]
        args = render["parameters"]["args"]
        assert args[:2] == ["--scene", "sh010_lit"]  # before anything it applies to
        settings = args[args.index("--python-expr") + 1]
        assert "render.use_file_extension = True" in settings
        assert "render.use_placeholder = False" in settings
        assert args.index("--python-expr") < args.index("--render-frame")
        assert args[args.index("--render-output") + 1].endswith("sh010.####")  # Blender adds .exr
    assert [t["commands"][0]["steps"] for t in renders] == [4, 4, 2]  # 1001-1004, ..., 1009,1010
    older = compile_flamenco_job(flamenco_settings(tmp_path, "http://denoise:8000"),
                                 manager_3_8=False)  # no frameCount: compiles, without steps
    assert [t["commands"][0]["steps"] for t in older if t["type"] == "blender"] == [0, 0, 0]


def test_flamenco_job_type_states_the_version_it_needs():
    header = FLAMENCO_SCRIPT.read_text().split("const JOB_TYPE")[0]
    assert "Needs Flamenco 3.3 or newer (the `exec` command" in header
    assert "restart" in header and "3.7" in header  # when the Manager reads scripts/ again


def test_flamenco_without_a_retry_wrapper_runs_the_client_directly(tmp_path):
    tasks = compile_flamenco_job(flamenco_settings(tmp_path, "http://denoise:8000",
                                                   retry_wrapper=""))
    (command,) = next(t for t in tasks if t["type"] == "misc")["commands"]
    assert command["parameters"]["exe"] == "quietframe"
    assert command["parameters"]["args"][0] == "denoise"


def run_exec(parameters: dict) -> subprocess.CompletedProcess:
    """Flamenco's `exec`: the executable run directly with its arguments, no shell."""
    return subprocess.run([parameters["exe"], *parameters["args"]], capture_output=True,
                          text=True, timeout=120)


def test_flamenco_tasks_run_in_dependency_order_against_a_server(tmp_path, live_server):
    """Render tasks stand in by writing their chunk's frames; each denoise task runs once its
    dependencies are done, as the Worker runs it: retry_on_75.py around the installed client."""
    tasks = compile_flamenco_job(flamenco_settings(
        tmp_path, live_server.url, frames="1001..1006", chunk_size=3, python=sys.executable,
        retry_wrapper=str(RETRY_WRAPPER), quietframe=str(QUIETFRAME)))
    frames = shot(6, "blender")
    (tmp_path / "render").mkdir()
    done: set[str] = set()
    for task in tasks:
        assert set(task["dependencies"]) <= done, task["name"]
        (command,) = task["commands"]
        if task["type"] == "blender":
            first, last = command["parameters"]["args"][-1].split("..")
            for frame in range(int(first), int(last) + 1):
                (tmp_path / "render" / f"sh010.{frame}.exr").write_bytes(frames[frame - 1001])
        else:
            result = run_exec(command["parameters"])
            assert result.returncode == 0, result.stderr
            assert result.stdout.count(" done [") == 3  # the task log: one line per frame
        done.add(task["name"])
    assert len(list((tmp_path / "denoised").glob("*.exr"))) == 6


def deadline(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(DEADLINE_SCRIPT), *args], capture_output=True,
                          text=True, timeout=60)


def read_info(path: Path) -> dict[str, str]:
    return dict(line.split("=", 1) for line in path.read_text().splitlines() if "=" in line)


SUBMISSION = ["--blend", "/shots/sh010/sh010.blend", "--render-output",
              "/shots/sh010/render/sh010.####.exr", "--out", "/shots/sh010/denoised",
              "--frames", "1001..1100", "--chunk-size", "12", "--pre-roll", "4"]


def test_deadline_write_only_writes_a_frame_dependent_denoise_job(tmp_path):
    result = deadline(*SUBMISSION, "--write-only", str(tmp_path))
    assert result.returncode == 0, result.stderr
    render_job, denoise_job = read_info(tmp_path / "render_job.txt"), read_info(
        tmp_path / "denoise_job.txt")
    render_plugin = read_info(tmp_path / "render_plugin.txt")
    denoise_plugin = read_info(tmp_path / "denoise_plugin.txt")
    assert render_job["Plugin"] == "Blender" and render_job["Frames"] == "1001-1100"
    assert render_plugin["OutputFile"] == "/shots/sh010/render/sh010.####"
    assert denoise_job["Plugin"] == "CommandLine"
    assert (denoise_job["Frames"], denoise_job["ChunkSize"]) == ("1001-1100", "12")
    assert denoise_job["JobDependencies"] == "<render job id>"
    assert denoise_job["IsFrameDependent"] == "true"
    assert denoise_job["FrameDependencyOffsetStart"] == "-4"  # the pre-roll's frames too
    arguments = denoise_plugin["Arguments"].split()
    assert "--strict" in arguments and "<STARTFRAME>-<ENDFRAME>" in arguments
    assert arguments[arguments.index("--pre-roll") + 1] == "4"
    assert arguments[arguments.index("--cut") + 1] == "1001"
    assert result.stdout.count("deadlinecommand ") == 2
    # python3 retry_on_75.py -- quietframe denoise ...: 75 retried in place, 2/3 end the task
    assert denoise_plugin["Executable"] == "/usr/bin/python3"
    assert arguments[:4] == ["/opt/quietframe/bin/retry_on_75.py", "--",
                             "/opt/quietframe/bin/quietframe", "denoise"]
    # and such a task fails after 3 errors, whatever the repository's limit
    assert denoise_job["OverrideTaskFailureDetection"] == "true"
    assert denoise_job["FailureDetectionTaskErrors"] == "3"


def test_deadline_without_a_retry_wrapper_runs_the_client_directly(tmp_path):
    result = deadline(*SUBMISSION, "--retry-wrapper", "", "--task-errors", "0",
                      "--write-only", str(tmp_path))
    assert result.returncode == 0, result.stderr
    plugin, job = read_info(tmp_path / "denoise_plugin.txt"), read_info(
        tmp_path / "denoise_job.txt")
    assert plugin["Executable"] == "/opt/quietframe/bin/quietframe"
    assert plugin["Arguments"].startswith("denoise ")
    assert "OverrideTaskFailureDetection" not in job  # the repository's limit


def test_deadline_denoise_tasks_run_against_a_server(tmp_path, live_server):
    """The denoise job's Arguments cut into Deadline's chunks, once the render wrote them."""
    (tmp_path / "render").mkdir()
    for i, data in enumerate(shot(6, "blender")):
        (tmp_path / "render" / f"sh010.{1001 + i}.exr").write_bytes(data)
    result = deadline("--blend", "sh010.blend", "--render-output",
                      str(tmp_path / "render" / "sh010.####.exr"), "--out",
                      str(tmp_path / "denoised"), "--frames", "1001-1006", "--chunk-size", "3",
                      "--pre-roll", "2", "--server", live_server.url, "--model", "nbg-2l-3g",
                      "--python", sys.executable, "--retry-wrapper", str(RETRY_WRAPPER),
                      "--quietframe", str(QUIETFRAME), "--write-only", str(tmp_path / "jobs"))
    assert result.returncode == 0, result.stderr
    plugin = read_info(tmp_path / "jobs" / "denoise_plugin.txt")
    for start in (1001, 1004):  # the CommandLine plugin: Executable + Arguments, per task
        line = plugin["Arguments"].replace("<STARTFRAME>", str(start)).replace(
            "<ENDFRAME>", str(start + 2))
        task = subprocess.run([plugin["Executable"], *shlex.split(line)], capture_output=True,
                              text=True, timeout=120)
        assert task.returncode == 0, task.stderr
    assert len(list((tmp_path / "denoised").glob("*.exr"))) == 6


def test_deadline_submits_the_render_then_the_denoise_depending_on_its_id(tmp_path):
    calls = tmp_path / "calls.txt"
    fake = tmp_path / "deadlinecommand"
    fake.write_text(f"""#!{sys.executable}
import sys
from pathlib import Path
job = Path(sys.argv[1]).read_text()
with open({str(calls)!r}, "a") as log:
    log.write(job + "----\\n")
print("Result=Success")
print("JobID=5f2a" + ("0001" if "Plugin=Blender" in job else "0002"))
""")
    fake.chmod(0o755)
    result = deadline(*SUBMISSION, "--deadlinecommand", str(fake))
    assert result.returncode == 0, result.stderr
    render_info, denoise_info, _ = calls.read_text().split("----\n")
    assert "Plugin=Blender" in render_info and "Plugin=CommandLine" in denoise_info
    assert "JobDependencies=5f2a0001\n" in denoise_info  # the render job's ID, as answered
    assert "render job 5f2a0001, denoise job 5f2a0002" in result.stdout


def test_deadline_refuses_a_pattern_without_a_frame_field(tmp_path):
    flags = [*SUBMISSION, "--write-only", str(tmp_path)]
    flags[flags.index("--render-output") + 1] = "/shots/sh010/render/sh010.exr"
    result = deadline(*flags)
    assert result.returncode == 2 and "####" in result.stderr


# ---- look-ahead: each chunk also reads the frames after it ------------------------------------


def test_flamenco_lookahead_waits_for_the_renders_of_the_post_roll(tmp_path):
    tasks = compile_flamenco_job(flamenco_settings(tmp_path, "http://denoise:8000",
                                                   lookahead=2))
    by_name = {t["name"]: t for t in tasks}
    # each denoise task: its own chunk's render, its 2 pre-roll frames' and 2 post-roll frames'
    assert by_name["denoise-1001-1004"]["dependencies"] == ["render-1001-1004",
                                                            "render-1005-1008"]
    assert by_name["denoise-1005-1008"]["dependencies"] == [
        "render-1001-1004", "render-1005-1008", "render-1009,1010"]
    assert by_name["denoise-1009,1010"]["dependencies"] == ["render-1005-1008",
                                                            "render-1009,1010"]
    for task in tasks:
        if task["type"] == "misc":
            args = task["commands"][0]["parameters"]["args"]
            assert args[args.index("--lookahead") + 1] == "2"
            assert args[args.index("--post-roll") + 1] == "2"
            cuts = [args[i + 1] for i, a in enumerate(args) if a == "--cut"]
            assert cuts == ["1001", "1011"]  # the job's first frame, the one after its last
    plain = compile_flamenco_job(flamenco_settings(tmp_path, "http://denoise:8000"))
    args = next(t for t in plain if t["type"] == "misc")["commands"][0]["parameters"]["args"]
    assert "--lookahead" not in args and "--post-roll" not in args


@pytest.fixture(params=["stand-in", "server"])
def lookahead_server(request):
    """(URL, model, the stand-in or None): the look-ahead stand-in, whose outputs are their
    own frames, and the real server (skipped where it has no look-ahead yet)."""
    if request.param == "stand-in":
        with FakeServer() as fake:
            yield fake.url, "fake", fake.fake
        return
    live = request.getfixturevalue("live_server")
    paths = json.loads(urllib.request.urlopen(f"{live.url}/openapi.json", timeout=60).read())
    if "/v1/sessions/{session_id}/frames/{index}/finish" not in paths["paths"]:
        pytest.skip("this server has no look-ahead (no finish route)")
    yield live.url, "oidn-fast-history", None


def assert_denoised_from_their_frames(denoised: Path, frames: list[bytes], fake) -> None:
    """Every frame written; by the stand-in, each from its own frame's upload."""
    assert sorted(p.name for p in denoised.glob("*.exr")) == [
        f"sh010.{n}.exr" for n in range(1001, 1001 + len(frames))]
    if fake is not None:
        assert all((denoised / f"sh010.{n}.exr").read_bytes() == frames[n - 1001]
                   for n in range(1001, 1001 + len(frames)))


def test_flamenco_lookahead_tasks_run_as_soon_as_their_renders_are_done(tmp_path,
                                                                        lookahead_server):
    """A scheduler that starts each denoise task once its dependencies are done, between render
    tasks: a chunk whose post-roll render were not among them would fail (--strict, a missing
    post-roll frame)."""
    url, model, fake = lookahead_server
    tasks = compile_flamenco_job(flamenco_settings(
        tmp_path, url, frames="1001..1006", chunk_size=2, model=model, lookahead=2,
        python=sys.executable, retry_wrapper=str(RETRY_WRAPPER), quietframe=str(QUIETFRAME)))
    frames = shot(6, "blender")
    render = tmp_path / "render"
    render.mkdir()
    done: set[str] = set()
    waiting = [t for t in tasks if t["type"] == "misc"]
    for task in (t for t in tasks if t["type"] == "blender"):
        for frame in render_frames(task["commands"][0]["parameters"]["args"][-1]):
            (render / f"sh010.{frame}.exr").write_bytes(frames[frame - 1001])
        done.add(task["name"])
        for ready in [t for t in waiting if set(t["dependencies"]) <= done]:
            result = run_exec(ready["commands"][0]["parameters"])
            assert result.returncode == 0, result.stderr
            waiting.remove(ready)
            done.add(ready["name"])
    assert not waiting
    assert_denoised_from_their_frames(tmp_path / "denoised", frames, fake)
    if fake is not None:  # chunk 1's post-roll, chunk 2's frame, chunk 3's pre-roll
        assert fake.sent("frame").count(1003) == 3


def render_frames(frames: str) -> list[int]:
    """The frames of Blender's --render-frame argument: `1001..1004`, `1005,1006`, `7`."""
    found = []
    for part in frames.split(","):
        first, _, last = part.partition("..")
        found += range(int(first), int(last or first) + 1)
    return found


def test_deadline_lookahead_offsets_the_dependency_end_and_passes_the_post_roll(tmp_path):
    result = deadline(*SUBMISSION, "--lookahead", "2", "--write-only", str(tmp_path))
    assert result.returncode == 0, result.stderr
    job = read_info(tmp_path / "denoise_job.txt")
    assert (job["FrameDependencyOffsetStart"], job["FrameDependencyOffsetEnd"]) == ("-4", "2")
    arguments = read_info(tmp_path / "denoise_plugin.txt")["Arguments"].split()
    assert arguments[arguments.index("--lookahead") + 1] == "2"
    assert arguments[arguments.index("--post-roll") + 1] == "2"
    assert [arguments[i + 1] for i, a in enumerate(arguments) if a == "--cut"] == ["1001",
                                                                                    "1101"]
    plain = deadline(*SUBMISSION, "--write-only", str(tmp_path / "plain"))
    assert plain.returncode == 0, plain.stderr
    assert read_info(tmp_path / "plain" / "denoise_job.txt")["FrameDependencyOffsetEnd"] == "0"
    assert "--lookahead" not in read_info(tmp_path / "plain" / "denoise_plugin.txt")["Arguments"]
    refused = deadline(*SUBMISSION, "--lookahead", "5", "--write-only", str(tmp_path / "no"))
    assert refused.returncode == 2 and "--lookahead takes 0 to 4" in refused.stderr


def test_deadline_lookahead_tasks_read_only_the_frames_their_dependency_waits_for(
        tmp_path, lookahead_server):
    """Each task of the denoise job run with the render folder holding just the frames its
    frame dependency (the offsets) has waited for: with --strict a missing one fails it."""
    url, model, fake = lookahead_server
    frames = shot(6, "blender")
    render = tmp_path / "render"
    result = deadline("--blend", "sh010.blend", "--render-output", str(render / "sh010.####.exr"),
                      "--out", str(tmp_path / "denoised"), "--frames", "1001-1006",
                      "--chunk-size", "2", "--pre-roll", "2", "--lookahead", "2", "--server",
                      url, "--model", model, "--python", sys.executable, "--retry-wrapper",
                      str(RETRY_WRAPPER), "--quietframe", str(QUIETFRAME), "--write-only",
                      str(tmp_path / "jobs"))
    assert result.returncode == 0, result.stderr
    job = read_info(tmp_path / "jobs" / "denoise_job.txt")
    plugin = read_info(tmp_path / "jobs" / "denoise_plugin.txt")
    before, after = int(job["FrameDependencyOffsetStart"]), int(job["FrameDependencyOffsetEnd"])
    for start in (1001, 1003, 1005):  # Deadline's chunks of 2
        shutil.rmtree(render, ignore_errors=True)
        render.mkdir()
        for frame in range(max(1001, start + before), min(1006, start + 1 + after) + 1):
            (render / f"sh010.{frame}.exr").write_bytes(frames[frame - 1001])
        line = plugin["Arguments"].replace("<STARTFRAME>", str(start)).replace(
            "<ENDFRAME>", str(start + 1))
        task = subprocess.run([plugin["Executable"], *shlex.split(line)], capture_output=True,
                              text=True, timeout=120)
        assert task.returncode == 0, task.stderr
    assert_denoised_from_their_frames(tmp_path / "denoised", frames, fake)
