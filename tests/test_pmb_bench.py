"""``bench pmb`` and ``bench lbp`` on tiny workloads: they run, report the design's keys, and the torch and
NumPy implementations compute the same numbers (speed is never asserted)."""

from __future__ import annotations

import json

from torchtrack.cli import main


def test_bench_pmb_tiny_agrees_with_numpy(tmp_path):
    out = tmp_path / "pmb.json"
    assert main(["bench", "pmb", "--targets", "6", "--measurements", "10", "--scans", "3", "--repeats", "1",
                 "--json", str(out)]) == 0
    payload = json.loads(out.read_text())
    assert {"workload", "ours_per_s", "reference", "reference_per_s", "ratio"} <= set(payload)
    assert payload["ours_per_s"] > 0 and payload["reference_per_s"] > 0
    assert payload["expected_count_difference"] < 1e-6


def test_bench_lbp_tiny_agrees_with_numpy(tmp_path):
    out = tmp_path / "lbp.json"
    assert main(["bench", "lbp", "--sizes", "5,20", "--repeats", "1", "--dtype", "float64", "--json", str(out)]) == 0
    payload = json.loads(out.read_text())
    assert payload["ours_per_s"] > 0 and payload["reference_per_s"] > 0
    assert all(v["max_abs_diff"] < 1e-10 for v in payload["per_size"].values())
