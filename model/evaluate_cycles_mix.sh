#!/usr/bin/env bash
# Before and after for learned tiers fine-tuned with Cycles in the mix (model/finetune_cycles.sh):
# each fine-tuned run scored beside the shipped model it would replace and per-frame OIDN (and
# Blender's own denoise on Cycles), on both renderers' test splits, one run per split.
#   PYTHON=.venv/bin/python model/evaluate_cycles_mix.sh export|test|test-mitsuba|test-cycles|docs
# Stages:
#   export:  each run in $RUNS (default ~/.cache/quietframe/runs/cycles-mix) exported as
#            models/training/<name>-mix/<name>-mix.onnx beside its checkpoint: the candidates,
#            stamped with version NBG_VERSION / AFFINITY_VERSION (the shipped card's + 1);
#   test:    quietframe-eval on the Mitsuba test split (1-16 spp) and the Cycles test split
#            (1-64 spp) with the shipped and the fine-tuned models, the targets table and a
#            before/after table per spp (quietframe-eval --compare) under $OUT (default
#            docs/evaluation/cycles-mix); test-mitsuba / test-cycles: one split alone;
#   docs:    once a candidate is shipped (model/ship_candidate.sh), the reports that show the
#            learned tiers, re-run: docs/benchmarks.md's Mitsuba test table (its sections from
#            the auto_choice marker on are kept) and docs/evaluation/cycles-test (its table in
#            docs/benchmarks.md is pasted by hand from
#            quietframe-eval --compare ... --against blender-denoise --wide).
# A candidate ships only if it loses at most 0.2 dB on the Mitsuba test split at every spp
# (docs/training.md, "Cycles in the mix").
set -eu
PY=${PYTHON:-python}
R=${RUNS:-$HOME/.cache/quietframe/runs/cycles-mix}
OUT=${OUT:-docs/evaluation/cycles-mix}
NAMES=(nbg-2l-3g affinity-h16-k5gc)
declare -A VERSION=([nbg-2l-3g]=${NBG_VERSION:-5} [affinity-h16-k5gc]=${AFFINITY_VERSION:-2})
STAGE=${1:?export, test, test-mitsuba, test-cycles or docs}

if [ "$STAGE" = export ]; then
    for name in "${NAMES[@]}"; do
        dir=models/training/$name-mix
        mkdir -p "$dir"
        cp "$R/$name"/{best.pt,config.json,log.txt} "$dir/"
        "$PY" -m quietframe.export.cli --checkpoint "$dir/best.pt" --out "$dir/$name-mix.onnx" \
            --version "${VERSION[$name]}"
    done
    exit 0
fi

models=() methods=oidn-frame
for name in "${NAMES[@]}"; do
    models+=(--model "models/training/$name-mix/$name-mix.onnx")
    methods+=",$name,$name-mix"
done
before_after() {  # split folder: each fine-tuned model against its shipped self, per spp
    for name in "${NAMES[@]}"; do
        printf '\n%s against %s (PSNR, in brackets the difference):\n\n' "$name-mix" "$name"
        "$PY" -m quietframe.bench.evaluate --compare "$OUT/$1/benchmarks.json" --wide \
            --methods "$name-mix" --against "$name"
    done > "$OUT/$1/before_after.md"
}
mitsuba() {
    "$PY" -m quietframe.bench.evaluate --split test --spp 1,2,4,8,16 --threads 2 --no-timing \
        --methods "$methods" "${models[@]}" --out "$OUT/mitsuba-test"
    "$PY" -m quietframe.bench.evaluate --compare "$OUT/mitsuba-test/benchmarks.json" --wide \
        --against oidn-frame > "$OUT/mitsuba-test/targets.md"
    before_after mitsuba-test
}
cycles() {
    "$PY" -m quietframe.bench.evaluate --renderer cycles --split test --threads 2 --no-timing \
        --methods "blender-denoise,$methods" "${models[@]}" --out "$OUT/cycles-test"
    "$PY" -m quietframe.bench.evaluate --compare "$OUT/cycles-test/benchmarks.json" --wide \
        --against oidn-frame,blender-denoise > "$OUT/cycles-test/targets.md"
    before_after cycles-test
}
docs() {
    local t=${TMPDIR:-/tmp}/cycles-mix-docs
    "$PY" -m quietframe.bench.evaluate --split test --spp 1,2,4,8,16 --threads 2 --methods \
        noisy,accumulation,oidn-fast,oidn-high,nbg-2l-1g,nbg-2l-3g,nbg-7l-3g,oidn-temporal-acc,oidn-acc,oidn-fast-acc,oidn-frame,affinity-h16-k5gc \
        --kernel-sizes 9,13 --single-frame affinity-h16-k5gc --out "$t/test"
    "$PY" -c "import pathlib, sys; from quietframe.bench.auto_choice import MARK_BEGIN as m; \
old = pathlib.Path('docs/benchmarks.md').read_text(); \
new = pathlib.Path(sys.argv[1]).read_text().rstrip() + '\n\n' + m + old.split(m, 1)[1]; \
pathlib.Path('docs/benchmarks.md').write_text(new)" "$t/test/benchmarks.md"
    cp "$t"/test/{benchmarks.json,psnr_vs_ms.png,crops.png} docs/
    "$PY" -m quietframe.bench.evaluate --renderer cycles --split test \
        --out docs/evaluation/cycles-test
}
case "$STAGE" in
test) mitsuba; cycles ;;
docs) docs ;;
test-mitsuba) mitsuba ;;
test-cycles) cycles ;;
*) echo "unknown stage $STAGE" >&2; exit 2 ;;
esac
