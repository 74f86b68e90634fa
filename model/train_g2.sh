#!/usr/bin/env bash
# Train the NBG and oidn-temporal tiers on the g2 data: two queues side by side (one thread
# each, one per core), each run resumable from its run directory (re-running this script
# continues where it stopped).
#   nohup nice -n 10 model/train_g2.sh > ~/.cache/quietframe/logs/train_g2.log 2>&1 &
# Runs (in $RUNS, default ~/.cache/quietframe/runs/g2; their results: docs/training.md):
#   queue 1: nbg-2l-3g (SMAPE + temporal) and the same with the noise-unbiased loss
#            (relmse+temporal: the loss ablation); nbg-2l-1g and nbg-7l-3g without the firefly
#            clamp; nbg-7l-3g with the floored clamp (--outlier-floor 128: the shipped run);
#   queue 2: oidn-temporal-acc (the shipped run); nbg-2l-3g without the clamp (the clamp
#            ablation); oidn-temporal-fast-acc with the half-resolution parameter CNN
#            (--net-scale 2) and at full resolution (500 steps; no longer shipped); nbg-2l-3g
#            and nbg-2l-1g with the floored clamp (the shipped nbg-2l-1g; nbg-2l-3g's is the
#            start of its fine-tune on the mix, model/finetune_cycles.sh).
# NBG runs train with buffer dropout 0.3, so they also denoise frames that lack some buffers
# (down to the colour alone).
# PYTHON: the interpreter (default python); STEPS (default 800): the schedule length.
set -u
source "$(dirname "${BASH_SOURCE[0]}")/train_run.sh"
PY=${PYTHON:-python}
R=${RUNS:-$HOME/.cache/quietframe/runs/g2}
S=${STEPS:-800}
mkdir -p "$R"
run() {  # name, then quietframe-train flags
    local name=$1
    shift
    train_run "$R/$name" --steps "$S" --eval-every 250 --threads 1 "$@"
}
nbg=(--dropout 0.3)
(
    run nbg-2l-3g --variant nbg-2l-3g --width 16 "${nbg[@]}"
    run nbg-2l-3g-relmse --variant nbg-2l-3g --width 16 --loss relmse+temporal "${nbg[@]}"
    run nbg-2l-1g --variant nbg-2l-1g --outlier-sigmas 0 "${nbg[@]}"
    run nbg-7l-3g --variant nbg-7l-3g --outlier-sigmas 0 "${nbg[@]}"
    run nbg-7l-3g-floor --variant nbg-7l-3g --outlier-sigmas 3 --outlier-floor 128 "${nbg[@]}"
) &
(
    run oidn-temporal-acc --variant oidn-temporal-acc
    run nbg-2l-3g-noclamp --variant nbg-2l-3g --width 16 --outlier-sigmas 0 "${nbg[@]}"
    run oidn-temporal-fast-acc-half --variant oidn-temporal-fast-acc --net-scale 2
    S=500 run oidn-temporal-fast-acc --variant oidn-temporal-fast-acc
    run nbg-2l-3g-floor --variant nbg-2l-3g --width 16 --outlier-sigmas 3 --outlier-floor 128 \
        "${nbg[@]}"
    run nbg-2l-1g-floor --variant nbg-2l-1g --outlier-sigmas 3 --outlier-floor 128 "${nbg[@]}"
) &
wait
