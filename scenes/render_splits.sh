#!/usr/bin/env bash
# Render the g2 splits in stages, a usable minimum of every split first, so training can start
# while the rest renders: test (12 sequences, 1024-spp references), the locked-off test and
# validation shots (2 sequences each), a first validation slice (VALIDATION_FIRST, default 2),
# a first train slice (TRAIN_FIRST, default 16, 256-spp references), then the rest of
# validation (12) and of train (TRAIN_SEQUENCES, default 120).
# All sequences: 8 frames, 256x256, inputs at 1,2,4,8 spp. Sequence seeds are fixed per split
# and index, so a slice is the start of the full split. Every command resumes: finished frames
# are skipped, so re-running this script continues where it stopped.
#   nohup nice -n 10 scenes/render_splits.sh > ~/.cache/quietframe/logs/render_g2.log 2>&1 &
# STAGES: the splits to render, space-separated (default: all, in the order above), e.g.
#   STAGES="validation-static validation" TOPUP_SPP="16 64" scenes/render_splits.sh
# TOPUP_SPP: colour levels above 8 spp added to every rendered split (evaluation only; see
# `quietframe-render topup`).
# PYTHON / PYTHONPATH select the interpreter and the checkout (default: `python` and the
# installed quietframe).
set -u
PY=${PYTHON:-python}
JOBS=${JOBS:-2}
STAGES=${STAGES:-all}
common=(--frames 8 --size 256x256 --spp 1,2,4,8 --jobs "$JOBS")
selected() {  # split: whether STAGES names it
    [ "$STAGES" = all ] || [[ " $STAGES " == *" $1 "* ]]
}
render() {  # split sequences reference_spp
    selected "$1" || return 0
    "$PY" -m quietframe.scenes.cli render --split "$1" --sequences "$2" --reference-spp "$3" \
        "${common[@]}" || echo "split $1: some sequences failed (re-run to retry)"
    local spp
    for spp in ${TOPUP_SPP:-}; do
        "$PY" -m quietframe.scenes.cli topup --split "$1" --spp "$spp" \
            || echo "split $1: the $spp-spp top-up failed (re-run to retry)"
    done
}
render test 12 1024
# Locked-off shots (for flicker): static camera and scene, noise animated per frame; one
# reference per sequence, for frame 0, at 4x the given spp (here 4096), shared by every frame.
render test-static 2 1024
render validation-static 2 1024
render validation "${VALIDATION_FIRST:-2}" 1024
render train "${TRAIN_FIRST:-16}" 256
render validation 12 1024
render train "${TRAIN_SEQUENCES:-120}" 256
