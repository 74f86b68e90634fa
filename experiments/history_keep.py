"""How much history the accumulation keeps on locked-off shots (the question: is the
history rejected on static pixels, for example because the aux buffers are noisy at low spp?).

    python -m quietframe.experiments.history_keep --renderer cycles --split test-static
        [--spp 1,2,4,8,16,64] [--json keep.json]

On a locked-off shot (static camera and scene, animated seed) the surface behind every pixel is
the same in every frame, so a perfect surface test keeps every pixel's history. This runs the
accumulation the `*-acc` tiers ship (`model/temporal.accumulate`: nearest reprojection, the
depth and normal tests of `history_valid`, weights 1/n floored at MIN_CURRENT_WEIGHT) over each
sequence on the inputs as the runtime feeds them (`runtime.sanitize`), and prints per spp, over
pixels with geometry (a normal longer than 0.1; sky and empty pixels have none):

- `kept`: the share of (pixel, frame > 0) whose history passed the surface test;
- `depth fails` / `normal fails`: the share each test rejected (a pixel can fail both);
- `frames held`: the mean history count at the last frame (it saturates at 1/0.2 + 1 = 6,
  where the current frame's weight reaches its 0.2 floor; a perfect test: min(T, 6));
- `noise left`: the temporal standard deviation of the accumulated radiance over the second
  half of the frames, divided by the noisy input's, for pixels with geometry;
- `noise left, all kept`: the same with every frame's surface test passed (each frame is given
  frame 0's depth and normal), what a test that saw through the aux noise would leave.

No reference is needed: on a locked-off shot the input's change from frame to frame is noise.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
import torch

from quietframe.bench import cli_args
from quietframe.bench.evaluate import load_sequence, sequence_dirs
from quietframe.model import temporal
from quietframe.runtime.sanitize import sanitize_buffer

GEOMETRY_MIN_NORMAL = 0.1  # shorter normals: no surface (sky, empty pixels)
DEFAULT_SPP = "1,2,4,8,16,64"


def _planes(buffers: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """(1, C, H, W) tensors of what the runtime would feed: sanitised (H, W, C) buffers."""
    out = {}
    for name in ("color", "depth", "normal", "motion"):
        clean, _ = sanitize_buffer(name, buffers[name].transpose(2, 0, 1).astype(np.float32))
        out[name] = torch.from_numpy(np.ascontiguousarray(clean))[None]
    return out


def _run(frames: list[dict[str, torch.Tensor]], resets: list[bool], fixed_aux: bool):
    """Accumulated radiance per frame and, per frame, the keep / depth-ok / normal-ok masks."""
    first = frames[0]
    state = torch.zeros(1, temporal.STATE_CHANNELS, *first["color"].shape[-2:])
    outputs, masks = [], []
    for f, reset in zip(frames, resets, strict=True):
        aux = first if fixed_aux else f
        depth, normal = aux["depth"], aux["normal"]
        warped, inside = temporal.backward_warp(state, f["motion"], mode="nearest")
        depth_ok = temporal.history_valid(warped[:, temporal.DEPTH], normal, depth, normal)
        normal_ok = temporal.history_valid(depth, warped[:, temporal.NORMAL], depth, normal)
        acc, state = temporal.accumulate(f["color"], depth, normal, f["motion"],
                                         torch.tensor([float(reset)]), state)
        kept = state[:, temporal.HISTORY_LENGTH] > 1.5  # history length grew past this frame alone
        masks.append((kept, depth_ok * inside > 0, normal_ok * inside > 0))
        outputs.append(acc)
    return torch.cat(outputs), masks, state[:, temporal.HISTORY_LENGTH]


def measure_sequence(frames: list[dict[str, np.ndarray]], resets: list[bool]) -> dict:
    planes = [_planes(b) for b in frames]
    geometry = (planes[0]["normal"].norm(dim=1, keepdim=True) > GEOMETRY_MIN_NORMAL)
    acc, masks, count = _run(planes, resets, fixed_aux=False)
    ideal, _, ideal_count = _run(planes, resets, fixed_aux=True)
    later = [m for t, m in enumerate(masks) if t > 0 and not resets[t]]
    share = [float(sum((m[k] & geometry).sum() for m in later)) /
             max(1.0, float(geometry.sum()) * len(later)) for k in range(3)]
    half = len(frames) // 2
    noisy = torch.cat([p["color"] for p in planes])[half:]
    g = geometry[0, 0]

    def temporal_std(x: torch.Tensor) -> float:
        return float(x[half:].std(dim=0).mean(dim=0)[g].mean()) if len(x) > half else float("nan")

    noise = float(noisy.std(dim=0).mean(dim=0)[g].mean())
    return {
        "pixels_with_geometry": float(geometry.float().mean()),
        "kept": share[0],
        "depth_fails": 1 - share[1],
        "normal_fails": 1 - share[2],
        "frames_held": float(count[geometry].mean()),
        "frames_held_all_kept": float(ideal_count[geometry].mean()),
        "noise_left": temporal_std(acc) / noise,
        "noise_left_all_kept": temporal_std(ideal) / noise,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    cli_args.add_sequences(p, spp=DEFAULT_SPP)
    cli_args.add_json(p)
    args = p.parse_args(argv)
    folders = sequence_dirs(args.data, args.split, args.renderer, args.spp)
    if not folders:
        print(f"no finished sequences in {args.split} ({args.renderer}) under {args.data}",
              file=sys.stderr)
        return 1
    rows = []
    for spp in args.spp:
        per = []
        for folder in folders:
            seq = load_sequence(folder, spp)
            per.append(measure_sequence([b for b, _, _ in seq], [r for _, _, r in seq]))
        rows.append({"spp": spp, "sequences": [f.name for f in folders],
                     **{k: float(np.mean([s[k] for s in per])) for k in per[0]},
                     "per_sequence": per})
    print(f"{args.renderer} {args.split}: {len(folders)} locked-off sequence(s), "
          "pixels with geometry\n")
    print("| spp | kept | depth fails | normal fails | frames held (all kept) "
          "| noise left | noise left, all kept |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['spp']} | {r['kept']:.1%} | {r['depth_fails']:.1%} | {r['normal_fails']:.1%} "
              f"| {r['frames_held']:.2f} ({r['frames_held_all_kept']:.2f}) "
              f"| {r['noise_left']:.3f} | {r['noise_left_all_kept']:.3f} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
