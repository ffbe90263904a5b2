#!/usr/bin/env bash
# Run every `torchtrack bench` workload and collect the JSON reports under out/bench/.
# Usage: bash scripts/bench-all.sh   (after scripts/setup.sh; takes a few minutes, mostly compilation)
set -euo pipefail
cd "$(dirname "$0")/.."
mkdir -p out/bench
TT=.venv/bin/torchtrack
for w in kf imm gmphd glmb pf pmb lbp clearmot registration; do
  echo "== torchtrack bench $w" >&2
  "$TT" bench "$w" --json "out/bench/$w.json"
done
