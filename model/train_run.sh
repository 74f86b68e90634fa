# Sourced by the training scripts (model/train_g2.sh, train_affinity.sh, finetune_cycles.sh,
# finetune_corpus.sh): one quietframe-train run whose output goes to DIR.out; a failed run is
# said and the queue goes on; the run's last log line is echoed. $PY is the interpreter.
#   train_run DIR [quietframe-train flags]
train_run() {
    local dir=$1
    shift
    "$PY" -m quietframe.model.train --run "$dir" "$@" > "$dir.out" 2>&1 \
        || echo "run $dir failed (see $dir.out)"
    echo "run $dir: $(tail -c 300 "$dir/log.txt" 2>/dev/null | tail -1)"
}
