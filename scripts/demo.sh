#!/usr/bin/env bash
# The main job on the small built-in default: install, then render -> train -> task (see README).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/risp demo --out "${1:-demo}"
