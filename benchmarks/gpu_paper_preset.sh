#!/usr/bin/env bash
# The `paper` training preset on one CUDA GPU, as far as a short lease allows (docs/PERFORMANCE.md §On a GPU):
#
#   N=10000 EPOCHS=12 bash benchmarks/gpu_paper_preset.sh OUTDIR [ENV]
#
# 1. renders ENV's train set (N samples with J, seed 1), 200 target-domain and 200 unseen train-domain images
#    (seeds 2 and 3: the same states and looks as the CPU runs of docs/RESULTS.md), with cuda_ad_rgb;
# 2. `risp-train fit` with the preset chosen by the hardware (paper: ResNet-18 w64, lr 1e-2, batch 16) and the
#    environment's default regularizer, EPOCHS epochs (the paper's 100 do not fit a 10-minute call: the cosine
#    schedule is the same, only shorter);
# 3. `risp-train eval` on the target and the val images.
# Everything a reader needs (timings, history, the evaluations) is copied to OUTDIR.
set -u
out=$1
env=${2:-quadrotor}
N=${N:-10000}
EPOCHS=${EPOCHS:-12}
WORKERS=${WORKERS:-12}
source "$(dirname "$0")/gpu_common.sh"

step "1. render $env on the GPU"
/usr/bin/time -f "render train $N with J, $WORKERS workers: %e s" timeout 240 python3 -m risp_data.cli render --env "$env" --n "$N" \
  --out "$work/$env-train" --format wds --workers "$WORKERS" --shard-size 250 --seed 1 --quiet 2>&1 | tail -n 2
render_test() {  # NAME DOMAIN SEED: 200 images without J
  /usr/bin/time -f "render $1 200: %e s" timeout 60 python3 -m risp_data.cli render --env "$env" --n 200 --out "$work/$env-$1" \
    --domain "$2" --no-jacobian --format wds --workers 4 --shard-size 100 --seed "$3" --quiet 2>&1 | tail -n 2
}
render_test target target 2
render_test val train 3
show_manifest "$work/$env-train"

step "2. risp-train fit (preset by the hardware), $EPOCHS epochs"
/usr/bin/time -f "fit: %e s" timeout 330 python3 -m risp_train.cli fit "$work/$env-train" --out "$work/run" \
  --epochs "$EPOCHS" --threads 4 --seed 0 --cache memory --quiet 2>&1 | tail -n 4
cp "$work/run/history.json" "$out/history.json"; cp "$work/run/config.json" "$out/config.json"

step "3. eval"
for s in target val; do
  timeout 60 python3 -m risp_train.cli eval "$work/run/model.pt" "$work/$env-$s" --out "$work/run/eval-$s" --threads 4 --quiet > /dev/null 2>&1
  cat "$work/run/eval-$s.md"; cp "$work/run/eval-$s.json" "$out/eval-$s.json"
done
step "done"
