#!/usr/bin/env bash
# Build the wheel, install it in a fresh virtual environment, and run the main commands from an empty
# folder: what a user gets from `pip install` (no checkout, no editable install). Run by .ci/run.
#   bash scripts/check-wheel.sh            # needs .venv from scripts/setup.sh (for setuptools)
# The WPAFB benchmark runs where the data is found (data/wpafb-aoi02, $TORCHTRACK_WPAFB or the machines'
# shared copy); elsewhere it is reported as skipped.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
PY=${PYTHON:-python3}
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT

step() { echo "check-wheel: $*" >&2; }
# run CMD...: run it quietly; on failure print its output and stop
run() {
  if ! "$@" > "$WORK/log" 2>&1; then
    tail -n 30 "$WORK/log" >&2
    echo "check-wheel: FAILED: $*" >&2
    exit 1
  fi
}

step "building the wheel"
.venv/bin/python -m pip wheel --quiet --no-deps --no-build-isolation -w "$WORK/dist" . 2>&1 | grep -v "^WARNING: Location" || true
WHEEL=$(ls "$WORK"/dist/*.whl)
"$PY" - "$WHEEL" <<'PYEOF'
import sys, zipfile
names = zipfile.ZipFile(sys.argv[1]).namelist()
top = sorted({n.split("/")[0] for n in names if not n.split("/")[0].endswith((".dist-info", ".data"))})
if top != ["torchtrack"]:
    sys.exit(f"check-wheel: top-level entries besides torchtrack in the wheel: {top}")
for needed in ("torchtrack/configs/maneuver.yaml", "torchtrack/detector/weights/centertrack_small.pt"):
    if needed not in names:
        sys.exit(f"check-wheel: {needed} missing from the wheel")
PYEOF

step "installing it in a fresh venv (CPU torch first)"
"$PY" -m venv "$WORK/venv"
"$WORK/venv/bin/python" -m pip install --quiet "torch==2.13.0" 2>&1 | grep -v "^WARNING: Location" || true
"$WORK/venv/bin/python" -m pip install --quiet "$WHEEL" 2>&1 | grep -v "^WARNING: Location" || true

mkdir "$WORK/empty"
cd "$WORK/empty"
export PATH="$WORK/venv/bin:$PATH"
step "torchtrack scenario maneuver --runs 2 (from an empty folder)"
run torchtrack scenario maneuver --runs 2 --json maneuver.json
step "torchtrack scenario formation --runs 2"
run torchtrack scenario formation --runs 2 --json formation.json
step "torchtrack demo"
run torchtrack demo --json demo.json
test -s out/demo/tracks.txt && test -s out/demo/metrics.json

WPAFB=""
for d in "${TORCHTRACK_WPAFB:-}" "$ROOT/data/wpafb-aoi02" "$ROOT/../shared/data/wpafb-aoi02"; do
  if [ -n "$d" ] && [ -f "$d/transformed_object_states.csv" ]; then WPAFB=$d; break; fi
done
if [ -n "$WPAFB" ]; then
  step "torchtrack track --benchmark wpafb (TORCHTRACK_WPAFB=$WPAFB)"
  TORCHTRACK_WPAFB="$WPAFB" run torchtrack track --benchmark wpafb --trackers gmphd --out out/wpafb --json wpafb.json
  test -s wpafb.json
  step "torchtrack data fetch wpafb --from $WPAFB (into ./data/wpafb-aoi02)"
  run torchtrack data fetch wpafb --from "$WPAFB" --no-progress
  test -s data/wpafb-aoi02/SHA256SUMS
else
  step "WPAFB data not found: benchmark skipped (torchtrack data fetch wpafb)"
fi
step "ok"
