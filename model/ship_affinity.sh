#!/usr/bin/env bash
# Install a new affinity model from a training run (model/train_affinity.sh). A retrained model
# that replaces a shipped one goes through model/ship_candidate.sh instead.
#   RUN=~/.cache/quietframe/runs/g2/s6/affinity-h16-k5gc-tau NAME=affinity-h16-k5gc \
#       PYTHON=.venv/bin/python model/ship_affinity.sh evaluate|ship
# Stages:
#   evaluate: keep the run's files in models/training/$NAME/, export it outside models/, and
#             evaluate it on the test split next to OIDN and NBG (docs/benchmarks.*, the
#             scatter, the crops); re-time the width table (docs/affinity-sweep.md; SWEEP=0
#             skips it);
#   ship:     install it in models/ with its measured validation tables (model=auto, the card)
#             — for a run that earns its place next to NBG and OIDN (docs/affinity.md).
# RUN: the run directory; NAME: the model's name in models/ and the reports (the run's
# variant); VERSION: the card's version (default 1); RUNS: the width sweep's runs (default
# ~/.cache/quietframe/runs/g2, <RUNS>/sweep).
set -eu
PY=${PYTHON:-python}
R=${RUNS:-$HOME/.cache/quietframe/runs/g2}
RUN=${RUN:?the training run directory}
NAME=${NAME:?the model name in models/}
VERSION=${VERSION:-1}
STAGE=${1:?evaluate or ship}
T=${TMPDIR:-/tmp}/ship-$NAME
mkdir -p "$T"

if [ "$STAGE" = evaluate ]; then
    mkdir -p models/training/$NAME
    cp "$RUN"/{best.pt,checkpoint.pt,config.json,log.txt} models/training/$NAME/
    "$PY" -m quietframe.export.cli --checkpoint models/training/$NAME/best.pt \
        --out "$T/$NAME.onnx" --version "$VERSION"
    "$PY" -m quietframe.bench.evaluate --split test --spp 1,2,4,8,16 --threads 2 --methods \
        noisy,accumulation,oidn-fast,oidn-high,nbg-2l-1g,nbg-2l-3g,nbg-7l-3g,oidn-temporal-acc,oidn-acc,oidn-fast-acc,oidn-frame,$NAME \
        --model "$T/$NAME.onnx" --kernel-sizes 9,13 --single-frame $NAME --out "$T/test"
    cp "$T"/test/{benchmarks.md,benchmarks.json,psnr_vs_ms.png,crops.png} docs/
    # the auto bench's section (its own run, docs/auto_choice.json) goes back into the report
    "$PY" -c "import json, pathlib; from quietframe.bench import auto_choice as a; \
r = json.loads(pathlib.Path('docs/auto_choice.json').read_text()); \
a.update_section(pathlib.Path('docs/benchmarks.md'), a.section(r, list(r['rows'][0]['fixed'])))"
    if [ "${SWEEP:-1}" != 0 ]; then
        "$PY" -m quietframe.experiments.affinity_sweep --kernel-sizes 5 9 13 --repeats 3 \
            --runs "$R/sweep" --out docs/affinity-sweep.md
    fi
fi

if [ "$STAGE" = ship ]; then
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
        --out models/$NAME.onnx --version "$VERSION"
    "$PY" -m quietframe.bench.model_card --stamp \
        --evaluation docs/evaluation/validation_affinity.json \
        --noise-points docs/evaluation/auto_validation_affinity.json \
        --absent docs/evaluation/absence_validation_affinity.json models/$NAME.onnx
fi
