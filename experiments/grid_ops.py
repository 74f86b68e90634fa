"""Micro-benchmark: bilateral splat + slice at 1280×720, custom ops vs PyTorch; and the temporal
reprojection (BackwardWarp custom op vs onnxruntime's GridSample).

python -m quietframe.experiments.grid_ops [--threads 2] [--guide smooth|random|both] [--repeats 15]
                                   [--no-torch] [--warp]

Times splat followed by slice (same guide) for each grid scale (σs, σr) of the NBG denoiser and
for all three grids, on a 3-channel HDR image with one guide per grid:
- onnxruntime: one graph of BilateralSplat -> BilateralSlice nodes per case (the grid stays inside
  onnxruntime, as in an exported model), inputs and outputs bound once (no copies in the loop),
  intra_op_num_threads = threads;
- PyTorch: quietframe.model.grid.splat_forward / slice_forward with torch.set_num_threads(threads).
Figures are medians (bench/timing.py). The functions return plain dicts so that bigger benchmarks
can reuse them.

--warp times the two warps of the NBG pre-stage (model/temporal.py: bilinear on the 8-channel
state, nearest on 4 of its channels) as one graph, ai.quietframe::BackwardWarp against the
standard GridSample nodes the model was exported with before, for a static camera, smooth motion
and per-pixel random motion (the gather-bound worst case).
"""

from __future__ import annotations

import argparse

import numpy as np

from quietframe.bench import cli_args
from quietframe.bench.timing import Timing, time_ms, timing_table
from quietframe.runtime.ops_library import OPS_DOMAIN, ops_library_path

HEIGHT, WIDTH = 720, 1280
SCALES = ((4, 4.0), (8, 8.0), (16, 16.0))  # (σs, σr) of the three grids


def range_cells(sigma_r: float) -> int:
    """D = floor(255/σr - 0.5) + 3 (docs/grid-math.md); here to keep the bench torch-free."""
    return int(np.floor(255.0 / sigma_r - 0.5)) + 3


def make_inputs(height: int = HEIGHT, width: int = WIDTH, guide: str = "smooth", seed: int = 0
                ) -> tuple[np.ndarray, list[np.ndarray]]:
    """An HDR image (1, 3, H, W) and one guide (1, 1, H, W) per grid scale.

    "smooth": guides vary slowly across the frame with a little noise, like a GuideNet output;
    "random": uniform noise, every pixel in a random range cell (the cache-unfriendly worst case).
    """
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width] / max(height, width)
    base = 0.5 + 0.3 * np.sin(6 * xx + 2 * yy)[None]
    image = base * rng.lognormal(0.0, 0.7, (3, height, width))  # noisy radiance, ≥ 0
    guides = []
    for k in range(len(SCALES)):
        if guide == "random":
            g = rng.random((height, width))
        elif guide == "smooth":
            g = 0.5 + 0.35 * np.sin((k + 2) * xx - 3 * yy) + 0.03 * rng.standard_normal(xx.shape)
        else:
            raise ValueError(f"guide must be 'smooth' or 'random', got {guide!r}")
        guides.append(np.clip(g, 0, 1)[None, None].astype(np.float32))
    return image[None].astype(np.float32), guides


def grid_graph(scales) -> bytes:
    """ONNX model: image, guide_i -> splat -> slice -> out_i for each (σs, σr) in `scales`."""
    from onnx import TensorProto, helper

    def value(name, channels):
        return helper.make_tensor_value_info(name, TensorProto.FLOAT, [1, channels, "H", "W"])

    nodes, guides, outputs = [], [], []
    for i, (sigma_s, sigma_r) in enumerate(scales):
        attrs = {"sigma_s": sigma_s, "sigma_r": float(sigma_r), "grid_depth": range_cells(sigma_r)}
        nodes.append(helper.make_node("BilateralSplat", ["image", f"guide_{i}"],
                                      [f"grid_{i}", f"weight_{i}"], domain=OPS_DOMAIN, **attrs))
        nodes.append(helper.make_node("BilateralSlice", [f"grid_{i}", f"weight_{i}", f"guide_{i}"],
                                      [f"out_{i}"], domain=OPS_DOMAIN, **attrs))
        guides.append(value(f"guide_{i}", 1))
        outputs.append(value(f"out_{i}", 3))
    graph = helper.make_graph(nodes, "grid_ops", [value("image", 3), *guides], outputs)
    opsets = [helper.make_opsetid("", 17), helper.make_opsetid(OPS_DOMAIN, 1)]
    # IR 9 = onnx 1.15, which every supported onnxruntime (>= 1.16) reads.
    return helper.make_model(graph, opset_imports=opsets, ir_version=9).SerializeToString()


def ort_runner(scales, image: np.ndarray, guides: list[np.ndarray], threads: int):
    """A no-argument callable that runs the splat/slice graph of `scales` once."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.register_custom_ops_library(str(ops_library_path()))
    session = ort.InferenceSession(grid_graph(scales), options,
                                   providers=["CPUExecutionProvider"])
    binding = session.io_binding()
    values = {"image": ort.OrtValue.ortvalue_from_numpy(image)}  # kept alive with the runner
    for i in range(len(scales)):
        values[f"guide_{i}"] = ort.OrtValue.ortvalue_from_numpy(guides[i])
        values[f"out_{i}"] = ort.OrtValue.ortvalue_from_numpy(np.empty_like(image))
    for name, value in values.items():
        if name.startswith("out_"):
            binding.bind_ortvalue_output(name, value)
        else:
            binding.bind_ortvalue_input(name, value)
    return lambda: (values, session.run_with_iobinding(binding))


def torch_runner(scales, image: np.ndarray, guides: list[np.ndarray], threads: int):
    """The same work through quietframe.model.grid (no autograd)."""
    import torch

    from quietframe.model import grid

    torch.set_num_threads(threads)
    x = torch.from_numpy(image)
    gs = [torch.from_numpy(g) for g in guides]

    def run():
        with torch.no_grad():
            for i, (sigma_s, sigma_r) in enumerate(scales):
                g, w = grid.splat_forward(x, gs[i], sigma_s, sigma_r)
                grid.slice_forward(g, w, gs[i], sigma_s, sigma_r)

    return run


def measure(threads: int = 2, guide: str = "smooth", repeats: int = 15, warmup: int = 3,
            height: int = HEIGHT, width: int = WIDTH, backends=("onnxruntime", "torch"),
            torch_repeats: int = 5) -> dict[str, dict[str, Timing]]:
    """{case: {backend: Timing}} for cases "sigma_s=4", "sigma_s=8", "sigma_s=16", "all".

    PyTorch takes seconds per call, so it gets `torch_repeats` timed calls after one warm-up.
    A backend that cannot be imported (torch on a serving install) is left out.
    """
    image, guides = make_inputs(height, width, guide)
    cases = {f"sigma_s={s}": [(s, r)] for s, r in SCALES} | {"all": list(SCALES)}
    runners = {"onnxruntime": ort_runner, "torch": torch_runner}
    results: dict[str, dict[str, Timing]] = {case: {} for case in cases}
    for backend in backends:
        for case, scales in cases.items():
            index = [SCALES.index(s) for s in scales]
            try:
                run = runners[backend](scales, image, [guides[i] for i in index], threads)
            except ImportError:
                break
            if backend == "torch":
                results[case][backend] = time_ms(run, warmup=1, repeats=torch_repeats)
            else:
                results[case][backend] = time_ms(run, warmup=warmup, repeats=repeats)
    return results


def report(threads: int = 2, guide: str = "smooth", repeats: int = 15,
           backends=("onnxruntime", "torch")) -> str:
    """Markdown table of `measure`: ms per splat+slice call, median wall time (minimum; median
    process CPU time, all threads). On a busy machine the fastest call, and CPU / threads, say
    more about the code than the median does."""
    results = measure(threads=threads, guide=guide, repeats=repeats, backends=backends)
    backends = sorted({b for r in results.values() for b in r}, key=["onnxruntime", "torch"].index)
    title = (f"splat + slice, {WIDTH}x{HEIGHT}, 3 channels, {guide} guides, {threads} threads, "
             f"ms per call: median wall (min; CPU) of {repeats} calls (PyTorch: of 5)")
    labels = {f"sigma_s={s}": f"({s}, {r:g})" for s, r in SCALES} | {"all": "all three"}
    rows = {labels[case]: timings for case, timings in results.items()}
    return timing_table(title, "grid (σs, σr)", backends, rows)


WARP_CHANNELS = ((8, "bilinear"), (4, "nearest"))  # the pre-stage's two warps


def warp_motion(kind: str, height: int = HEIGHT, width: int = WIDTH, seed: int = 0) -> np.ndarray:
    """Motion (1, 2, H, W) in pixels: "static", "smooth" (a slow pan with some zoom and swirl,
    like a camera move) or "random" (independent per pixel, N(0, 3²): no two neighbours alike)."""
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    if kind == "static":
        return np.zeros((1, 2, height, width), np.float32)
    if kind == "smooth":
        mx = 1.3 + 2.0 * np.sin(xx / 200) + 0.01 * (yy - height / 2)
        my = -0.7 + 1.5 * np.cos(yy / 150) - 0.005 * (xx - width / 2)
        return np.stack((mx, my))[None].astype(np.float32)
    if kind == "random":
        rng = np.random.default_rng(seed)
        return (3 * rng.standard_normal((1, 2, height, width))).astype(np.float32)
    raise ValueError(f"motion must be 'static', 'smooth' or 'random', got {kind!r}")


def warp_graph(op: str) -> bytes:
    """ONNX model of the pre-stage's warps: image_i (1, C_i, H, W) and motion -> warped_i.

    op "BackwardWarp": our custom op (its inside masks are outputs too, as in the model);
    op "GridSample": the standard op on a precomputed sampling grid (1, H, W, 2) in [-1, 1].
    """
    from onnx import TensorProto, helper

    def value(name, shape):
        return helper.make_tensor_value_info(name, TensorProto.FLOAT, shape)

    nodes, inputs, outputs = [], [], []
    for i, (channels, mode) in enumerate(WARP_CHANNELS):
        inputs.append(value(f"image_{i}", [1, channels, "H", "W"]))
        outputs.append(value(f"warped_{i}", [1, channels, "H", "W"]))
        if op == "BackwardWarp":
            outputs.append(value(f"inside_{i}", [1, 1, "H", "W"]))
            nodes.append(helper.make_node(
                "BackwardWarp", [f"image_{i}", "motion"], [f"warped_{i}", f"inside_{i}"],
                domain=OPS_DOMAIN, mode=["bilinear", "nearest"].index(mode)))
        else:
            nodes.append(helper.make_node(
                "GridSample", [f"image_{i}", "grid"], [f"warped_{i}"],
                mode="linear" if mode == "bilinear" else mode, padding_mode="border",
                align_corners=0))
    inputs.append(value("motion", [1, 2, "H", "W"]) if op == "BackwardWarp"
                  else value("grid", [1, "H", "W", 2]))
    graph = helper.make_graph(nodes, "warp", inputs, outputs)
    opsets = [helper.make_opsetid("", 20), helper.make_opsetid(OPS_DOMAIN, 1)]
    return helper.make_model(graph, opset_imports=opsets, ir_version=9).SerializeToString()


def warp_runner(op: str, motion: np.ndarray, threads: int, seed: int = 0):
    """A no-argument callable that runs the warp graph of `op` once on a random state."""
    import onnxruntime as ort

    _, _, height, width = motion.shape
    rng = np.random.default_rng(seed)
    feeds = {f"image_{i}": rng.random((1, c, height, width), dtype=np.float32)
             for i, (c, _) in enumerate(WARP_CHANNELS)}
    if op == "BackwardWarp":
        feeds["motion"] = motion
    else:  # pixel centre p + motion -> (2(p + motion) + 1)/size - 1, as model/temporal.py
        yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
        gx = (2 * (xx + motion[0, 0]) + 1) / width - 1
        gy = (2 * (yy + motion[0, 1]) + 1) / height - 1
        feeds["grid"] = np.stack((gx, gy), axis=-1)[None].astype(np.float32)
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.register_custom_ops_library(str(ops_library_path()))
    session = ort.InferenceSession(warp_graph(op), options, providers=["CPUExecutionProvider"])
    binding = session.io_binding()
    values = {name: ort.OrtValue.ortvalue_from_numpy(array) for name, array in feeds.items()}
    for name, value in values.items():
        binding.bind_ortvalue_input(name, value)
    for output in session.get_outputs():
        binding.bind_output(output.name)  # allocated by onnxruntime on the first run, then reused
    return lambda: (values, session.run_with_iobinding(binding))


def measure_warp(threads: int = 2, repeats: int = 15, warmup: int = 3,
                 motions=("static", "smooth", "random"),
                 ops=("BackwardWarp", "GridSample")) -> dict[str, dict[str, Timing]]:
    """{motion: {op: Timing}} for both warps of one 720p frame."""
    results: dict[str, dict[str, Timing]] = {}
    for kind in motions:
        motion = warp_motion(kind)
        results[kind] = {op: time_ms(warp_runner(op, motion, threads), warmup=warmup,
                                     repeats=repeats) for op in ops}
    return results


def warp_report(threads: int = 2, repeats: int = 15) -> str:
    """Markdown table of `measure_warp`: ms per frame, median wall time (minimum; CPU)."""
    results = measure_warp(threads=threads, repeats=repeats)
    ops = ("BackwardWarp", "GridSample")
    title = (f"temporal warps (8 channels bilinear + 4 nearest), {WIDTH}x{HEIGHT}, {threads} "
             f"threads, ms per frame: median wall (min; CPU) of {repeats} calls")
    return timing_table(title, "motion", ops, results)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    cli_args.add_threads(parser)
    parser.add_argument("--guide", choices=["smooth", "random", "both"], default="both")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--no-torch", action="store_true", help="time the custom ops only")
    parser.add_argument("--warp", action="store_true",
                        help="time the temporal warps instead of splat + slice")
    args = parser.parse_args(argv)
    if args.warp:
        print(warp_report(threads=args.threads, repeats=args.repeats))
        return 0
    backends = ("onnxruntime",) if args.no_torch else ("onnxruntime", "torch")
    for guide in ["smooth", "random"] if args.guide == "both" else [args.guide]:
        print(report(threads=args.threads, guide=guide, repeats=args.repeats, backends=backends))
        print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
