# Sourced by the GPU scripts (gpu_check.sh, gpu_paper_preset.sh) after they set $out: the output and work folders,
# unbuffered Python, the `step` banner, `show_manifest`, and what machine and libraries the run used.
mkdir -p "$out"
work=$(mktemp -d)
export PYTHONUNBUFFERED=1
step() { echo "== $1 ($(date +%T))"; }
# which Mitsuba variant rendered a shard folder, and how many samples it holds
show_manifest() { python3 -c "import json,sys; m=json.load(open(sys.argv[1])); print('manifest variant:', m.get('variant'), 'samples:', m.get('n'))" "$1/manifest.json"; }

step "machine"
nvidia-smi -L
python3 -c "import torch, drjit as dr, mitsuba as mi; print('torch', torch.__version__, torch.cuda.get_device_name(0)); print('drjit', dr.__version__, 'mitsuba', mi.__version__, 'CUDA backend:', dr.has_backend(dr.JitBackend.CUDA))"
