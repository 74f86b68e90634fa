#!/usr/bin/env bash
# Measure one retrained model beside the shipped one it replaces, and ship it: for a candidate
# from any training run (model/finetune_cycles.sh, a new run of model/train_g2.sh), with every
# figure from runs of this script.
#   NAME=affinity-h16-k5gc RUN=~/.cache/quietframe/runs/affinity-h16-k5gc-clamp VERSION=3 \
#     PYTHON=.venv/bin/python model/ship_candidate.sh export|measure|timing|test|ship
#   NAME:    the shipped model it replaces (models/$NAME.onnx, models/training/$NAME/);
#   RUN:     the run directory (best.pt, config.json, log.txt);
#   VERSION: the version the shipped file gets (the shipped card's + 1).
# Stages, in order (each run's figures under $OUT, default docs/evaluation/$NAME-v$VERSION):
#   export:  RUN/best.pt -> $OUT/candidate/$NAME-candidate.onnx (named so that every run below
#            scores it as its own method beside the shipped model);
#   measure: validation, both renderers, 1-64 spp, and their locked-off shots (the tables `auto`
#            reads: model selection's split), with Blender's denoise on Cycles (auto's floor);
#            on Mitsuba also the noise points and buffer-absence figures (bench/auto_choice);
#   timing:  720p time on each renderer's frames beside oidn-frame (nothing else running);
#   test:    both test splits with the shipped model, the candidate and oidn-frame (and Blender's
#            denoise) in one run each, and a before/after table (quietframe-eval --compare);
#   ship:    install the candidate under NAME with both renderers' tables stamped from the
#            measure and timing runs (bench/model_card --stamp --measured-as), then its card.
set -eu
PY=${PYTHON:-python}
NAME=${NAME:?the shipped model to replace}
RUN=${RUN:?the training run directory}
VERSION=${VERSION:?the version to ship as}
OUT=${OUT:-docs/evaluation/$NAME-v$VERSION}
SPP=1,2,4,8,16,64
CANDIDATE=$NAME-candidate
ONNX=$OUT/candidate/$CANDIDATE.onnx
STAGE=${1:?export, measure, timing, test or ship}
evaluate() {  # renderer split methods out [more args]
    local renderer=$1 split=$2 methods=$3 out=$4
    shift 4
    "$PY" -m quietframe.bench.evaluate --renderer "$renderer" --split "$split" --spp "$SPP" \
        --threads 2 --methods "$methods" --model "$ONNX" --out "$out" "$@"
}
case "$STAGE" in
export)
    mkdir -p "$OUT/candidate"
    "$PY" -m quietframe.export.cli --checkpoint "$RUN/best.pt" --out "$ONNX" --version "$VERSION"
    ;;
measure)
    for split in validation validation-static; do
        evaluate mitsuba "$split" "$CANDIDATE" "$OUT/mitsuba-$split" --no-timing
        evaluate cycles "$split" "blender-denoise,$CANDIDATE" "$OUT/cycles-$split" --no-timing
    done
    "$PY" -m quietframe.bench.auto_choice --split validation --threads 2 --max-frames 3 \
        --buffer-sets all --no-absence --model "$ONNX" --only "$CANDIDATE" \
        --out "$OUT/mitsuba-noise-points"
    "$PY" -m quietframe.bench.auto_choice --split validation --threads 2 --max-frames 3 \
        --buffer-sets all --sequences 6 --spp 1,8 --model "$ONNX" --only "$CANDIDATE" \
        --out "$OUT/mitsuba-absence"
    ;;
timing)
    for renderer in mitsuba cycles; do
        "$PY" -m quietframe.bench.evaluate --renderer "$renderer" --split validation \
            --sequences 1 --spp 1 --threads 2 --methods "oidn-frame,$CANDIDATE" \
            --model "$ONNX" --out "$OUT/timing-$renderer"
    done
    ;;
test)
    evaluate mitsuba test "oidn-frame,$NAME,$CANDIDATE" "$OUT/mitsuba-test" --no-timing
    evaluate cycles test "blender-denoise,oidn-frame,$NAME,$CANDIDATE" "$OUT/cycles-test" \
        --no-timing
    for renderer in mitsuba cycles; do
        "$PY" -m quietframe.bench.evaluate --compare "$OUT/$renderer-test/benchmarks.json" --wide \
            --methods "$CANDIDATE" --against "$NAME" > "$OUT/$renderer-test/before_after.md"
    done
    ;;
ship)
    rm -f "models/training/$NAME/checkpoint.pt"  # a fine-tune keeps no resumable state of its own
    cp "$RUN"/{best.pt,config.json,log.txt} "models/training/$NAME/"
    "$PY" -m quietframe.export.cli --checkpoint "models/training/$NAME/best.pt" \
        --out "models/$NAME.onnx" --version "$VERSION"
    "$PY" -m quietframe.bench.model_card --stamp --no-card "models/$NAME.onnx" \
        --measured-as "$CANDIDATE" --renderer mitsuba \
        --evaluation "$OUT/mitsuba-validation/benchmarks.json" \
        --static-evaluation "$OUT/mitsuba-validation-static/benchmarks.json" \
        --noise-points "$OUT/mitsuba-noise-points/auto_choice.json" \
        --absent "$OUT/mitsuba-absence/auto_choice.json" \
        --timing "$OUT/timing-mitsuba/benchmarks.json"
    "$PY" -m quietframe.bench.model_card --stamp --no-card "models/$NAME.onnx" \
        --measured-as "$CANDIDATE" --renderer cycles \
        --evaluation "$OUT/cycles-validation/benchmarks.json" \
        --static-evaluation "$OUT/cycles-validation-static/benchmarks.json" \
        --timing "$OUT/timing-cycles/benchmarks.json"
    "$PY" -m quietframe.bench.model_card "models/$NAME.onnx" --measured-as "$CANDIDATE" \
        --evaluation "$OUT/mitsuba-validation/benchmarks.json"
    rm -r "$OUT/candidate"  # shipped now: models/$NAME.onnx is the same export
    ;;
*) echo "unknown stage $STAGE" >&2; exit 2 ;;
esac
