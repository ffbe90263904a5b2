"""Bad and hostile input (issue 25): one-line errors naming file and line, MOTChallenge's conf-0 convention,
exact large ids, and memory of reading a detection file bounded by its size."""

import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from torchtrack.cli import main
from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import from_points, read_mot, write_motdata
from torchtrack.metrics import clear_mot


def _two_objects(tmp_path, conf_second: float):
    """gt: objects 1 and 2 in frames 1-2, object 2 with ``conf_second``; returns the gt path."""
    gt = from_points([1, 1, 2, 2], [1, 2, 1, 2], [10.0, 50.0, 11.0, 51.0], [10.0, 50.0, 10.0, 50.0],
                     conf=[1.0, conf_second, 1.0, conf_second])
    write_motdata(tmp_path / "gt.txt", gt)
    return tmp_path / "gt.txt"


def test_zero_conf_ground_truth_is_ignored_as_in_motchallenge(tmp_path):
    gt = read_mot(_two_objects(tmp_path, 0.0))
    only_first = from_points([1, 2], [7, 7], [10.5, 11.5], [10.0, 10.0])
    m = clear_mot(gt, only_first)
    assert (m["MOTA"], m["FN"], m["FP"], m["GT"]) == (1.0, 0, 0, 1)
    # a prediction on the conf-0 object is neither a hit nor a false positive
    both = from_points([1, 1, 2, 2], [7, 8, 7, 8], [10.5, 50.5, 11.5, 51.5], [10.0, 50.0, 10.0, 50.0])
    m = clear_mot(gt, both)
    assert (m["MOTA"], m["FP"], m["TP"], m["predictions"]) == (1.0, 0, 2, 2)
    # counted as objects on request: the plain score of the full ground truth
    counted = clear_mot(gt, only_first, count_zero_conf=True)
    plain = clear_mot(read_mot(_two_objects(tmp_path, 1.0)), only_first)
    assert counted == plain and plain["MOTA"] == 0.5 and plain["FN"] == 2


def test_eval_command_ignores_zero_conf_and_counts_on_request(tmp_path, capsys):
    gt = _two_objects(tmp_path, 0.0)
    write_motdata(tmp_path / "pred.txt", from_points([1, 2], [7, 7], [10.5, 11.5], [10.0, 10.0]))
    assert main(["eval", "--gt", str(gt), "--pred", str(tmp_path / "pred.txt")]) == 0
    assert "100.00" in capsys.readouterr().out
    assert main(["eval", "--gt", str(gt), "--pred", str(tmp_path / "pred.txt"), "--count-zero-conf"]) == 0
    assert "50.00" in capsys.readouterr().out


def test_non_utf8_bytes_even_in_a_comment_are_one_error_naming_the_line(tmp_path, capsys):
    bad = tmp_path / "det.txt"
    bad.write_bytes(b"1,1,1,1,8,8,1\n# caf\xe9\n2,1,1,1,8,8,1\n")
    with pytest.raises(TorchtrackError, match=r"det.txt:2: not UTF-8"):
        read_mot(bad)
    assert main(["eval", "--gt", str(bad), "--pred", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("torchtrack eval: error:") and "det.txt:2" in err[0]


def test_large_ids_stay_exact_and_frames_beyond_int64_are_refused(tmp_path):
    big = 2**53 + 1                             # not representable as a float64
    path = tmp_path / "t.txt"
    path.write_text(f"1,{big},1,1,8,8,1\n1,{big + 1},1,1,8,8,1\n")
    assert read_mot(path).id.tolist() == [big, big + 1]
    path.write_text("1,1,1,1,8,8,1\n100000000000000000000,1,1,1,8,8,1\n")
    with pytest.raises(TorchtrackError, match=r"t.txt:2: frame 100000000000000000000 is outside the 64-bit"):
        read_mot(path)
    path.write_text("1,1.5,1,1,8,8,1\n")
    with pytest.raises(TorchtrackError, match=r"t.txt:1: id must be an integer"):
        read_mot(path)


def test_reading_a_detection_file_takes_memory_near_its_size(tmp_path):
    rng = np.random.default_rng(0)
    n = 60_000
    path = tmp_path / "det.txt"
    xy = rng.uniform(0, 5000, (n, 2))
    path.write_text("".join(f"{1 + i // 100},-1,{x:.3f},{y:.3f},8.000,8.000,0.9,0.1234,-0.4321,-1\n"
                            for i, (x, y) in enumerate(xy)))
    size = path.stat().st_size
    tracemalloc.start()
    data = read_mot(path)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert data.size == n and np.allclose(data.centers()[:, 0], xy[:, 0] + 4.0, atol=1e-3)
    assert peak < 1.5 * size, f"reading {size} bytes peaked at {peak} bytes"


def test_empty_and_nan_weight_files_are_one_error(tmp_path):
    import torch

    import torchtrack.detector as detector_package
    from torchtrack.detector.checkpoint import load_checkpoint

    empty = tmp_path / "empty.pt"
    empty.write_bytes(b"")
    with pytest.raises(TorchtrackError, match="empty.pt: unreadable, truncated or not a torch file"):
        load_checkpoint(empty)
    shipped = torch.load(Path(detector_package.__file__).parent / "weights" / "centertrack_small.pt",
                         weights_only=True)
    first = next(k for k, t in shipped["model"].items() if t.is_floating_point())
    shipped["model"][first] = torch.full_like(shipped["model"][first], float("nan"))
    torch.save(shipped, tmp_path / "nan.pt")
    with pytest.raises(TorchtrackError, match=f"nan.pt: NaN or infinite weights in {first}"):
        load_checkpoint(tmp_path / "nan.pt")


def test_binary_wpafb_csv_and_absurd_clutter_are_one_error(tmp_path, capsys):
    from torchtrack.sim.detections import simulate_detections

    binary = tmp_path / "truth.csv"
    binary.write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe")
    assert main(["convert-wpafb", str(binary), "--out", str(tmp_path / "gt.txt")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "truth.csv: not UTF-8 text" in err[0]
    truth = from_points([1, 2], [1, 1], [5.0, 6.0], [5.0, 5.0])
    with pytest.raises(TorchtrackError, match="clutter 1e\\+09 per frame over 2 frames"):
        simulate_detections(truth, pd=0.9, sigma=1.0, clutter=1e9, image_size=(100, 100))


def test_sparse_frame_numbers_are_crossed_in_one_step(tmp_path):
    from torchtrack.pipeline.frame_detections import MAX_GAP, stream_frames

    det = from_points([1, 4, 4 + MAX_GAP + 2, 10**9, 10**9 + 1], [-1] * 5, [10.0, 11, 12, 50, 51], [10.0] * 5)
    frames = stream_frames(det)
    # short gaps are frames where nothing was detected; the long ones are crossed (the trackers predict by dt)
    assert frames.tolist() == [1, 2, 3, 4, 4 + MAX_GAP + 2, 10**9, 10**9 + 1]
    gt = from_points([1, 2, 3, 10**9, 10**9 + 1], [1, 1, 1, 2, 2], [10.0, 11, 12, 50, 51], [10.0] * 5)
    write_motdata(tmp_path / "det.txt", from_points([1, 2, 3, 10**9, 10**9 + 1], [-1] * 5, [10.0, 11, 12, 50, 51],
                                                     [10.0] * 5))
    write_motdata(tmp_path / "gt.txt", gt)
    assert main(["track", "--detections", str(tmp_path / "det.txt"), "--gt", str(tmp_path / "gt.txt"),
                 "--tracker", "greedy", "--out", str(tmp_path / "out")]) == 0
    tracks = read_mot(tmp_path / "out" / "tracks.txt")
    assert tracks.frames().tolist() == [1, 2, 3, 10**9, 10**9 + 1]
    assert clear_mot(gt, tracks)["MOTA"] == 1.0


@pytest.mark.parametrize("scenario, section, key", [("maneuver", "stationary", "sigma"),
                                                    ("formation", "scenario", "dt"),
                                                    ("jtc", "trajectory", "speed"), ("pedestrian", "scene", "dt")])
def test_scenario_configs_refuse_wrong_types_and_unknown_keys_naming_the_key(scenario, section, key, tmp_path,
                                                                             capsys):
    import yaml

    from torchtrack.config import preset_path

    doc = yaml.safe_load(preset_path(scenario).read_text())
    doc[section][key] = "abc"
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(doc))
    assert main(["scenario", scenario, "--config", str(bad), "--runs", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"torchtrack scenario: error: {bad}: {section}.{key} must be a finite number; got 'abc'"]
    doc[section][key] = "1e-1"                  # PyYAML reads this as a string: taken as the number
    doc[section]["typo"] = 1
    bad.write_text(yaml.safe_dump(doc))
    assert main(["scenario", scenario, "--config", str(bad), "--runs", "1"]) == 2
    assert f"unknown key(s) ['{section}.typo']" in capsys.readouterr().err


def _random_frames(rng, n_frames=6, n=300, size=400.0):
    start = rng.uniform(0, size, (n, 2))
    velocity = rng.normal(0, 2, (n, 2))
    return [start + k * velocity + rng.normal(0, 0.5, (n, 2)) for k in range(n_frames)]


def test_sort_on_gated_pairs_equals_the_dense_assignment(monkeypatch):
    import torch

    import torchtrack.filters.trackers.sort as sort_module
    from torchtrack.filters.trackers.options import SORTConfig

    frames = _random_frames(np.random.default_rng(1))

    def run():
        tracker = sort_module.SORT(SORTConfig(max_distance=6.0, min_hits=1))
        return [tuple(t.tolist() for t in tracker.step(k + 1, torch.as_tensor(z))) for k, z in enumerate(frames)]

    dense = run()
    monkeypatch.setattr(sort_module, "DENSE_PAIRS", 0)       # every frame through the k-d tree and components
    assert run() == dense


def test_greedy_on_gated_pairs_equals_the_brute_force_rule():
    import torch

    from torchtrack.filters.trackers.greedy import GreedyTracker
    from torchtrack.filters.trackers.options import GreedyConfig

    frames = _random_frames(np.random.default_rng(2))
    tracker = GreedyTracker(GreedyConfig(max_distance=5.0, max_age=1))
    pos, ids, age, next_id = np.empty((0, 2)), np.empty(0, np.int64), np.empty(0, np.int64), 1
    for k, z in enumerate(frames):
        got, _ = tracker.step(k + 1, torch.as_tensor(z))
        # brute force: detections in order take the nearest free track within the gate (ties: earlier track)
        want, taken = np.zeros(len(z), np.int64), np.zeros(len(pos), bool)
        for i, p in enumerate(z):
            d = np.where(taken, np.inf, np.hypot(*(pos - p).T) if len(pos) else np.zeros(0))
            d[d > 5.0] = np.inf
            if len(d) and np.isfinite(d.min()):
                j = int(np.argmin(d))
                taken[j], want[i] = True, ids[j]
        new = want == 0
        want[new] = np.arange(next_id, next_id + new.sum())
        next_id += int(new.sum())
        keep = age[~taken] + 1 <= 1
        pos = np.concatenate([z, pos[~taken][keep]])
        ids, age = np.concatenate([want, ids[~taken][keep]]), np.concatenate([np.zeros(len(z), np.int64),
                                                                              (age[~taken] + 1)[keep]])
        assert got.tolist() == want.tolist()
