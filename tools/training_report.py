"""Training curves and a summary table from quietframe-train run directories (log.txt).

    python tools/training_report.py RUN_DIR [RUN_DIR ...] --out docs

Writes <out>/training_curves.png (training loss and validation PSNR against the step, one
line per run) and prints a markdown table: run, variant, width, loss, steps, best val PSNR.
Figures come from the logs as written during training; nothing is recomputed.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path


@dataclass
class RunLog:
    name: str
    config: dict
    losses: list[tuple[int, float]]  # (step, smoothed training loss)
    validations: list[tuple[int, float]]  # (step, val PSNR dB)

    @property
    def best(self) -> tuple[int, float]:
        return max(self.validations, key=lambda v: v[1], default=(0, float("nan")))


def read_run(run: Path) -> RunLog:
    config = json.loads((run / "config.json").read_text())
    losses, validations = [], []
    for line in (run / "log.txt").read_text().splitlines():
        record = json.loads(line)
        if "loss" in record:
            losses.append((record["step"], record["loss"]))
        if "val_psnr" in record and record.get("val_sequences"):
            validations.append((record["step"], record["val_psnr"]))
    return RunLog(run.name, config, losses, validations)


def markdown_table(runs: list[RunLog]) -> str:
    lines = [
        "| run | variant | width | loss | steps | best val PSNR (1 spp, last frame) | at step |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        step, best = r.best
        last = r.losses[-1][0] if r.losses else 0
        lines.append(f"| {r.name} | {r.config['variant']} | {r.config['width']} | "
                     f"{r.config['loss']} | {last} | "
                     f"{best:.2f} | {step} |")
    return "\n".join(lines)


def plot(runs: list[RunLog], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_loss, ax_val) = plt.subplots(1, 2, figsize=(11, 4))
    for r in runs:
        if r.losses:
            steps, values = zip(*r.losses, strict=True)
            # losses of different kinds differ in scale: normalise by the first logged value
            ax_loss.plot(steps, [v / values[0] for v in values], label=r.name)
        if r.validations:
            steps, values = zip(*r.validations, strict=True)
            ax_val.plot(steps, values, marker=".", label=r.name)
    ax_loss.set(xlabel="step", ylabel="training loss / first logged loss", title="training")
    ax_val.set(xlabel="step", ylabel="PSNR dB", title="validation, 1 spp, last frame")
    for ax in (ax_loss, ax_val):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", type=Path, nargs="+")
    parser.add_argument("--out", type=Path, default=Path("docs"))
    args = parser.parse_args(argv)
    runs = [read_run(r) for r in args.runs]
    args.out.mkdir(parents=True, exist_ok=True)
    plot(runs, args.out / "training_curves.png")
    print(markdown_table(runs))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
