"""``torchtrack bench imm`` end to end at toy size: design keys, and agreement with FilterPy."""

import json

import pytest

from torchtrack.cli import main


def test_bench_imm_reports_and_agrees_with_filterpy(tmp_path):
    pytest.importorskip("filterpy")
    out = tmp_path / "b.json"
    rc = main(["bench", "imm", "--tracks", "64", "--steps", "4", "--reference-tracks", "4", "--no-compile",
               "--json", str(out)])
    assert rc == 0
    res = json.loads(out.read_text())
    for key in ("workload", "ours_per_s", "reference", "reference_per_s", "ratio"):
        assert key in res
    assert res["ours_per_s"] > 0 and res["reference_per_s"] > 0
    assert res["max_abs_deviation_from_reference"] < 1e-2   # metres, float32 against FilterPy's float64
