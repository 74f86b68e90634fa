#!/usr/bin/env bash
# Before and after for the learned tiers retrained with Cycles in the mix (issue 23,
# deliverable 5), on both test splits in one run each, next to per-frame OIDN (and Blender's own
# denoise on Cycles):
#   export: the fine-tuned runs of model/finetune_cycles.sh as <name>-mix.onnx beside their
#           checkpoints in models/training/<name>-mix/ (kept in git: the candidates);
#   test:   quietframe-eval on the Mitsuba test split (1-16 spp) and the Cycles test split
#           (1-64 spp) with the shipped and the fine-tuned models, and issue 24's comparison
#           table per spp (bench/compare_table) under docs/evaluation/cycles-mix/;
#           test-mitsuba / test-cycles: one split alone (the other may still be rendering).
#   ship:   install the candidates under the shipped names (next version) with both renderers'
#           tables, each measured on validation with the candidate under its own name
#           (bench/model_metrics --measured-as): Mitsuba from model/stamp_mitsuba_tables.sh
#           measure (run it first), Cycles from a run here on the Cycles validation splits,
#           each with a quiet 720p timing run on that renderer's frames; then the cards;
#   docs:   after ship, the reports that show the learned tiers, re-run with the new ones
#           installed: docs/benchmarks.md's Mitsuba test table (the same methods; the file's
#           later sections, from the auto_choice marker on, are kept) and the Cycles test run
#           (docs/evaluation/cycles-test; its table in docs/benchmarks.md is pasted by hand,
#           python -m quietframe.bench.compare_table ... --against blender-denoise --wide).
# A candidate is shipped only if it loses at most 0.2 dB on the Mitsuba test split at every spp
# (the rule; both pass it: docs/training.md, "Cycles in the mix").
#   PYTHON=.venv/bin/python model/evaluate_cycles_mix.sh export|test|test-mitsuba|test-cycles|ship|docs
set -eu
PY=${PYTHON:-python}
R=${RUNS:-$HOME/.cache/quietframe/runs/cycles-mix}
OUT=${OUT:-docs/evaluation/cycles-mix}
NAMES=(nbg-2l-3g affinity-h16-k5gc)
declare -A VERSION=([nbg-2l-3g]=5 [affinity-h16-k5gc]=2)  # the shipped cards' versions + 1
STAGE=${1:?export, test, test-mitsuba, test-cycles, ship or docs}

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
        "$PY" -m quietframe.bench.compare_table "$OUT/$1/benchmarks.json" --wide \
            --methods "$name-mix" --against "$name"
    done > "$OUT/$1/before_after.md"
}
mitsuba() {
    "$PY" -m quietframe.bench.evaluate --split test --spp 1,2,4,8,16 --threads 2 --no-timing \
        --methods "$methods" "${models[@]}" --out "$OUT/mitsuba-test"
    "$PY" -m quietframe.bench.compare_table "$OUT/mitsuba-test/benchmarks.json" --wide \
        --against oidn-frame > "$OUT/mitsuba-test/targets.md"
    before_after mitsuba-test
}
cycles() {
    "$PY" -m quietframe.bench.evaluate --renderer cycles --split test --threads 2 --no-timing \
        --methods "blender-denoise,$methods" "${models[@]}" --out "$OUT/cycles-test"
    "$PY" -m quietframe.bench.compare_table "$OUT/cycles-test/benchmarks.json" --wide \
        --against oidn-frame,blender-denoise > "$OUT/cycles-test/targets.md"
    before_after cycles-test
}
ship() {
    local mitsuba=${MITSUBA_TABLES:-docs/evaluation/mitsuba-tables} name
    local candidates
    candidates=$(printf '%s-mix,' "${NAMES[@]}")
    candidates=${candidates%,}
    for split in validation validation-static; do
        "$PY" -m quietframe.bench.evaluate --renderer cycles --split "$split" --threads 2 \
            --no-timing --methods "blender-denoise,oidn-frame,$candidates" "${models[@]}" \
            --out "$OUT/cycles-$split"
    done
    # quiet 720p timing on each renderer's frames (the tables are per renderer)
    "$PY" -m quietframe.bench.evaluate --renderer cycles --split validation --sequences 1 \
        --spp 1 --threads 2 --methods "oidn-frame,$candidates" "${models[@]}" \
        --out "$OUT/timing-cycles"
    "$PY" -m quietframe.bench.evaluate --split validation --sequences 1 --spp 1 --threads 2 \
        --methods "oidn-frame,$candidates" "${models[@]}" --out "$OUT/timing-mitsuba"
    for name in "${NAMES[@]}"; do
        # The shipped run's files become the candidate's (tests/test_export checks that
        # models/<name>.onnx is the export of models/training/<name>/best.pt); the old run
        # stays in git history. A fine-tune keeps no resumable checkpoint.pt of its own.
        rm -f "models/training/$name/checkpoint.pt"
        cp "models/training/$name-mix"/{best.pt,config.json,log.txt} "models/training/$name/"
        "$PY" -m quietframe.export.cli --checkpoint "models/training/$name/best.pt" \
            --out "models/$name.onnx" --version "${VERSION[$name]}"
        "$PY" -m quietframe.bench.model_metrics "models/$name.onnx" --measured-as "$name-mix" \
            --renderer mitsuba --evaluation "$mitsuba/validation/benchmarks.json" \
            --static-evaluation "$mitsuba/validation-static/benchmarks.json" \
            --noise-points "$mitsuba/noise-points/auto_choice.json" \
            --absent "$mitsuba/absence/auto_choice.json" \
            --timing "$OUT/timing-mitsuba/benchmarks.json"
        "$PY" -m quietframe.bench.model_metrics "models/$name.onnx" --measured-as "$name-mix" \
            --renderer cycles --evaluation "$OUT/cycles-validation/benchmarks.json" \
            --static-evaluation "$OUT/cycles-validation-static/benchmarks.json" \
            --timing "$OUT/timing-cycles/benchmarks.json"
        "$PY" -m quietframe.bench.model_card "models/$name.onnx" --measured-as "$name-mix" \
            --evaluation "$mitsuba/validation/benchmarks.json"
        rm -r "models/training/$name-mix"  # shipped now
    done
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
ship) ship ;;
docs) docs ;;
test-mitsuba) mitsuba ;;
test-cycles) cycles ;;
*) echo "unknown stage $STAGE" >&2; exit 2 ;;
esac
