#!/usr/bin/env bash
# Render the Cycles training corpus (scenes/corpus_shots.py): validation first (12 shots, for
# model selection), then train (120), in chunks of CHUNK shots, one Blender process a chunk.
# Resumable: finished files are skipped, so re-running continues where it stopped; each chunk
# rewrites <split>/split.json (shots done, CPU-hours, the projected total, reference noise).
#   nohup nice -n 15 scenes/render_corpus.sh > ~/.cache/quietframe/logs/corpus.log 2>&1 &
# Run from the repository root. CYCLES_PYTHON: the Cycles venv's interpreter (`make cycles`);
# THREADS (default 2); SPLITS (default "validation train"); CHUNK (default 6 shots); OUT (the
# data folder, default ~/.cache/quietframe/data); FRAMES (frames a shot, default the corpus's 8:
# FRAMES=4 renders each shot's first 4 frames, what one training window reads, at half the cost);
# FIRST (default 0): the first shot index each split renders from (a session that continues a
# fine-tune renders the shots its checkpoints have not seen first, e.g. FIRST=36).
# Budget and figures: docs/data.md, "Training corpus".
set -u
PY=${CYCLES_PYTHON:-.venv-cycles/bin/python}
CHUNK=${CHUNK:-6}
for split in ${SPLITS:-validation train}; do
    count=$("$PY" -c "from quietframe.scenes.corpus_shots import SPLIT_COUNT; print(SPLIT_COUNT['$split'])") \
        || { echo "corpus: no split $split"; exit 2; }
    for ((start = ${FIRST:-0}; start < count; start += CHUNK)); do
        echo "corpus $split: shots $start-$((start + CHUNK - 1)) ($(date -u +%FT%TZ))"
        "$PY" -m quietframe.scenes.corpus_render --split "$split" --start "$start" \
            --count "$CHUNK" --threads "${THREADS:-2}" ${OUT:+--out "$OUT"} ${FRAMES:+--frames "$FRAMES"} \
            || echo "corpus $split $start: some shots failed (re-run to retry)"
    done
done
echo "corpus: done ($(date -u +%FT%TZ))"
