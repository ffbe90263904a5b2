"""``scripts/bench-all.sh --compare REV``: every ``torchtrack bench`` on this checkout and on revision REV, in
alternation, and the ratio (this checkout / REV) of each rate, the median over the rounds.

REV is checked out in a temporary ``git worktree`` and run with ``PYTHONPATH`` pointing at it, by the same
Python, on the same machine, in the same minutes: each round runs every bench on both sides, the side that
goes first alternating, so that a change of load shifts both. Rates are the benches' ``*_per_s`` keys (wall
time) and their ``cpu_ms_per_*`` keys turned into rates (process CPU time: what the work costs on a shared
machine); the references' own rates are left out. A bench the other revision lacks is reported and skipped.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

QUICK = {
    # bench: arguments that keep one run within about a minute on a loaded 2-core machine
    "kf": ["--tracks", "10000", "--steps", "20", "--general-steps", "2", "--loop-tracks", "20"],
    "imm": [],
    "gmphd": ["--reference-steps", "2", "--repeats", "3"],
    "glmb": [],
    "pf": [],
    "pmb": ["--scans", "20", "--repeats", "3"],
    "lbp": ["--sizes", "10,100,300", "--repeats", "3"],
    "clearmot": ["--frames", "128"],
    "registration": [],
}
"""The default workloads; ``--full`` runs every bench with its own defaults instead."""

SKIPPED_PREFIXES = ("reference", "numpy")


def rates(payload: dict, prefix: str = "") -> dict[str, float]:
    """``{workload/key: rate}`` of one bench's JSON: one workload's payload, or a mapping of them."""
    if "ours_per_s" not in payload:
        out = {}
        for name, sub in payload.items():
            if isinstance(sub, dict):
                out.update(rates(sub, f"{prefix}{name}/"))
        return out
    out = {}
    for key, value in payload.items():
        if not isinstance(value, int | float) or key.startswith(SKIPPED_PREFIXES) or value <= 0:
            continue
        if key.endswith("_per_s"):
            out[prefix + key] = float(value)
        elif key.startswith("cpu_ms_per_"):
            out[prefix + key.replace("cpu_ms_per_", "cpu_per_") + "/s"] = 1000.0 / value
    return out


def run_bench(python: str, tree: Path, bench: str, args: list[str], out: Path, threads: int) -> dict | None:
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS=str(threads))
    cmd = [python, "-m", "torchtrack", "bench", bench, *args, "--json", str(out)]
    done = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        tail = (done.stderr or done.stdout).strip().splitlines()[-1:] or ["(no output)"]
        print(f"  {bench} at {tree}: failed ({tail[0]})", file=sys.stderr)
        return None
    return json.loads(out.read_text())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("rev", help="the revision to compare against (anything git rev-parse accepts)")
    parser.add_argument("--rounds", type=int, default=3, help="alternated rounds (default 3)")
    parser.add_argument("--benches", default=",".join(QUICK), help="comma-separated benches (default: all)")
    parser.add_argument("--full", action="store_true", help="each bench with its own default workload")
    parser.add_argument("--python", default=sys.executable, help="the interpreter for both sides")
    parser.add_argument("--threads", type=int, default=1, help="OMP_NUM_THREADS of every run (default 1)")
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "bench" / "compare")
    args = parser.parse_args(argv)
    if os.sep in args.python:       # a path (the default .venv/bin/python) must work from the other side's tree too
        args.python = os.path.abspath(args.python)
    benches = [b for b in args.benches.split(",") if b]
    rev = subprocess.run(["git", "rev-parse", "--short", args.rev], cwd=ROOT, capture_output=True, text=True)
    if rev.returncode != 0:
        print(f"bench-all.sh --compare: error: unknown revision {args.rev!r}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="bench-compare-") as tmp:
        other = Path(tmp) / "rev"
        subprocess.run(["git", "worktree", "add", "--detach", str(other), rev.stdout.strip()], cwd=ROOT,
                       check=True, capture_output=True)
        try:
            sides = {"this": ROOT, "rev": other}
            got: dict[str, dict[str, dict[str, list[float]]]] = {b: {"this": {}, "rev": {}} for b in benches}
            for rnd in range(args.rounds):
                for bench in benches:
                    order = ("this", "rev") if rnd % 2 == 0 else ("rev", "this")
                    print(f"round {rnd + 1}/{args.rounds}: bench {bench}", file=sys.stderr)
                    for side in order:
                        extra = [] if args.full else QUICK.get(bench, [])
                        payload = run_bench(args.python, sides[side], bench, extra,
                                            args.out / f"{side}-{bench}-{rnd}.json", args.threads)
                        for key, value in rates(payload or {}).items():
                            got[bench][side].setdefault(key, []).append(value)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(other)], cwd=ROOT, capture_output=True)
    print(f"ratio = this checkout / {args.rev} ({rev.stdout.strip()}), median of {args.rounds} alternated rounds")
    print(f"{'bench':<14}{'rate':<46}{'this':>12}{'rev':>12}{'ratio':>8}")
    slower = []
    for bench in benches:
        mine, theirs = got[bench]["this"], got[bench]["rev"]
        if not mine or not theirs:
            print(f"{bench:<14}{'(not run on both sides)':<46}")
            continue
        for key in sorted(set(mine) & set(theirs)):
            a, b = statistics.median(mine[key]), statistics.median(theirs[key])
            ratio = a / b
            print(f"{bench:<14}{key:<46}{a:>12.4g}{b:>12.4g}{ratio:>8.2f}")
            if ratio < 0.95:
                slower.append(f"{bench} {key}")
    if slower:
        print("slower than the revision by more than 5 %: " + ", ".join(slower))
    return 0


if __name__ == "__main__":
    sys.exit(main())
