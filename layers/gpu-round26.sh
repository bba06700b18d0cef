#!/usr/bin/env bash
# Prepared in round 26 (2026-11-28) for the lent GPU of that session: the relight preset's two estimators continued on
# a world whose paint is sometimes dark (`--low-key P`: each surface's albedo times a gain in LOW_KEY_GAIN with
# probability P, `SceneParams.darkened`) — photographs' low-key backdrops, which round 25's probe A found read as
# relief turned from the light. Three runs share the GPU, fresh close-ups at batch 512, world seed 67 (never drawn
# before): `lk-closeup` (layers/surface-lit-closeup-32, the default's estimator, its own recipe, low-key 0.3),
# `ctl-closeup` (the same without low-key: the control, so that a change is the dark paint's and not more steps')
# and `lk-told` (layers/surface-lit-told-32, the told route's, its own recipe, low-key 0.3). The weights, logs and
# configs come back as tars in $OUT. Judged on this CPU by rule LK in docs/BENCHMARKS.md, round 26 (written before
# the call).
#
#   OUT=out/gpu26 MINUTES=7.5 bash layers/gpu-round26.sh              # any machine; cuda where there is one
set -u
OUT=${OUT:-out/gpu26}
MINUTES=${MINUTES:-7.5}
RUNS=${RUNS:-/tmp/runs}
PY=${PY:-python3}
BATCH=${BATCH:-512}
common="--input lit --silhouette --working-size 32 --channels 32,64,128 --blocks 2 --lights 3 --zoom 3 --lr 0.0005
  --warmup 50 --world-seed 67 --batch-size $BATCH --minutes $MINUTES"
closeup="$common --init-from layers/surface-lit-closeup-32"
told="$common --init-from layers/surface-lit-told-32 --light-input --light-given 0.75 --light-jitter 10 --walls-only 0.5
  --relief 0.5"
source "$(dirname "$0")/gpu-lib.sh"
mkdir -p "$OUT" "$RUNS"
(nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null || echo "no GPU") | tee "$OUT/round26.log"
runs=(
  "lk-closeup $closeup --low-key 0.3"
  "ctl-closeup $closeup"
  "lk-told $told --low-key 0.3"
)
for r in "${runs[@]}"; do
  set -- $r
  train_in_background "$@"
done
wait
for r in "${runs[@]}"; do
  set -- $r
  pack_run "$1" "$OUT/round26.log"
done
cat "$OUT/round26.log"
ls -la "$OUT"
