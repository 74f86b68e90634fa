#!/usr/bin/env bash
# Score model/finetune_corpus.sh's candidates beside the shipped learned tiers, each figure from
# one run with the input itself, per-frame OIDN (fast and high) and Blender's denoise:
#   PYTHON=.venv/bin/python model/evaluate_corpus_candidates.sh export|speed|validation|test
#   export:     RUNS/<name>/best.pt -> OUT/candidates/<name>-SUFFIX.onnx (the shipped card's
#               tables carried: their splits may not be on the machine; named so that every run
#               scores it as its own method beside the shipped file);
#   validation: the corpus's validation shots (what chose the checkpoints) at 1-64 spp;
#   test:       the zoo's test shots rendered on the machine (both rounds; reported only);
#   speed:      1280x720 time of each beside plain OIDN-high and OIDN-fast (bench/oidn_speedup).
# Then bench/learned_report.py writes OUT/<run>/report/README.md per run with the issue's
# targets. RUNS: the fine-tune's runs (default ~/.cache/quietframe/runs/corpus); OUT (default
# docs/evaluation/learned-corpus); SUFFIX (default corpus): the candidates' name after the tier's;
# VERSION_NBG / VERSION_AFFINITY: the versions the files get. The second corpus fine-tune (the
# noise level, 2026-12-07): OUT=docs/evaluation/learned-noise SUFFIX=noise VERSION_NBG=7
# VERSION_AFFINITY=5.
set -eu
PY=${PYTHON:-python}
RUNS=${RUNS:-$HOME/.cache/quietframe/runs/corpus}
OUT=${OUT:-docs/evaluation/learned-corpus}
NBG=nbg-2l-3g
AFF=affinity-h16-k5gc
SUFFIX=${SUFFIX:-corpus}
CANDIDATES="$OUT/candidates/$NBG-$SUFFIX.onnx $OUT/candidates/$AFF-$SUFFIX.onnx"
TIERS=$NBG,$AFF,$NBG-$SUFFIX,$AFF-$SUFFIX
METHODS=noisy,$TIERS,oidn-fast-history/frame,oidn-high,blender-denoise
STAGE=${1:?export, validation, test or speed}
score() {  # zoo split out [zoo_eval flags]
    local zoo=$1 split=$2 out=$3
    shift 3
    "$PY" -m quietframe.bench.zoo_eval --zoo "$zoo" --split "$split" --spp 1,4,16,64 \
        --methods "$METHODS" --extra-models $CANDIDATES --threads 2 --out "$out" "$@"
    local times=()  # the speed stage's, where it ran first
    [ -f "$OUT/speed/times.json" ] && times=(--times "$OUT/speed/times.json")
    "$PY" -m quietframe.bench.learned_report "$out/zoo.json" --tiers "$TIERS" "${times[@]}" \
        --out "$out/report" > /dev/null
}
case "$STAGE" in
export)
    mkdir -p "$OUT/candidates"
    "$PY" -m quietframe.export.cli --checkpoint "$RUNS/$NBG/best.pt" \
        --out "$OUT/candidates/$NBG-$SUFFIX.onnx" --version "${VERSION_NBG:-6}" \
        --metrics-from "models/$NBG.onnx"
    "$PY" -m quietframe.export.cli --checkpoint "$RUNS/$AFF/best.pt" \
        --out "$OUT/candidates/$AFF-$SUFFIX.onnx" --version "${VERSION_AFFINITY:-4}" \
        --metrics-from "models/$AFF.onnx"
    ;;
validation)
    score corpus validation "$OUT/corpus-validation"
    ;;
test)
    for zoo in zoo1 zoo2; do
        if ls "$HOME/.cache/quietframe/data/$zoo-cycles/test/"*/manifest.json > /dev/null 2>&1; then
            score "$zoo" test "$OUT/$zoo-test"
        fi
    done
    ;;
speed)
    mkdir -p "$OUT/speed"
    "$PY" -m quietframe.bench.oidn_speedup "models/$NBG.onnx" "models/$AFF.onnx" $CANDIDATES \
        --rounds 5 --threads 2 --json "$OUT/speed/times.json" | tee "$OUT/speed/README.md"
    ;;
*)
    echo "unknown stage $STAGE: export, validation, test or speed" >&2
    exit 2
    ;;
esac
