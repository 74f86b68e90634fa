"""quietframe-export: write an NBG, oidn-temporal or affinity model (trained checkpoint or seeded
untrained) to ONNX. Its card (`<out>.md`, the measured table stamped from an evaluation) is
written afterwards by `python -m quietframe.bench.model_card --stamp` (export does not depend
on bench)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from quietframe.export.affinity_export import export_affinity
from quietframe.export.onnx_export import export_nbg, export_oidn_only
from quietframe.model import affinity, families, oidn_temporal, output_history
from quietframe.model.nbg import AccumulationDenoiser, NBGDenoiser


def carried_metrics(old: Path, training: dict) -> tuple[dict, dict]:
    """(training notes, measured tables) for a new version of the model in `old`: its tables,
    and in the notes the version that measured them."""
    import onnx

    props = {p.key: p.value for p in onnx.load(str(old), load_external_data=False).metadata_props}
    metrics = json.loads(props.get("quietframe.metrics", "{}"))
    # Tables carried before were measured by an earlier version still: name that one.
    measured = json.loads(props.get("quietframe.training", "{}")).get(
        "tables_measured_with_version", props.get("quietframe.version", "?"))
    return {**training, "tables_measured_with_version": measured}, metrics


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="quietframe-export", description=__doc__)
    parser.add_argument("--variant", default="nbg-2l-3g",
                        help="architecture when untrained (nbg-…, oidn-temporal-…, affinity-…); "
                             "'accumulation' = the pre-stage alone, 'aligned-accumulation' = "
                             "the same kept only under pixel-aligned motion; oidn-acc, "
                             "oidn-fast-acc = OIDN on the accumulation, no learned stage; "
                             "oidn-history, oidn-fast-history = OIDN on the aligned "
                             "accumulation, then a history of OIDN's output")
    parser.add_argument("--checkpoint", type=Path, help="training checkpoint (.pt)")
    parser.add_argument("--width", type=int, help="GuideNet width (untrained only)")
    parser.add_argument("--seed", type=int, default=0, help="initialisation seed (untrained)")
    parser.add_argument("--version", default="0")
    parser.add_argument("--out", type=Path, required=True, help="output .onnx path")
    parser.add_argument("--metrics-from", type=Path, metavar="OLD.onnx",
                        help="carry the measured tables of an earlier version of this model "
                             "into the new file (its training notes say which version measured "
                             "them), for a change the tables could not yet be measured again for")
    parser.add_argument("--resampled-weight-per-doubling", type=float, metavar="W",
                        help="NBG or affinity checkpoint: the resampled history fades with "
                             "the frame's spp (NBGConfig / AffinityConfig."
                             "resampled_weight_per_doubling; no weights, so a trained model "
                             "takes it as it is)")
    parser.add_argument("--albedo-prefilter", type=float, metavar="SIGMA",
                        help="NBG or affinity checkpoint: the albedo is blurred by SIGMA px at "
                             "1 spp, less at more, before demodulation (NBGConfig / "
                             "AffinityConfig.albedo_prefilter; no weights)")
    args = parser.parse_args(argv)
    overrides = {k: v for k, v in (("resampled_weight_per_doubling",
                                    args.resampled_weight_per_doubling),
                                   ("albedo_prefilter", args.albedo_prefilter)) if v is not None}
    if overrides and not args.checkpoint:
        parser.error("--resampled-weight-per-doubling and --albedo-prefilter apply to a "
                     "--checkpoint")

    if args.variant in oidn_temporal.OIDN_ONLY_VARIANTS and not args.checkpoint:
        path = export_oidn_only(oidn_temporal.OIDN_ONLY_VARIANTS[args.variant], args.out,
                                version=args.version)
        print(f"wrote {path}")
        return 0
    if args.variant in ("accumulation", "aligned-accumulation") and not args.checkpoint:
        model = AccumulationDenoiser(aligned_history=args.variant == "aligned-accumulation")
        training, metrics = {"trained": False}, {}
        if args.metrics_from:
            training, metrics = carried_metrics(args.metrics_from, training)
    elif args.variant in output_history.VARIANTS and not args.checkpoint:
        model = output_history.OutputHistory(output_history.VARIANTS[args.variant])
        training, metrics = {"trained": False, "learned_stage": False}, {}
        if args.metrics_from:
            training, metrics = carried_metrics(args.metrics_from, training)
    elif args.checkpoint:
        model, checkpoint = families.load_checkpoint(args.checkpoint, **overrides)
        if overrides and not isinstance(model, NBGDenoiser | affinity.AffinityDenoiser):
            parser.error("--resampled-weight-per-doubling and --albedo-prefilter apply to an "
                         "NBG or affinity checkpoint")
        training, metrics = checkpoint.get("training", {}), checkpoint.get("metrics", {})
        if args.metrics_from:  # the old tables, with this checkpoint's own selection record
            training, carried = carried_metrics(args.metrics_from, training)
            metrics = {**carried, **metrics}
    else:
        family = families.family_of_variant(args.variant)
        torch.manual_seed(args.seed)
        model = family.variant(args.variant, **({"width": args.width} if args.width else {}))
        training, metrics = {"trained": False, "seed": args.seed}, {}
    export = export_affinity if isinstance(model, affinity.AffinityDenoiser) else export_nbg
    path = export(model, args.out, version=args.version, training=training, metrics=metrics)
    print(f"wrote {path} ({path.stat().st_size / 1024:.0f} KiB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
