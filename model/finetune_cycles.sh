#!/usr/bin/env bash
# Fine-tune the shipped learned tiers (nbg-2l-3g, affinity-h16-k5gc) from their checkpoints in
# models/training/<name>/best.pt on the Mitsuba and Cycles train splits together: two runs side
# by side (one thread each), each resumable from its run directory. Score them with
# model/evaluate_cycles_mix.sh, ship one with model/ship_candidate.sh.
#   nohup nice -n 5 model/finetune_cycles.sh > ~/.cache/quietframe/logs/finetune.log 2>&1 &
# PYTHON: the interpreter (default python); RUNS: where runs go (default
# ~/.cache/quietframe/runs/cycles-mix); NBG_STEPS / AFFINITY_STEPS: schedule lengths (400, 600).
# Why fine-tuning: the shipped weights already hold what Mitsuba taught them, and a candidate
# ships only if it loses at most 0.2 dB on the Mitsuba test split; a short schedule at a third
# of the original learning rate moves them towards Cycles frames (camera-space normals,
# Blackman-Harris pixels, 16-64 spp) without starting over. Each run keeps its original data,
# loss, dropout and crop settings.
set -u
source "$(dirname "${BASH_SOURCE[0]}")/train_run.sh"
PY=${PYTHON:-python}
R=${RUNS:-$HOME/.cache/quietframe/runs/cycles-mix}
mkdir -p "$R"
run() {  # name, then quietframe-train flags
    local name=$1
    shift
    train_run "$R/$name" --init "models/training/$name/best.pt" --renderers mitsuba,cycles \
        --threads 1 --seed 1 "$@"
}
run nbg-2l-3g --steps "${NBG_STEPS:-400}" --eval-every 100 --lr 0.0003 --dropout 0.3 \
    --loss smape+temporal --crop 128 --frames 4 --batch 4 &
run affinity-h16-k5gc --steps "${AFFINITY_STEPS:-600}" --eval-every 150 --lr 0.00015 \
    --loss tau+temporal --crop 128 --frames 4 --batch 4 &
wait
