#!/usr/bin/env bash
# Fine-tune the shipped learned tiers (nbg-2l-3g, affinity-h16-k5gc) on the Cycles training
# corpus (shots from outside the generator, scenes/corpus_shots.py) mixed with the generator's
# Cycles train split, picking checkpoints on the corpus's validation shots at 1-64 spp through
# the runtime's Stream (--select-on corpus; model/zoo_selection.py). Two runs side by side (one
# thread each), each resumable from its run directory.
#   nohup nice -n 5 model/finetune_corpus.sh > ~/.cache/quietframe/logs/finetune-corpus.log 2>&1 &
# PYTHON: the interpreter (default python); RUNS: where runs go (default
# ~/.cache/quietframe/runs/corpus); NBG_STEPS / AFFINITY_STEPS: schedule lengths; RENDERERS: the
# generator's splits mixed in (default cycles: g2-cycles/train; "mitsuba,cycles" where the
# Mitsuba split is rendered too). Data: scenes/render_corpus.sh, scenes/render_cycles_splits.sh.
# INIT_FROM: the git revision whose models/training/<name>/best.pt each run starts from (default
# b0cc9f2: the first corpus fine-tune, nbg-2l-3g version 6 and affinity-h16-k5gc version 4; that
# fine-tune itself started from 6abc3cf28baa, the generator-trained checkpoints, with
# NOISE_LEVEL=0).
# nbg-2l-3g gains the pass-through candidates (--passthrough 1, model/nbg.py): the grids alone
# cannot give back an input that is already clean (docs/training.md, "Training on the corpus").
# NOISE_LEVEL (default 1): both tiers read the frame's spp (nbg --noise-blend: the blend moves
# with the pixel's noise level; affinity --noise-input: the U-Net reads it), each starting as the
# checkpoint it extends (docs/training.md, "The noise level").
# The third run (training with the fade, nothing shipped; docs/training.md): INIT_FROM=6fba52b
# SELECT_ON=zoo+corpus NBG_STEPS=1000 AFFINITY_STEPS=800.
# SELECT_ON (default corpus): the shots that pick the checkpoint; zoo+corpus adds the zoo's
# validation shots rendered here (model/zoo_selection.py).
# FADE (default 0.134, the shipped files' setting; 0 off): both tiers train with the resampled
# history fading with the frame's spp (--resampled-weight-per-doubling, docs/training.md, "The
# resampled history"), so the blend learns the faded history and the checkpoint carries it.
# Learning rates: half of each tier's original (1e-3, 5e-4), above model/finetune_cycles.sh's
# third: this data is further from the generator's; each run scores its starting model at step 0,
# so a fine-tune that does not help leaves best.pt at the shipped weights.
set -u
source "$(dirname "${BASH_SOURCE[0]}")/train_run.sh"
PY=${PYTHON:-python}
R=${RUNS:-$HOME/.cache/quietframe/runs/corpus}
INIT_FROM=${INIT_FROM:-b0cc9f2}
NOISE=${NOISE_LEVEL:-1}
FADE=${FADE:-0.134}
mkdir -p "$R"
run() {  # name, then quietframe-train flags
    local name=$1
    shift
    git show "$INIT_FROM:models/training/$name/best.pt" > "$R/$name.init.pt" || return 1
    train_run "$R/$name" --init "$R/$name.init.pt" --renderers "${RENDERERS:-cycles}" \
        --corpus 1 --select-on "${SELECT_ON:-corpus}" --select-spp 1,4,16,64 \
        --resampled-weight-per-doubling "$FADE" --threads 1 --seed 1 "$@"
}
run nbg-2l-3g --passthrough 1 --noise-blend "$NOISE" --steps "${NBG_STEPS:-1500}" --eval-every 250 --lr 0.0005 \
    --dropout 0.3 --loss smape+temporal --crop 128 --frames 4 --batch 4 &
run affinity-h16-k5gc --noise-input "$NOISE" --steps "${AFFINITY_STEPS:-1200}" --eval-every 200 --lr 0.0002 \
    --loss tau+temporal --crop 128 --frames 4 --batch 4 &
wait
