#!/usr/bin/env bash
# Prepared in round 24 (2026-11-28) for the lent GPU of that session: the told estimator (layers/surface-lit-told-32)
# continued on a world whose objects rest on the wall (`--rest 1`: attached shadows, a height field above the wall)
# with a loss on its height field against the true heights above the wall (`--height-weight`): the heights a cast
# shadow needs (docs/BENCHMARKS.md, round 23's S3: casting from the true heights +2.0 dB on shadowed select, from the
# told layer's integrated normals +0.3). Three runs share the GPU, fresh scenes (cast shadows are rendered per step
# under each scene's source light): input with its shadows half the time, height weight 1 (`h-shadow`) and 4
# (`h-shadow-w4`), and shadowless input, weight 1 (`h-plain`). The weights, logs and configs come back as tars in
# $OUT. Judged on this CPU by rule HT in docs/BENCHMARKS.md, round 24 (written before the call):
#   OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface_shadows.py --heights layers/surface-lit-told-32 \
#       h-shadow/surface h-shadow-w4/surface h-plain/surface
#
#   OUT=out/gpu24 MINUTES=7 bash layers/gpu-round24.sh              # any machine; cuda where there is one
set -u
OUT=${OUT:-out/gpu24}
MINUTES=${MINUTES:-7}
RUNS=${RUNS:-/tmp/runs}
PY=${PY:-python3}
BATCH=${BATCH:-512}
INIT=${INIT:-layers/surface-lit-told-32}
lit="--input lit --silhouette --light-input --light-given 0.75 --light-jitter 10 --walls-only 0.25 --relief 0.5 --zoom 3
  --channels 32,64,128 --blocks 2 --lights 3 --lr 0.001 --warmup 100 --world-seed 61 --init-from $INIT --rest 1"
source "$(dirname "$0")/gpu-lib.sh"
mkdir -p "$OUT" "$RUNS"
(nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null || echo "no GPU") | tee "$OUT/round24.log"
runs=(
  "h-shadow $lit --height-weight 1 --shadows 0.5"
  "h-shadow-w4 $lit --height-weight 4 --shadows 0.5"
  "h-plain $lit --height-weight 1"
)
for r in "${runs[@]}"; do
  set -- $r
  train_in_background "$@" --working-size 32 --batch-size "$BATCH" --minutes "$MINUTES"
done
wait
for r in "${runs[@]}"; do
  set -- $r
  pack_run "$1" "$OUT/round24.log"
done
cat "$OUT/round24.log"
ls -la "$OUT"
