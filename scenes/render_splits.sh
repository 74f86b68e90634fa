#!/usr/bin/env bash
# Render the g2 splits one after the other: test, validation (12 sequences x 8 frames, 256x256,
# 1,2,4,8 spp, 1024-spp references), then train (256-spp references). Every command resumes:
# finished frames are skipped, so re-running this script continues where it stopped.
#   nohup nice -n 10 scenes/render_splits.sh > ~/.cache/quietframe/logs/render_g2.log 2>&1 &
# PYTHON / PYTHONPATH select the interpreter and the checkout (default: `python` and the
# installed quietframe). TRAIN_SEQUENCES (default 120) sizes the train split.
set -u
PY=${PYTHON:-python}
JOBS=${JOBS:-2}
common=(--frames 8 --size 256x256 --spp 1,2,4,8 --jobs "$JOBS")
for split in test validation; do
    "$PY" -m quietframe.scenes.cli render --split "$split" --sequences 12 --reference-spp 1024 \
        "${common[@]}" || echo "split $split: some sequences failed (re-run to retry)"
done
"$PY" -m quietframe.scenes.cli render --split train --sequences "${TRAIN_SEQUENCES:-120}" \
    --reference-spp 256 "${common[@]}" || echo "split train: some sequences failed"
