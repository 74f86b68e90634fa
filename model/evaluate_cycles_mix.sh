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
#   ship:   spent: it installed both candidates on 2026-12-04 (nbg-2l-3g v5, affinity-h16-k5gc
#           v2) and removed their folders; git show c659a22:model/evaluate_cycles_mix.sh has it
#           as it ran. A new candidate ships with model/ship_candidate.sh;
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
ship) echo "ship is spent (see the header): use model/ship_candidate.sh" >&2; exit 2 ;;
docs) docs ;;
test-mitsuba) mitsuba ;;
test-cycles) cycles ;;
*) echo "unknown stage $STAGE" >&2; exit 2 ;;
esac
