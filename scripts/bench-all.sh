#!/usr/bin/env bash
# Run every `torchtrack bench` workload and collect the JSON reports under out/bench/.
# Usage: bash scripts/bench-all.sh   (after scripts/setup.sh; takes a few minutes, mostly compilation)
#        bash scripts/bench-all.sh --compare REV [--rounds N] [--benches pmb,gmphd] [--full]
#          every bench on this checkout and on revision REV (a temporary git worktree), alternated in the same
#          minutes, and the ratio per workload (median of the rounds): a slowdown is seen before it lands.
# PYTHON=... picks the interpreter (default .venv/bin/python).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
if [ "${1:-}" = "--compare" ]; then
  shift
  exec "$PY" scripts/bench_compare.py --python "$PY" "$@"
fi
mkdir -p out/bench
for w in kf imm gmphd glmb pf pmb lbp clearmot registration; do
  echo "== torchtrack bench $w" >&2
  "$PY" -m torchtrack bench "$w" --json "out/bench/$w.json"
done
