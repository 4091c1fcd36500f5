#!/usr/bin/env bash
# The GPU checks of docs/PERFORMANCE.md §GPU, as one script for a CUDA machine (risp's Python packages on
# PYTHONPATH or installed; the llvm_ad_rgb references made beforehand on a CPU machine):
#
#   PYTHONPATH=. python benchmarks/gpu_check.py reference --out gpu_reference.npz      # CPU machine
#   bash benchmarks/gpu_check.sh gpu_reference.npz OUTDIR                               # GPU machine
#
# 1. cuda_ad_rgb against llvm_ad_rgb: images, forward-mode Jacobians, projective state gradients (same seeds);
# 2. risp-data render on the GPU (cube, N train-domain samples with J, 200 target-domain images), timed;
# 3. risp-train fit on the GPU with the paper and the cpu preset's networks (width 64, 16), EPOCHS epochs, and eval;
# 4. the tests that need a GPU (tests/test_train_runtime.py) and the variant tests.
set -u
ref=$1
out=${2:-gpu-check}
N=${N:-1000}            # training samples rendered on the GPU
EPOCHS=${EPOCHS:-5}     # epochs of each fit
WORKERS=${WORKERS:-1}   # render worker processes sharing the GPU
source "$(dirname "$0")/gpu_common.sh"

step "1. cuda_ad_rgb vs llvm_ad_rgb"
timeout 240 python3 benchmarks/gpu_check.py compare "$ref" --json "$out/gpu_check.json" 2>&1 | tail -n 12

step "2. risp-data render on the GPU"
/usr/bin/time -f "render train $N with J, $WORKERS workers: %e s" timeout 240 python3 -m risp_data.cli render --env cube --n "$N" \
  --out "$work/cube-train" --format wds --workers "$WORKERS" --shard-size 250 --seed 1 --quiet 2>&1 | tail -n 3
/usr/bin/time -f "render target 200: %e s" timeout 120 python3 -m risp_data.cli render --env cube --n 200 \
  --out "$work/cube-target" --domain target --no-jacobian --format wds --workers "$WORKERS" --shard-size 100 --seed 2 --quiet 2>&1 | tail -n 3
show_manifest "$work/cube-train"

for preset in paper cpu; do
  step "3. risp-train fit on the GPU ($preset preset's network, $EPOCHS epochs of $N)"
  /usr/bin/time -f "fit $preset: %e s" timeout 300 python3 -m risp_train.cli fit "$work/cube-train" --out "$work/run-$preset" \
    --preset "$preset" --epochs "$EPOCHS" --workers 4 --seed 0 --quiet 2>&1 | tail -n 3
  timeout 60 python3 -m risp_train.cli eval "$work/run-$preset/model.pt" "$work/cube-target" --out "$work/run-$preset/eval-target" \
    --quiet > /dev/null 2>&1
  cat "$work/run-$preset/eval-target.md"
  cp "$work/run-$preset/history.json" "$out/fit_${preset}_history.json"
  cp "$work/run-$preset/eval-target.json" "$out/eval_${preset}_target.json"
done

step "4. tests that need a GPU"
timeout 120 python3 -m pytest -q -p no:cacheprovider tests/test_train_runtime.py tests/test_render.py -k "gpu or cuda or device or init_mitsuba" 2>&1 | tail -n 5
step "done"
