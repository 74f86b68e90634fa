#!/usr/bin/env bash
# Ship the affinity quality tier from its training run (model/train_affinity.sh), issue 15:
# export, keep the run's files, measure its tables on the validation split (for model=auto and
# the card), then the test-split evaluation next to OIDN and NBG and the auto bench (reports).
#   PYTHON=.venv/bin/python model/ship_affinity.sh [validation|test|all]
# Writes models/affinity-h24.{onnx,md}, models/training/affinity-h24/, docs/evaluation/
# {validation,auto_validation,absence_validation}_affinity.json, docs/benchmarks.{md,json},
# docs/psnr_vs_ms.png, docs/crops.png, docs/auto_choice.*, docs/affinity-sweep.md.
set -eu
PY=${PYTHON:-python}
R=${RUNS:-$HOME/.cache/quietframe/runs/g2}
RUN=$R/affinity-h24
NAME=affinity-h24
VERSION=${VERSION:-1}
STAGE=${1:-all}
T=${TMPDIR:-/tmp}/ship-$NAME
mkdir -p "$T"

if [ "$STAGE" = validation ] || [ "$STAGE" = all ]; then
    mkdir -p models/training/$NAME
    cp "$RUN"/{best.pt,checkpoint.pt,config.json,log.txt} models/training/$NAME/
    "$PY" -m quietframe.export.cli --checkpoint models/training/$NAME/best.pt \
        --out models/$NAME.onnx --version "$VERSION"
    # validation: per-spp PSNR/TRMAE and 720p ms (model=auto, the card), each kernel size and
    # the single-frame behaviour (docs/affinity.md)
    "$PY" -m quietframe.bench.evaluate --split validation --spp 1,2,4,8 --threads 2 \
        --methods $NAME --kernel-sizes 5,7,9,11,13 --single-frame $NAME --out "$T/val"
    "$PY" -m quietframe.bench.auto_choice --split validation --threads 2 --max-frames 3 \
        --buffer-sets all --no-absence --only $NAME --out "$T/pts"
    "$PY" -m quietframe.bench.auto_choice --split validation --threads 2 --max-frames 3 \
        --buffer-sets all --sequences 6 --spp 1,8 --only $NAME --out "$T/abs"
    cp "$T/val/benchmarks.json" docs/evaluation/validation_affinity.json
    cp "$T/pts/auto_choice.json" docs/evaluation/auto_validation_affinity.json
    cp "$T/abs/auto_choice.json" docs/evaluation/absence_validation_affinity.json
    "$PY" -m quietframe.export.cli --checkpoint models/training/$NAME/best.pt \
        --out models/$NAME.onnx --version "$VERSION" --card \
        --evaluation docs/evaluation/validation_affinity.json
    "$PY" -m quietframe.bench.model_metrics --evaluation docs/evaluation/validation_affinity.json \
        --noise-points docs/evaluation/auto_validation_affinity.json \
        --absent docs/evaluation/absence_validation_affinity.json models/$NAME.onnx
fi

if [ "$STAGE" = test ] || [ "$STAGE" = all ]; then
    "$PY" -m quietframe.bench.evaluate --split test --spp 1,2,4,8,16 --threads 2 --methods \
        noisy,accumulation,oidn-fast,oidn-high,nbg-2l-1g,nbg-2l-3g,nbg-7l-3g,oidn-temporal-acc,oidn-acc,oidn-fast-acc,oidn-frame,$NAME \
        --kernel-sizes 9,13 --single-frame $NAME --out docs
    "$PY" -m quietframe.bench.auto_choice --split test --threads 2 --max-frames 3 --sequences 6 \
        --spp 1,4,16 --out docs
    "$PY" -m quietframe.bench.affinity_sweep --kernel-sizes 5 9 13 --repeats 3 \
        --runs "$R/sweep" --out docs/affinity-sweep.md
fi
