"""Does the stored form of a session's state (service/state_codec.py) change what the history
tiers make? Each tier runs every Cycles zoo shot (validation and test) and the g2 test sequence
twice: its state kept in memory between frames, and its state written to the stored form and
read back between frames (what a replica that loads the session from a store continues from).

    python -m quietframe.experiments.state_codec [--spp 1,4,16,64] [--threads 2] [--json rows.json]
        [--models oidn-history-cleanaux,oidn-history,oidn-fast-history,nbg-2l-3g] [--shots a,b]

Prints, per tier, shot and spp: mean PSNR (tone-mapped, as everywhere) of both runs and their
difference, TRMAE's, and on a locked-off shot the flicker of both; then the worst differences
and the stored bytes per pixel of the last frame's state (all planes, as both stores write
them) against the float32 form's. Cuts are not flagged (as bench/zoo_eval.py).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from quietframe.bench.cli_args import add_data, add_json, add_threads
from quietframe.bench.evaluate import Scores, give_header_spp, load_sequence, run_sequence
from quietframe.bench.harness import RuntimeMethod, planar_frames
from quietframe.runtime import find_model
from quietframe.scenes.zoo_shots import ZOO_VERSION
from quietframe.service import state_codec

MODELS = ("oidn-history-cleanaux", "oidn-history", "oidn-fast-history", "nbg-2l-3g")
G2_TEST = Path("g2-cycles") / "test" / "7000000"


class StoredState(RuntimeMethod):
    """The runtime with its state written to the stored form and read back after each frame."""

    stored_bytes = 0
    float32_bytes = 0

    def __call__(self, planes):
        color = super().__call__(planes)
        state = self.state
        assert state is not None
        encoded = state_codec.encode(state)
        shapes = {name: tensor.shape for name, tensor in state.items()}
        self.state = state_codec.decode(encoded.layout, encoded.planes, shapes)
        self.stored_bytes = sum(p.size for p in encoded.planes)
        self.float32_bytes = sum(t.nbytes for t in state.values())
        return color


def sequences(data: Path) -> list[tuple[str, Path, bool]]:
    """(name, folder, locked off) of every zoo shot and the g2 test sequence."""
    data, out = data.expanduser(), []
    for manifest in sorted(data.glob(f"{ZOO_VERSION}-cycles/*/*/manifest.json")):
        zoo = json.loads(manifest.read_text())["zoo"]
        out.append((zoo["name"], manifest.parent, zoo["camera"] == "locked"))
    g2 = data / G2_TEST
    if (g2 / "manifest.json").is_file():
        config = json.loads((g2 / "manifest.json").read_text())["config"]
        out.append((f"g2/{g2.name}", g2, bool(config.get("locked_off"))))
    return out


def score(method, frames, locked: bool) -> dict[str, float]:
    scores = Scores()
    run_sequence(method, frames, scores, None, locked)
    return scores.summary()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_data(p)
    add_threads(p)
    add_json(p)
    p.add_argument("--spp", default="1,4,16,64")
    p.add_argument("--models", default=",".join(MODELS))
    p.add_argument("--shots", default="", help="comma list of shot names (default: all)")
    args = p.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    found = [f for f in sequences(args.data)
             if not args.shots or f[0] in args.shots.split(",")]
    if not found:
        raise SystemExit(f"no Cycles zoo shots or g2 test sequence under {args.data}")
    rows = []
    print("| model | shot | spp | PSNR memory | PSNR stored | Δ dB | ΔTRMAE | flicker memory "
          "| flicker stored | stored B/px | float32 B/px |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name in args.models.split(","):
        path = find_model(name)  # a name, or a path to an .onnx file
        model = path.stem
        memory = RuntimeMethod(path, args.threads, renderer="cycles")
        stored = StoredState(memory.denoiser, renderer="cycles")
        for name, folder, locked in found:
            for spp in (int(s) for s in args.spp.split(",")):
                frames = planar_frames(load_sequence(folder, spp))
                frames = [(p_, r, i == 0) for i, (p_, r, _) in enumerate(frames)]
                a, b = {}, {}
                for method, out in ((memory, a), (stored, b)):
                    give_header_spp(method, "cycles", spp)
                    out.update(score(method, frames, locked))
                pixels = frames[0][1].shape[0] * frames[0][1].shape[1]
                row = {"model": model, "shot": name, "spp": spp, "locked": locked,
                       "psnr_memory": a["psnr"], "psnr_stored": b["psnr"],
                       "delta_db": b["psnr"] - a["psnr"], "delta_trmae": b["trmae"] - a["trmae"],
                       "flicker_memory": a["flicker"], "flicker_stored": b["flicker"],
                       "stored_bytes_px": stored.stored_bytes / pixels,
                       "float32_bytes_px": stored.float32_bytes / pixels}
                rows.append(row)
                flicker = (f"{a['flicker']:.5f} | {b['flicker']:.5f}" if locked else "– | –")
                print(f"| {model} | {name} | {spp} | {a['psnr']:.3f} | {b['psnr']:.3f} | "
                      f"{row['delta_db']:+.4f} | {row['delta_trmae']:+.5f} | {flicker} | "
                      f"{row['stored_bytes_px']:.2f} | {row['float32_bytes_px']:.1f} |",
                      flush=True)
    print()
    for model in dict.fromkeys(r["model"] for r in rows):
        mine = [r for r in rows if r["model"] == model]
        worst = max(mine, key=lambda r: abs(r["delta_db"]))
        flick = [abs(r["flicker_stored"] / r["flicker_memory"] - 1) for r in mine if r["locked"]]
        trmae = max(abs(r["delta_trmae"]) for r in mine)
        print(f"{model}: worst |Δ PSNR| {abs(worst['delta_db']):.4f} dB ({worst['shot']}, "
              f"{worst['spp']} spp); mean Δ {np.mean([r['delta_db'] for r in mine]):+.5f} dB; "
              f"worst locked-off flicker change {100 * max(flick, default=0):.3f}%; worst "
              f"|Δ TRMAE| {trmae:.5f}; stored "
              f"{np.mean([r['stored_bytes_px'] for r in mine]):.2f} B/px (float32 form "
              f"{mine[0]['float32_bytes_px']:.1f})")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
