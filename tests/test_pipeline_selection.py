"""Tracker selection for the video pipeline: option grids, and a search that finds the setting that is
right by construction."""

import numpy as np
import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import from_points
from torchtrack.pipeline.config import PipelineConfig
from torchtrack.pipeline.frame_detections import FrameDetections
from torchtrack.pipeline.selection import SequenceDetections, choose, evaluate, option_sets, select


def test_option_sets_nest_dotted_keys():
    sets = option_sets({"a": [1, 2], "filter.q": [3.0]})
    assert sets == [{"a": 1, "filter": {"q": 3.0}}, {"a": 2, "filter": {"q": 3.0}}]
    assert option_sets({}) == [{}]


@pytest.fixture(scope="module")
def moving_pair():
    """Two targets moving at 6 px/frame (detected exactly, with their velocity and a large frame difference)
    and a static false alarm (no velocity, little frame difference)."""
    frames, dets = 12, []
    rows = []
    for k in range(1, frames + 1):
        truth = np.array([[20.0 + 6 * k, 40.0], [20.0 + 6 * k, 90.0]])
        pos = np.vstack([truth, [[100.0, 140.0]]])
        vel = np.array([[6.0, 0.0], [6.0, 0.0], [0.0, 0.0]])
        dets.append(FrameDetections(k, np.eye(3), pos, vel, np.ones(3), pos, vel, np.array([20.0, 20.0, 1.0]),
                                    np.ones(3, bool)))
        rows += [(k, 1, *truth[0]), (k, 2, *truth[1])]
    r = np.array(rows)
    gt = from_points(r[:, 0].astype(np.int64), r[:, 1].astype(np.int64), r[:, 2], r[:, 3])
    return [SequenceDetections("pair", gt, None, dets)]


def test_evaluate_scores_the_tracker_on_kept_detections(moving_pair):
    cfg = PipelineConfig()
    near = evaluate("greedy", {"max_distance": 10.0, "max_age": 0}, (0.0, 0.0), moving_pair, cfg)
    assert near["IDS"] == 0 and near["FN"] == 0 and near["FP"] == 12  # the static false alarm, every frame
    assert near["HOTA"] == pytest.approx((24 / 36) ** 0.5, abs=1e-12)  # DetA 24 / (24 + 12), AssA 1, exact hits
    for gate in ((2.0, 0.0), (0.0, 5.0)):
        moving_only = evaluate("greedy", {"max_distance": 10.0, "max_age": 0}, gate, moving_pair, cfg)
        assert moving_only["FP"] == 0 and moving_only["MOTA"] == pytest.approx(1.0)
        assert moving_only["HOTA"] == pytest.approx(1.0, abs=1e-12)


def test_select_finds_the_min_speed_that_drops_the_static_false_alarm(moving_pair):
    chosen, log = select(moving_pair, PipelineConfig(tracker="greedy"), ["greedy"], [(0.0, 0.0), (2.0, 0.0)],
                         {"greedy": {"max_distance": [10.0], "max_age": [0]}}, progress=False)
    assert chosen.min_speed == 2.0 and chosen.trackers == {"greedy": {"max_distance": 10.0, "max_age": 0}}
    assert len(log) == 2 and torch.tensor([r["MOTA"] for r in log]).argmax().item() == 1


def test_choose_prefers_identities_among_options_level_in_mota():
    rows = [{"MOTA": 0.803, "IDF1": 0.82, "name": "a"}, {"MOTA": 0.800, "IDF1": 0.86, "name": "b"},
            {"MOTA": 0.790, "IDF1": 0.90, "name": "c"}]
    assert choose(rows)["name"] == "a"
    assert choose(rows, 0.005)["name"] == "b"
    assert choose(rows, 0.02)["name"] == "c"
    assert choose(rows, 0.02, max_ids=None)["name"] == "c"
    rows = [{**r, "IDS": ids} for r, ids in zip(rows, (40, 30, 20))]
    assert choose(rows, 0.005, max_ids=35)["name"] == "b"     # "a" has too many switches
    assert choose(rows, 0.0, max_ids=25)["name"] == "c"
    assert choose(rows, 0.005, max_ids=10)["name"] == "b"     # none has so few: the limit is ignored


def test_select_with_an_identity_switch_limit_relative_to_a_reference(monkeypatch, moving_pair):
    # scripted scores: option x trades MOTA for identity switches; the reference has 50 switches
    table = {("gmphd", 1): (0.82, 40), ("gmphd", 2): (0.80, 25), ("sort", 1): (0.70, 50)}

    def scripted(name, options, gate, data, config):
        mota, ids = table[(name, options["x"])]
        return {"MOTA": mota, "IDS": ids, "FP": 0, "FN": 0, "IDF1": 0.5, "HOTA": 0.5}

    monkeypatch.setattr("torchtrack.pipeline.selection.evaluate", scripted)
    grids = {"gmphd": {"x": [1, 2]}, "sort": {"x": [1]}}
    free, _ = select(moving_pair, PipelineConfig(), ["gmphd", "sort"], [(2.0, 5.0)], grids, progress=False)
    assert free.trackers["gmphd"] == {"x": 1}
    limited, _ = select(moving_pair, PipelineConfig(), ["gmphd", "sort"], [(2.0, 5.0)], grids, progress=False,
                        ids_limit=("sort", 0.6))
    assert limited.trackers == {"gmphd": {"x": 2}, "sort": {"x": 1}}       # 25 <= 0.6 x 50 < 40
    with pytest.raises(TorchtrackError, match="reference"):
        select(moving_pair, PipelineConfig(), ["gmphd"], [(2.0, 5.0)], grids, progress=False, ids_limit=("sort", 0.6))


def test_select_trackers_refuses_a_non_positive_identity_switch_ratio(tmp_path, capsys):
    from torchtrack.cli import main

    code = main(["select-trackers", "--sequences", str(tmp_path), "--out", str(tmp_path / "s.yaml"),
                 "--max-ids-ratio", "0"])
    assert code == 2 and "--max-ids-ratio must be > 0" in capsys.readouterr().err
    assert not (tmp_path / "s.yaml").exists()


def test_select_trackers_refuses_an_identity_switch_reference_before_running_anything(tmp_path, capsys):
    from torchtrack.cli import main

    code = main(["select-trackers", "--sequences", str(tmp_path / "missing"), "--out", str(tmp_path / "s.yaml"),
                 "--trackers", "gmphd", "sort", "--max-ids-ratio", "0.6", "--ids-reference", "gmphd"])
    err = capsys.readouterr().err
    assert code == 2 and "identity-switch reference 'gmphd'" in err and "missing" not in err
    assert not (tmp_path / "s.yaml").exists()
