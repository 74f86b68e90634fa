#!/usr/bin/env bash
# Render the Cycles splits of the g2 scenes, staged and resumable like
# render_splits.sh: test, the locked-off test shots, validation (and its locked-off shots),
# then train.
# Finished files are skipped, so re-running continues where a stopped render left off.
#   nohup nice -n 10 scenes/render_cycles_splits.sh > ~/.cache/quietframe/logs/render_cycles.log 2>&1 &
# CYCLES_PYTHON: the interpreter of the Cycles venv (python3.11 -m venv V && V/bin/pip install
# ".[cycles]"; or bpy==4.5.4 plus tools/dev_links.py for a development checkout).
# Budget (docs/data.md, "Cycles splits"): ~17 CPU-hours on this 2-core machine in all.
set -u
PY=${CYCLES_PYTHON:-$HOME/venv-bpy/bin/python}
STAGES=${STAGES:-all}  # the splits to render, space-separated, e.g. "validation validation-static"
selected() {  # split: whether STAGES names it
    [ "$STAGES" = all ] || [[ " $STAGES " == *" $1 "* ]]
}
render() {  # split sequences size reference_spp [more args]; FRAMES: frames a sequence (8)
    local split=$1 n=$2 size=$3 ref=$4
    selected "$split" || return 0
    shift 4
    "$PY" -m quietframe.scenes.cycles_render --split "$split" --sequences "$n" \
        --frames "${FRAMES:-8}" --size "$size" --spp 1,2,4,8,16,64 --reference-spp "$ref" \
        --threads "${THREADS:-2}" "$@" \
        || echo "split $split: some sequences failed (re-run to retry)"
}
render test "${TEST_SEQUENCES:-8}" 192x192 512
render test-static "${STATIC_SEQUENCES:-2}" 192x192 512  # flicker on locked-off shots
render validation "${VALIDATION_SEQUENCES:-8}" 192x192 512
render validation-static "${STATIC_SEQUENCES:-2}" 192x192 512
# Train: 4 frames a sequence (one 4-frame training window; scenes, not frames, are what the
# learned tiers lack), so 40 sequences fit one 3-hour session (1.96 CPU-hours measured on
# 2026-12-04). STAGES=train renders train alone (a fresh machine needs it first).
FRAMES=4 render train "${TRAIN_SEQUENCES:-40}" 128x128 256 --reference-min-spp 32
