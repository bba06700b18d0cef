# Shared by the GPU round scripts from round 24 on (sourced, not run): start one `lasagna train-surface` run in the
# background, and pack a finished run's weights, log and config into $OUT for the device tool to bring back.
# Needs RUNS (where runs are written), OUT (what comes back) and PY (the python that holds lasagna).

# train_in_background NAME ARGS...: train-surface ARGS into $RUNS/NAME (its output in $RUNS/NAME.log), in the background.
train_in_background() {
  local name=$1
  shift
  OMP_NUM_THREADS=${THREADS:-4} PYTHONUNBUFFERED=1 $PY -m lasagna train-surface "$@" --out "$RUNS/$name" \
    --no-progress >"$RUNS/$name.log" 2>&1 &
  sleep 1
}

# pack_run NAME LOG: the run's last lines appended to LOG, its weights, log and config tarred into $OUT/NAME.tar.
pack_run() {
  local name=$1 log=$2
  { echo "== $name"; tail -n 2 "$RUNS/$name.log"; tail -n 1 "$RUNS/$name/log.jsonl"; } >>"$log" 2>&1
  tar -C "$RUNS" -cf "$OUT/$name.tar" "$name/surface" "$name/log.jsonl" "$name/train_config.json" "$name.log"
}
