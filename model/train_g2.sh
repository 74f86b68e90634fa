#!/usr/bin/env bash
# The g2 training runs, two queues side by side (one thread each, one per core), each run
# resumable from its run directory (re-running this script continues where it stopped):
#   queue 1: nbg-2l-3g (SMAPE + temporal), the same with the noise-unbiased loss
#            (relmse+temporal), nbg-2l-1g and nbg-7l-3g without the clamp, nbg-7l-3g with
#            the floored clamp (--outlier-floor 128; not finished yet)
#   queue 2: oidn-temporal-acc, nbg-2l-3g without the pre-stage's firefly clamp
#            (--outlier-sigmas 0: shipped as nbg-2l-3g v3), oidn-temporal-fast-acc with the
#            half-resolution parameter CNN (--net-scale 2, ablation), then the same at full
#            resolution (500 steps), and nbg-2l-3g / nbg-2l-1g with the floored clamp
#            (--outlier-floor 128)
# (the two nbg-2l-3g ablations of docs/training.md: loss, clamp)
# NBG runs train with buffer dropout 0.3 (issue 14: missing buffers, the colour-only path).
#   nohup nice -n 10 model/train_g2.sh > ~/.cache/quietframe/logs/train_g2.log 2>&1 &
# PYTHON selects the interpreter (default: python); STEPS (default 800) the schedule length.
set -u
PY=${PYTHON:-python}
R=${RUNS:-$HOME/.cache/quietframe/runs/g2}
S=${STEPS:-800}
mkdir -p "$R"
run() {  # name, then quietframe-train flags
    local name=$1
    shift
    "$PY" -m quietframe.model.train --run "$R/$name" --steps "$S" --eval-every 250 \
        --threads 1 "$@" > "$R/$name.out" 2>&1 || echo "run $name failed (see $R/$name.out)"
    echo "run $name: $(tail -c 300 "$R/$name/log.txt" 2>/dev/null | tail -1)"
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
