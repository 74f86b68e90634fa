#!/usr/bin/env bash
# Train the affinity tier: two queues side by side (one thread each, one per core), each run
# resumable from its run directory (re-running continues where it stopped).
#   nohup nice -n 10 model/train_affinity.sh k5 > ~/.cache/quietframe/logs/train_affinity.log 2>&1 &
# `k5`: the runs the shipped affinity-h16-k5gc comes from (runs in $RUNS/s6; docs/affinity.md,
# "K = 5 kernels, the guide, coarse-first, the τ loss"), kernel size 5, τ loss:
#   queue 1: affinity-h16-k5g (1200 steps), then affinity-h16-k5gc (coarse-first), 1200 steps
#            resumed to 3200: the shipped run (its best.pt, then fine-tuned on the mix by
#            model/finetune_cycles.sh);
#   queue 2: affinity-h16-k6gc, 3500 steps (K = 6: the support doubled; behind K = 5).
# No argument: the paper-structure runs, superseded by k5 (its runs are in docs/affinity.md's history):
#   queue 1: affinity-h24, 128² crops, 4 frames, batch 4, the kernel size drawn per step from
#            5, 9, 13 (one model for the run-time knob); not installed;
#   queue 2: the width sweep, affinity-h8/h16/h24/h32 with equal short schedules at kernel
#            size 5: the runs docs/affinity-sweep.md reads (experiments/affinity_sweep.py --runs).
# The affinity filters run natively (model/affinity_native.py: 3.5-11x faster steps than the
# PyTorch reference, docs/affinity-training-kernels.md).
# PYTHON: the interpreter (default python); RUNS: where runs go (default
# ~/.cache/quietframe/runs/g2); STEPS (default 3000): affinity-h24's schedule; SWEEP_STEPS
# (default 600): the sweep's.
set -u
source "$(dirname "${BASH_SOURCE[0]}")/train_run.sh"
PY=${PYTHON:-python}
R=${RUNS:-$HOME/.cache/quietframe/runs/g2}
S=${STEPS:-3000}
W=${SWEEP_STEPS:-600}
mkdir -p "$R/sweep" "$R/s6"
run() {  # run directory, then quietframe-train flags
    local dir=$1
    shift
    train_run "$dir" --threads 1 --kernel-size 5 --lr 0.0005 --frames 4 --batch 4 --seed 0 "$@"
}
if [ "${1:-}" = k5 ]; then
    tau=(--crop 128 --loss tau+temporal --eval-every 200)
    (
        run "$R/s6/affinity-h16-k5g-tau" --variant affinity-h16-k5g "${tau[@]}" --steps 1200
        run "$R/s6/affinity-h16-k5gc-tau" --variant affinity-h16-k5gc "${tau[@]}" --steps 1200
        run "$R/s6/affinity-h16-k5gc-tau" --variant affinity-h16-k5gc "${tau[@]}" --steps 3200
    ) &
    (
        run "$R/s6/affinity-h16-k6gc-tau" --variant affinity-h16-k6gc --crop 128 \
            --loss tau+temporal --eval-every 250 --steps 3500
    ) &
    wait
    exit 0
fi
(
    run "$R/affinity-h24" --variant affinity-h24 --crop 128 --steps "$S" --eval-every 250 \
        --kernel-sizes 5,9,13
) &
(
    for v in affinity-h8 affinity-h16 affinity-h24 affinity-h32; do
        run "$R/sweep/$v" --variant "$v" --crop 128 --steps "$W" --eval-every 200
    done
) &
wait
