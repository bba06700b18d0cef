#!/usr/bin/env bash
# Prepared in round 20 (2026-11-27) for the lent GPU of that session: round 18's call (layers/gpu-round18.sh, the
# told estimator continued at a GPU's scale, a scene bank beside the fresh-scene control) with a third run beside
# them, the shading preset's estimator (layers/surface-albedo-32, reads the unlit base) continued from a bank of
# $ALBEDO_BANK scenes at zoom 1 (its own training's scale; a GPU renders ~1 800 of them a second) at batch 1024 on a
# world seed its training never drew. Each run stops at its --minutes budget; the weights, logs and configs come
# back as tars in $OUT. Judged on this CPU by the rules in docs/BENCHMARKS.md, round 20 (written before the call):
#   OMP_NUM_THREADS=2 .venv/bin/python benchmarks/relight_candidates.py --estimator \
#       lit-bank/surface@wall_relief=0.25 lit-fresh/surface@wall_relief=0.25 --kinds given --leak
#   OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface.py --splits select --sizes 64 256 --count 16 \
#       --albedo layers/surface-albedo-32 albedo-bank/surface --dome 0.25,0.25
#
#   OUT=out/gpu20 MINUTES=8 bash layers/gpu-round20.sh              # any machine; cuda where there is one
set -u
OUT=${OUT:-out/gpu20}
MINUTES=${MINUTES:-8}
RUNS=${RUNS:-/tmp/runs}
PY=${PY:-python3}
BANK=${BANK:-32768}
ALBEDO_BANK=${ALBEDO_BANK:-65536}
# A bank is rendered before its run's clock starts (~80 s for 32768 close-ups on an H200 alone, ~35 s for 65536
# scenes at zoom 1): the banked runs get that much less of the budget so that all three end together.
BANK_MINUTES=${BANK_MINUTES:-1.5}
bank_minutes=$(awk "BEGIN{print $MINUTES - $BANK_MINUTES}")
INIT=${INIT:-layers/surface-lit-told-32}
lit="--input lit --silhouette --light-input --light-given 0.75 --light-jitter 10 --walls-only 0.5 --relief 0.5 --zoom 3
  --channels 32,64,128 --blocks 2 --lights 3 --lr 0.001 --warmup 100 --world-seed 53 --init-from $INIT"
albedo="--input albedo --silhouette --channels 32,64,128 --blocks 2 --lights 3 --lr 0.001 --warmup 100 --world-seed 59
  --init-from layers/surface-albedo-32"
mkdir -p "$OUT" "$RUNS"
(nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null || echo "no GPU") | tee "$OUT/round20.log"
runs=(
  "lit-bank $bank_minutes $lit --scene-bank $BANK --batch-size 1024"
  "lit-fresh $MINUTES $lit --batch-size 512"
  "albedo-bank $bank_minutes $albedo --scene-bank $ALBEDO_BANK --batch-size 1024"
)
for r in "${runs[@]}"; do
  set -- $r
  name=$1
  minutes=$2
  shift 2
  OMP_NUM_THREADS=4 PYTHONUNBUFFERED=1 $PY -m lasagna train-surface "$@" --out "$RUNS/$name" --working-size 32 \
    --minutes "$minutes" --no-progress >"$RUNS/$name.log" 2>&1 &
  sleep 1
done
wait
for r in "${runs[@]}"; do
  set -- $r
  name=$1
  { echo "== $name"; tail -n 2 "$RUNS/$name.log"; tail -n 1 "$RUNS/$name/log.jsonl"; } >>"$OUT/round20.log" 2>&1
  tar -C "$RUNS" -cf "$OUT/$name.tar" "$name/surface" "$name/log.jsonl" "$name/train_config.json" "$name.log"
done
cat "$OUT/round20.log"
ls -la "$OUT"
