#!/usr/bin/env bash
# auto's Mitsuba tables at 1-64 spp: every shipped model measured on one set of Mitsuba
# validation frames and the tables stamped into its card. auto reads them for any frame whose
# header names no renderer with a table of its own (Mitsuba, Arnold, RenderMan, V-Ray); the test
# split then scores auto against per-frame OIDN (docs/evaluation/mitsuba-tables/README.md).
#   PYTHON=.venv/bin/python model/stamp_mitsuba_tables.sh render|measure-static|measure|measure-history|timing|stamp|test
# Stages, in order (figures under $OUT, default docs/evaluation/mitsuba-tables):
#   render:  the Mitsuba validation split (12 x 8 frames, 256^2, 1024-spp references) and its
#            2 locked-off shots, with 16- and 64-spp inputs topped up (~4 CPU-hours on 2 cores,
#            resumable: finished frames are skipped);
#   measure: quietframe-eval on both (measure-static: the locked-off shots alone, which render
#            first), every shipped model (validation only: model selection), and beside them
#            any candidates of model/evaluate_cycles_mix.sh export under their own names
#            (models/training/<name>-mix/), with their noise points and buffer-absence figures
#            (bench/auto_choice), so shipping one stamps it from these same runs
#            (bench/model_card --stamp --measured-as);
#   measure-history: the noise points and buffer-absence figures of the history tiers
#            (oidn-history*), which `measure` does not take;
#   timing:  a quiet 720p timing run of every model on Mitsuba frames (pause the renders);
#   stamp:   bench/model_card --stamp --no-card --renderer mitsuba into models/*.onnx (then
#            regenerate the cards: python -m quietframe.bench.model_card models/*.onnx);
#   test:    auto and the temporal tiers against oidn-frame on the Mitsuba test split and its
#            locked-off shots (needs test topped up to 64 spp), and the targets table.
set -eu
PY=${PYTHON:-python}
SPP=1,2,4,8,16,64
OUT=${OUT:-docs/evaluation/mitsuba-tables}
STAGE=${1:?render, measure-static, measure, measure-history, timing, stamp or test}
shopt -s nullglob  # none unless evaluate_cycles_mix.sh export made some
CANDIDATES=(models/training/*-mix/*-mix.onnx)
shopt -u nullglob
HISTORY=oidn-history,oidn-fast-history,oidn-history-cleanaux  # measure-history's models
models() {  # the shipped models' and the candidates' method names (file stems), comma-separated
    local names=() f
    for f in models/*.onnx "${CANDIDATES[@]}"; do names+=("$(basename "$f" .onnx)"); done
    (IFS=,; echo "${names[*]}")
}
candidate_args() {  # --model PATH per candidate
    local f
    for f in "${CANDIDATES[@]}"; do printf -- '--model\n%s\n' "$f"; done
}
render() {  # splits (space-separated), with the 16- and 64-spp top-ups
    STAGES="$1" TOPUP_SPP="16 64" PYTHON="$PY" scenes/render_splits.sh
}
evaluate() {  # split methods out [more args]
    local split=$1 methods=$2 out=$3
    shift 3
    "$PY" -m quietframe.bench.evaluate --split "$split" --spp "$SPP" --threads 2 --no-timing \
        --methods "$methods" --out "$out" "$@"
}
mapfile -t extra < <(candidate_args)
case "$STAGE" in
render)
    render "validation-static validation"
    ;;
measure-static)  # the locked-off shots alone (rendered first, so this can run beside the rest)
    evaluate validation-static "$(models),oidn-high-cleanaux-fast" "$OUT/validation-static" \
        "${extra[@]}"
    ;;
measure)
    evaluate validation "$(models),oidn-high-cleanaux-fast" "$OUT/validation" "${extra[@]}"
    [ -f "$OUT/validation-static/benchmarks.json" ] || "$0" measure-static
    only=$(for f in "${CANDIDATES[@]}"; do basename "$f" .onnx; done | paste -sd,)
    "$PY" -m quietframe.bench.auto_choice --split validation --threads 2 --max-frames 3 \
        --buffer-sets all --no-absence "${extra[@]}" --only "$only" --out "$OUT/noise-points"
    "$PY" -m quietframe.bench.auto_choice --split validation --threads 2 --max-frames 3 \
        --buffer-sets all --sequences 6 --spp 1,8 "${extra[@]}" --only "$only" \
        --out "$OUT/absence"
    ;;
measure-history)  # the history tiers' noise points and absence figures (auto needs them)
    "$PY" -m quietframe.bench.auto_choice --split validation --threads 2 --max-frames 3 \
        --buffer-sets all --no-absence --only "$HISTORY" --out "$OUT/noise-points-history"
    "$PY" -m quietframe.bench.auto_choice --split validation --threads 2 --max-frames 3 \
        --buffer-sets all --sequences 6 --spp 1,8 --only "$HISTORY" --out "$OUT/absence-history"
    ;;
timing)  # quiet: pause the renders (kill -STOP) for the few minutes this takes
    "$PY" -m quietframe.bench.evaluate --split validation --sequences 1 --spp 1 --threads 2 \
        --methods "$(models)" "${extra[@]}" --out "$OUT/timing"
    ;;
stamp)
    # auto considers a model only with a 720p time on the table it reads; the history tiers
    # also get their noise points and absence figures (measure-history), which the others
    # keep from the runs that shipped them
    stamp() {  # more stamping args, then the models
        "$PY" -m quietframe.bench.model_card --stamp --no-card --renderer mitsuba \
            --evaluation "$OUT/validation/benchmarks.json" \
            --static-evaluation "$OUT/validation-static/benchmarks.json" \
            --timing "$OUT/timing/benchmarks.json" "$@"
    }
    history=() others=()
    for f in models/*.onnx; do
        if [[ ",$HISTORY," == *",$(basename "$f" .onnx),"* ]]; then history+=("$f")
        else others+=("$f"); fi
    done
    stamp "${others[@]}"
    stamp --noise-points "$OUT/noise-points-history/auto_choice.json" \
        --absent "$OUT/absence-history/auto_choice.json" "${history[@]}"
    ;;
test)
    render "test-static test"  # test is rendered: this adds its 64-spp top-up
    methods=auto,oidn-frame,oidn-high-cleanaux-fast,oidn-acc,oidn-fast-acc
    methods+=,oidn-history,oidn-fast-history,oidn-history-cleanaux
    evaluate test "$methods" "$OUT/test"
    evaluate test-static "$methods" "$OUT/test-static"
    {
        "$PY" -m quietframe.bench.evaluate --compare "$OUT/test/benchmarks.json" --wide \
            --against oidn-frame
        echo
        "$PY" -m quietframe.bench.evaluate --compare "$OUT/test/benchmarks.json" \
            --against oidn-frame --static "$OUT/test-static/benchmarks.json"
    } > "$OUT/targets.md"
    ;;
*) echo "unknown stage $STAGE" >&2; exit 2 ;;
esac
