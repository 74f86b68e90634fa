"""What the service answers to a fixed set of requests, as digests: run it on two commits and
diff the outputs to show a refactor changed no reply (bytes, model choices, resets, errors).

    python tools/reply_digest.py > after.txt
    git worktree add /tmp/before <commit> && (cd /tmp/before && python tools/reply_digest.py) \
        > before.txt; diff before.txt after.txt

Each line: the request, the status, the sha256 of the reply body (an EXR or an error's JSON)
and the reply headers that carry decisions (model, reset, choice, motion, missing, sanitized,
error code). Timings are left out. The requests: the Blender fixtures (tests/fixtures) as
sequences through every installed model and `auto`, locked off with `camera: locked`, a cut,
a retry, a gap, and refused input (a frame out of order, a damaged body, a wrong size). The
service runs in-process (FastAPI's TestClient) with the installed models.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SEQUENCES = ROOT / "tests" / "fixtures" / "blender_sequences"
SINGLES = ROOT / "tests" / "fixtures" / "blender"
KEPT_HEADERS = ("x-quietframe-model", "x-quietframe-reset", "x-quietframe-choice",
                "x-quietframe-motion", "x-quietframe-missing", "x-quietframe-sanitized",
                "x-quietframe-sanitized-buffers", "x-quietframe-replayed", "x-quietframe-frame",
                "content-type", "retry-after")


def frames(name: str) -> list[bytes]:
    return [p.read_bytes() for p in sorted(SEQUENCES.glob(f"{name}.000[0-9].exr"))]


def size_of(path: Path) -> tuple[int, int]:
    import OpenEXR

    (x0, y0), (x1, y1) = OpenEXR.File(str(path), header_only=True).header()["dataWindow"]
    return int(x1 - x0 + 1), int(y1 - y0 + 1)


def line(what: str, reply) -> str:
    body = reply.content
    headers = {k: reply.headers[k] for k in KEPT_HEADERS if k in reply.headers}
    if reply.headers.get("content-type", "").startswith("application/json"):
        headers["error"] = json.loads(body).get("error")
    digest = hashlib.sha256(body).hexdigest()[:16]
    return f"{what}: {reply.status_code} {digest} {json.dumps(headers, sort_keys=True)}"


def run(client, models: list[str]) -> list[str]:
    out = []

    def session(size: tuple[int, int] = (128, 72), **fields) -> str:
        reply = client.post("/v1/sessions", json={"width": size[0], "height": size[1], **fields})
        assert reply.status_code == 201, reply.text
        return reply.json()["id"]

    def send(sid: str, index: int, body: bytes, query: str = "") -> object:
        return client.post(f"/v1/sessions/{sid}/frames/{index}{query}", content=body,
                           headers={"Content-Type": "image/x-exr"})

    for model in [*models, "auto"]:
        for shot in ("motion_blur", "locked_off"):
            sid = session(model=model)
            for i, body in enumerate(frames(shot)):
                out.append(line(f"{model} {shot} {i}", send(sid, i, body)))
            client.delete(f"/v1/sessions/{sid}")
    # locked off by the TD, a cut by query, a retry, a gap, refused frames
    sid = session(model="auto", camera="locked")
    shot = frames("locked_off")
    out.append(line("locked 0", send(sid, 0, shot[0])))
    out.append(line("locked 1", send(sid, 1, shot[1])))
    out.append(line("locked 1 retry", send(sid, 1, shot[1])))
    out.append(line("locked 2 cut", send(sid, 2, shot[2], "?cut=true")))
    out.append(line("locked 5 gap", send(sid, 5, shot[3])))
    out.append(line("locked 4 out of order", send(sid, 4, shot[4])))
    out.append(line("locked 6 damaged", send(sid, 6, shot[4][: len(shot[4]) // 2])))
    out.append(line("locked 6 wrong size", send(sid, 6, (SINGLES / "plain_rgba.0002.exr")
                                                     .read_bytes())))
    out.append(line("locked 6", send(sid, 6, shot[5])))
    client.delete(f"/v1/sessions/{sid}")
    for path in sorted(SINGLES.glob("*.exr")):
        sid = session(size_of(path), model="auto")
        out.append(line(f"auto {path.name}", send(sid, 0, path.read_bytes())))
        client.delete(f"/v1/sessions/{sid}")
    return out


def main() -> int:
    from fastapi.testclient import TestClient

    from quietframe.service.main import create_app
    from quietframe.service.settings import Settings

    settings = Settings(threads=2, workers=1)
    with TestClient(create_app(settings)) as client:
        models = sorted(m["name"] for m in client.get("/v1/models").json()["models"])
        for text in run(client, models):
            print(text, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
