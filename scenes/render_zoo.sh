#!/usr/bin/env bash
# Render the validation zoo (scenes/zoo_shots.py) with Cycles: validation first (auto's tables),
# then test (reported only); ZOO=zoo2 renders round 2 (the shots the history finds hard).
# Resumable: finished files are skipped, so re-running continues.
#   nohup nice -n 10 scenes/render_zoo.sh > ~/.cache/quietframe/logs/render_zoo.log 2>&1 &
# CYCLES_PYTHON: the Cycles venv's interpreter (`make cycles`). The photos are fetched from PyPI
# on first use (scenes/zoo_assets.py). Budget and figures: docs/zoo.md.
set -u
PY=${CYCLES_PYTHON:-.venv-cycles/bin/python}
for split in ${SPLITS:-validation test}; do
    "$PY" -m quietframe.scenes.zoo_render --split "$split" --zoo "${ZOO:-zoo1}" \
        --threads "${THREADS:-2}" \
        ${SHOTS:+--shots "$SHOTS"} || echo "zoo $split: some shots failed (re-run to retry)"
done
