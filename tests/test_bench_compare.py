"""scripts/bench_compare.py (``bench-all.sh --compare``): which numbers of a bench's JSON become compared rates."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

_SCRIPT = Path(__file__).parents[1] / "scripts" / "bench_compare.py"
_spec = importlib.util.spec_from_file_location("bench_compare", _SCRIPT)
bench_compare = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench_compare)


def test_rates_of_one_workload_leave_out_the_reference_and_turn_cpu_milliseconds_into_rates():
    payload = {"workload": "w", "ours_per_s": 80.0, "reference": "numpy", "reference_per_s": 30.0, "ratio": 2.7,
               "unit": "scans", "cpu_ms_per_scan": 4.0, "numpy_cpu_ms_per_scan": 9.0, "threads": 1}
    assert bench_compare.rates(payload) == {"ours_per_s": 80.0, "cpu_per_scan/s": pytest.approx(250.0)}


def test_rates_of_several_workloads_are_named_by_workload():
    one = {"ours_per_s": 10.0, "reference_per_s": 1.0, "enhanced_per_s": 5.0, "enhanced_cpu_per_s": 6.0}
    got = bench_compare.rates({"tutorial": one, "wpafb": dict(one, ours_per_s=2.0)})
    assert got == {"tutorial/ours_per_s": 10.0, "tutorial/enhanced_per_s": 5.0, "tutorial/enhanced_cpu_per_s": 6.0,
                   "wpafb/ours_per_s": 2.0, "wpafb/enhanced_per_s": 5.0, "wpafb/enhanced_cpu_per_s": 6.0}


def test_an_unknown_revision_is_a_one_line_error(capsys):
    assert bench_compare.main(["no-such-revision-xyz"]) == 2
    assert "bench-all.sh --compare: error: unknown revision 'no-such-revision-xyz'" in capsys.readouterr().err
