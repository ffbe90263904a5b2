"""``torchtrack bench hota``: both implementations timed on the same data and agreeing (TrackEval test-only)."""

import json
import warnings

import pytest

from torchtrack.cli import main


def test_bench_hota_small_workload(tmp_path, capsys):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pytest.importorskip("trackeval")
    out = tmp_path / "b.json"
    assert main(["bench", "hota", "--frames", "20", "--objects", "15", "--repeats", "1", "--json", str(out)]) == 0
    got = json.loads(out.read_text())
    assert got["scores_agree"] is True and got["truth_points"] == 300 and got["unit"] == "frames"
    assert got["ours_per_s"] > 0 and got["reference_per_s"] > 0 and 0 < got["HOTA"] <= 1
    assert "ratio:" in capsys.readouterr().out


def test_bench_hota_needs_both_files(tmp_path, capsys):
    assert main(["bench", "hota", "--gt", str(tmp_path / "gt.txt")]) == 2
    assert "--gt and --pred go together" in capsys.readouterr().err
