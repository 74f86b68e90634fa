#!/usr/bin/env bash
# The affinity quality tier's g2 runs (issue 15), two queues side by side (one thread each,
# one per core), each resumable from its run directory (re-running continues where it stopped):
#   queue 1: affinity-h24, the shipped run: 128² crops, 4 frames, batch 4, the kernel size
#            drawn per step from 5, 9, 13 (one model for the run-time knob), 5 the default
#   queue 2: the width sweep: affinity-h8/h16/h24/h32 with equal short schedules at kernel
#            size 5, for validation PSNR per width at equal steps (experiments/affinity_sweep.py --runs)
# The affinity filters run natively (model/affinity_native.py; 3.5-11x faster steps than the
# PyTorch reference loop, docs/affinity-training-kernels.md).
#   nohup nice -n 10 model/train_affinity.sh > ~/.cache/quietframe/logs/train_affinity.log 2>&1 &
# PYTHON selects the interpreter (default: python); STEPS (default 3000) the shipped schedule,
# SWEEP_STEPS (default 600) the sweep's.
#
# `model/train_affinity.sh k5` runs the second round instead (docs/affinity.md, "K = 5 kernels,
# the guide and the τ loss"), runs in $RUNS/s6, one thread each, two queues:
#   queue 1: affinity-h16-k5g with τ loss (1200 steps), then affinity-h16-k5gc (coarse-first)
#            with τ loss, 1200 steps, resumed to 3200 (the candidate to ship);
#   queue 2: affinity-h16-k6gc with τ loss, 3500 steps (K = 6: the support doubled).
set -u
PY=${PYTHON:-python}
R=${RUNS:-$HOME/.cache/quietframe/runs/g2}
S=${STEPS:-3000}
W=${SWEEP_STEPS:-600}
mkdir -p "$R/sweep" "$R/s6"
run() {  # run directory, then quietframe-train flags
    local dir=$1
    shift
    "$PY" -m quietframe.model.train --run "$dir" --threads 1 --kernel-size 5 --lr 0.0005 \
        --frames 4 --batch 4 --seed 0 "$@" > "$dir.out" 2>&1 || echo "run $dir failed (see $dir.out)"
    echo "run $dir: $(tail -c 300 "$dir/log.txt" 2>/dev/null | tail -1)"
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
