"""``torchtrack bench kf`` end to end at toy size (eager): the design's keys and the general-path extras."""

import json

from torchtrack.cli import main


def test_bench_kf_reports_general_path(tmp_path):
    out = tmp_path / "kf.json"
    rc = main(["bench", "kf", "--tracks", "300", "--steps", "4", "--general-steps", "3", "--loop-tracks", "2",
               "--no-compile", "--json", str(out)])
    assert rc == 0
    res = json.loads(out.read_text())
    for key in ("workload", "ours_per_s", "reference", "reference_per_s", "ratio", "general_path_per_s",
                "general_path_eager_per_s", "general_path_per_cpu_s", "general_warmup_s", "batch_first_loop_per_s"):
        assert key in res, key
    assert res["general_path_per_s"] > 0 and res["general_path_per_cpu_s"] > 0
