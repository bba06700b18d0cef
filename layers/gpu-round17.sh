#!/usr/bin/env bash
# Round 17 (2026-11-27): the one call a lent GPU got, three trainings side by side on it, each stopped by its
# --minutes budget (docs/BENCHMARKS.md, "Round of 2026-11-27 (17)"):
#   relit-big       the larger relit prior of layers/prior-gpu.sh (5.5 M parameters, from scratch, batch 512):
#                   does a prior trained at a GPU's scale raise the relight default's cap (round 13, T)?
#   lit-relief-gpu  the shipped lit estimator continued on close-ups with three relief walls in four (round 16's D)
#                   at batch 512: the candidate that could ship
#   walls-gpu       the shipped lit estimator continued on bare relief walls only (round 16's W) at batch 1024: does
#                   relief become a rule at this scale, where 15 CPU minutes left every wall flat?
# The weights, logs and configs come back as tars in $OUT (the prior's in 15 MB parts); the runs themselves in
# $RUNS (default /tmp/runs, outside $OUT, whose files a device call returns at most eight of).
#
#   OUT=out/gpu17 MINUTES=8 bash layers/gpu-round17.sh            # any machine; cuda where there is one
set -u
OUT=${OUT:-out/gpu17}
MINUTES=${MINUTES:-8}
RUNS=${RUNS:-/tmp/runs}
PY=${PY:-python3}
mkdir -p "$OUT" "$RUNS"
(nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null || echo "no GPU") | tee "$OUT/round17.log"
OUT=$OUT RUNS=$RUNS MINUTES=$MINUTES PY=$PY bash layers/prior-gpu.sh >>"$OUT/round17.log" 2>&1 &
prior=$!
runs=(
  "lit-relief-gpu --zoom 3 --relief 0.67 --batch-size 512 --world-seed 37"
  "walls-gpu      --walls-only --relief 1 --batch-size 1024 --world-seed 41"
)
for r in "${runs[@]}"; do
  set -- $r
  name=$1
  shift
  OMP_NUM_THREADS=4 PYTHONUNBUFFERED=1 $PY -m lasagna train-surface --input lit --silhouette "$@" \
    --out "$RUNS/$name" --working-size 32 --channels 32,64,128 --blocks 2 --lights 3 --lr 0.001 --warmup 100 \
    --init-from layers/surface-lit-closeup-32 --minutes "$MINUTES" --no-progress >"$RUNS/$name.log" 2>&1 &
  sleep 1
done
wait
for r in "${runs[@]}"; do
  set -- $r
  name=$1
  { echo "== $name"; tail -n 2 "$RUNS/$name.log"; tail -n 1 "$RUNS/$name/log.jsonl"; } >>"$OUT/round17.log" 2>&1
  tar -C "$RUNS" -cf "$OUT/$name.tar" "$name/surface" "$name/log.jsonl" "$name/train_config.json" "$name.log"
done
cat "$OUT/round17.log"
ls -la "$OUT"
