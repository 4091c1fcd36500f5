#!/usr/bin/env bash
# The main job on the small built-in default: install, then render -> train -> task (see README).
#   bash scripts/demo.sh                 # writes demo/
#   bash scripts/demo.sh FOLDER          # writes FOLDER/
#   bash scripts/demo.sh [--out F] [--seed S] [--quick] [--help]   # risp demo's own options
set -euo pipefail
cd "$(dirname "$0")/.."
if [ $# -gt 0 ] && [[ "$1" != -* ]]; then  # a bare first argument is the output folder, as before
  out="$1"; shift; set -- --out "$out" "$@"
fi
bash scripts/setup.sh
exec .venv/bin/risp demo "$@"
