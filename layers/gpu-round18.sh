#!/usr/bin/env bash
# Prepared in round 17 (2026-11-27) for the next lent GPU: the light-reading estimator trained where its loss is
# (bare relief walls and full close-ups, round 17's M) at a GPU's scale — which, round 17 measured, is bought by
# rendering less, not by a bigger batch: the world's renderer is 90–98 % of a step (benchmarks/train_throughput.py,
# docs/train_throughput_h200.json). Two runs side by side, each stopped by its --minutes budget:
#   lit-bank   a scene bank of $BANK close-ups rendered once (train-surface --scene-bank), batch 1024
#   lit-fresh  the control: fresh scenes every step, batch 512 (round 17's GPU rate, ~260 scenes a second)
# both continuing $INIT (default layers/surface-lit-told-32: round 17's M, shipped in round 19 as the estimator a
# surface layer reads when told its source light, so nothing needs carrying). The weights, logs and configs come
# back as tars in $OUT. Since round 19 they are judged first as told estimators, against the shipped told route
# (rule TL's bar: +0.10 dB all pixels on select, objects ≥ −0.05, leak ≥ 40 dB):
#   OMP_NUM_THREADS=2 .venv/bin/python benchmarks/relight_candidates.py --estimator \
#       lit-bank/surface@wall_relief=0.25 lit-fresh/surface@wall_relief=0.25 --kinds given --leak
# and by round 17's rule (docs/BENCHMARKS.md, WLS/M) as the untold estimator:
#   OMP_NUM_THREADS=2 .venv/bin/python benchmarks/relight_candidates.py --estimator lit-bank/surface \
#       lit-fresh/surface --kinds free surface --leak
# and, since round 18, its light (the surface layer's gap is its source elevation; a scale that reads the objects
# better should show it there first):
#   OMP_NUM_THREADS=2 .venv/bin/python benchmarks/source_light.py --estimator layers/surface-lit-told-32 lit-bank/surface \
#       lit-fresh/surface --count 32
#
#   OUT=out/gpu18 MINUTES=8 bash layers/gpu-round18.sh              # any machine; cuda where there is one
set -u
OUT=${OUT:-out/gpu18}
MINUTES=${MINUTES:-8}
RUNS=${RUNS:-/tmp/runs}
PY=${PY:-python3}
BANK=${BANK:-32768}
# The bank is rendered before the run's clock starts (at ~400 close-ups a second on an H200: ~80 s for 32768).
BANK_MINUTES=${BANK_MINUTES:-1.5}
bank_minutes=$(awk "BEGIN{print $MINUTES - $BANK_MINUTES}")
INIT=${INIT:-layers/surface-lit-told-32}
mkdir -p "$OUT" "$RUNS"
(nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null || echo "no GPU") | tee "$OUT/round18.log"
runs=(
  "lit-bank  $bank_minutes --scene-bank $BANK --batch-size 1024"
  "lit-fresh $MINUTES --batch-size 512"
)
for r in "${runs[@]}"; do
  set -- $r
  name=$1
  minutes=$2
  shift 2
  OMP_NUM_THREADS=4 PYTHONUNBUFFERED=1 $PY -m lasagna train-surface --input lit --silhouette --light-input \
    --light-given 0.75 --light-jitter 10 --walls-only 0.5 --relief 0.5 --zoom 3 "$@" --out "$RUNS/$name" \
    --working-size 32 --channels 32,64,128 --blocks 2 --lights 3 --lr 0.001 --warmup 100 --world-seed 53 \
    --init-from "$INIT" --minutes "$minutes" --no-progress >"$RUNS/$name.log" 2>&1 &
  sleep 1
done
wait
for r in "${runs[@]}"; do
  set -- $r
  name=$1
  { echo "== $name"; tail -n 2 "$RUNS/$name.log"; tail -n 1 "$RUNS/$name/log.jsonl"; } >>"$OUT/round18.log" 2>&1
  tar -C "$RUNS" -cf "$OUT/$name.tar" "$name/surface" "$name/log.jsonl" "$name/train_config.json" "$name.log"
done
cat "$OUT/round18.log"
ls -la "$OUT"
