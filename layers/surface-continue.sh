#!/usr/bin/env bash
# The shipped surface estimators continued, several processes of `lasagna train-surface` on one machine (a GPU
# where there is one), each stopped by its --minutes budget. Each run's final EMA weights, log and config come back
# as one tar in $OUT; the candidates are measured on `select` (benchmarks/surface.py --splits select) against the
# shipped ones. SET picks the round:
#   wide  on the `wide` split (train's families and the generic gem and blob shapes, `lasagna.world.splits`) beside
#         the same continuation on `train` (the control: as many steps and scenes, no new shapes)
#   zoom  on `train` with close-ups (--zoom 3: windows of 1 to 3 working sizes around object pixels), from
#         $INIT_ALBEDO / $INIT_LIT (default: the catalogue's estimators; the round of 2026-11-26 started from the
#         first runs' weights, runs/surface-albedo-32/surface and runs/surface-lit-32/surface)
#
#   zoom2 the lit estimator only, for photographs (the round of 2026-11-26 (3)): the first close-up run continued
#         ($INIT_LIT_ZOOM, default runs/zoom/lit-zoom/surface) with --zoom 3, and the shipped one with --zoom 2 and 4
#
#   SET=wide OUT=out/surface-wide MINUTES=7.5 bash layers/surface-continue.sh
# WORLD_SEED (default 11) picks the training scenes; a continuation takes another seed than the run it continues.
set -u
OUT=${OUT:-out/surface-wide}
MINUTES=${MINUTES:-7.5}
BATCH=${BATCH:-256}
RUNS=${RUNS:-$OUT/run}
PY=${PY:-python3}
mkdir -p "$OUT" "$RUNS"
SET=${SET:-wide}
case $SET in
wide)
  runs=(
    "albedo-wide  --input albedo --split wide  --init-from layers/surface-albedo-32"
    "albedo-train --input albedo --split train --init-from layers/surface-albedo-32"
    "lit-wide     --input lit    --split wide  --init-from layers/surface-lit-32"
    "lit-train    --input lit    --split train --init-from layers/surface-lit-32"
  ) ;;
zoom)
  runs=(
    "albedo-zoom  --input albedo --split train --zoom 3 --init-from ${INIT_ALBEDO:-layers/surface-albedo-32}"
    "lit-zoom     --input lit    --split train --zoom 3 --init-from ${INIT_LIT:-layers/surface-lit-32}"
  ) ;;
zoom2)
  runs=(
    "lit-zoom3-more --input lit --split train --zoom 3 --init-from ${INIT_LIT_ZOOM:-runs/zoom/lit-zoom/surface}"
    "lit-zoom2      --input lit --split train --zoom 2 --init-from ${INIT_LIT:-layers/surface-lit-32}"
    "lit-zoom4      --input lit --split train --zoom 4 --init-from ${INIT_LIT:-layers/surface-lit-32}"
  ) ;;
*) echo "SET must be wide, zoom or zoom2, got $SET" >&2; exit 2 ;;
esac
declare -A pids
for r in "${runs[@]}"; do
  set -- $r
  name=$1
  shift
  OMP_NUM_THREADS=2 PYTHONUNBUFFERED=1 $PY -m lasagna train-surface "$@" --out "$RUNS/$name" --silhouette \
    --channels 32,64,128 --blocks 2 --lights 3 --lr 0.001 --batch-size "$BATCH" --world-seed "${WORLD_SEED:-11}" \
    --minutes "$MINUTES" --no-progress >"$RUNS/$name.log" 2>&1 &
  pids[$name]=$!
  sleep 1
done
wait
for r in "${runs[@]}"; do
  set -- $r
  name=$1
  tail -n 2 "$RUNS/$name.log"
  tail -n 1 "$RUNS/$name/log.jsonl" 2>/dev/null
  tar -C "$RUNS" -cf "$OUT/$name.tar" "$name/surface" "$name/log.jsonl" "$name/train_config.json" "$name.log" 2>/dev/null
done
ls -la "$OUT"
