#!/usr/bin/env bash
# The surface-estimator candidates trained side by side on one GPU (an H200 lent to the session of 2026-11-26):
# six runs of `lasagna train-surface`, one per process, each stopped by its --minutes budget. Each run's final
# EMA weights, log and config come back as one tar in $OUT (default out/surface-runs; the runs themselves in
# $RUNS, default $OUT/run); the candidates are
# measured on the `select` split (benchmarks/surface.py --splits select) and the best per input ships.
#
#   OUT=out/surface-runs MINUTES=6.5 bash layers/surface-runs.sh        # any machine; cuda where there is one
set -u
OUT=${OUT:-out/surface-runs}
MINUTES=${MINUTES:-6.5}
RUNS=${RUNS:-$OUT/run}
PY=${PY:-python3}
mkdir -p "$OUT" "$RUNS"
runs=(
  "lit-n-s32     --input lit    --output normals --channels 32,64,128     --working-size 32 --batch-size 256"
  "lit-n-l32     --input lit    --output normals --channels 32,64,128,256 --working-size 32 --batch-size 256"
  "lit-n-l64     --input lit    --output normals --channels 32,64,128,256 --working-size 64 --batch-size 128"
  "lit-h-l64     --input lit    --output height  --channels 32,64,128,256 --working-size 64 --batch-size 128"
  "albedo-n-l32  --input albedo --output normals --channels 32,64,128,256 --working-size 32 --batch-size 256"
  "albedo-n-l64  --input albedo --output normals --channels 32,64,128,256 --working-size 64 --batch-size 128"
)
launch() {  # name, minutes, extra flags...
  local name=$1 minutes=$2
  shift 2
  OMP_NUM_THREADS=2 PYTHONUNBUFFERED=1 $PY -m lasagna train-surface "$@" --out "$RUNS/$name" \
    --minutes "$minutes" --blocks 2 --lights 3 --lr 0.001 --no-progress >"$RUNS/$name.log" 2>&1 &
  pids[$name]=$!
}
declare -A pids
for r in "${runs[@]}"; do
  set -- $r
  name=$1
  shift
  launch "$name" "$MINUTES" "$@"
  sleep 1
done
# A run that died in its first minute (a device that cannot render the world, say) starts again rendering on the CPU.
sleep 60
for r in "${runs[@]}"; do
  set -- $r
  if ! kill -0 "${pids[$1]}" 2>/dev/null && ! grep -q '"out"' "$RUNS/$1.log"; then
    echo "restarting $1 with --render-on cpu:"; tail -n 3 "$RUNS/$1.log"
    rm -rf "${RUNS:?}/$1"
    name=$1
    shift
    launch "$name" "$(awk "BEGIN{print $MINUTES - 1.1}")" "$@" --render-on cpu
  fi
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
