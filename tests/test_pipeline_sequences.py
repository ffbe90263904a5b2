"""Many sequences: discovery, exact pooled aggregation, and sharding over two torchrun ranks (gloo)."""

import json
import sys

import numpy as np
import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import read_mot
from torchtrack.io.moving import moving_mask
from torchtrack.io.outputs import MARKER
from torchtrack.metrics import clear_mot
from torchtrack.pipeline.config import PipelineConfig
from torchtrack.pipeline.sequences import concatenate, find_sequences, run_sequences
from torchtrack.sim.video import VideoConfig, write_sequence

# A test-only stand-in detector: the brightest local maxima of the frame (no weights needed).
STANDIN = '''
import cv2, numpy as np, torch
from types import SimpleNamespace

class PeakDetector:
    def detect(self, frame, prev_frame, prev_points):
        blur = cv2.GaussianBlur(frame.astype(np.float32), (0, 0), 1.5)
        peak = (blur == cv2.dilate(blur, np.ones((9, 9), np.uint8))) & (blur > np.percentile(blur, 99.5))
        ys, xs = np.nonzero(peak)
        xy = torch.tensor(np.stack([xs, ys], 1), dtype=torch.float64)
        return SimpleNamespace(xy=xy, score=torch.ones(len(xy)), velocity=torch.zeros(len(xy), 2))
'''


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    root = tmp_path_factory.mktemp("seqs")
    cfg = VideoConfig(height=128, width=128, frames=4)
    for i, name in enumerate(("b_seq", "a_seq", "c_seq")):
        write_sequence(cfg, torch.Generator().manual_seed(20_000_100 + i), root / name)
    (root / "c_seq" / "img1").mkdir()  # the MOTChallenge layout is found too
    for f in (root / "c_seq" / "frames").iterdir():
        f.rename(root / "c_seq" / "img1" / f.name)
    (root / "c_seq" / "frames").rmdir()
    (root / "notes").mkdir()
    (root / "notes" / "readme.txt").write_text("not a sequence")
    (root / "helper.py").write_text(STANDIN)
    return root


def _standin(root):
    sys.path.insert(0, str(root))
    try:
        from helper import PeakDetector
    finally:
        sys.path.remove(str(root))
    return PeakDetector()


def test_find_sequences_layouts_and_warnings(root, tmp_path):
    with pytest.warns(UserWarning, match="skipping 1 folder.*notes"):
        seqs = find_sequences(root)
    assert [s.name for s in seqs] == ["a_seq", "b_seq", "c_seq"]
    assert seqs[2].frames.name == "img1" and seqs[0].gt.name == "gt.txt" and seqs[0].camera is not None
    with pytest.raises(TorchtrackError, match="no sequence found"):
        find_sequences(tmp_path)
    with pytest.raises(TorchtrackError, match="no such folder"):
        find_sequences(tmp_path / "nope")


def test_pooled_aggregate_is_exact():
    gt = read_mot_like([(1, 1, 10, 10), (2, 1, 12, 10), (1, 2, 50, 50), (2, 2, 50, 52)])
    pred = read_mot_like([(1, 7, 10, 11), (2, 8, 12, 10), (1, 3, 50, 50)])
    one = clear_mot(gt, pred)
    both = clear_mot(*concatenate([(gt, pred), (gt, pred)]))
    for k in ("FP", "FN", "IDS", "TP", "GT", "MT", "ML", "FRAG"):
        assert both[k] == 2 * one[k], k
    for k in ("MOTA", "MOTP", "IDF1", "precision", "recall"):
        assert both[k] == pytest.approx(one[k]), k


def read_mot_like(rows):
    from torchtrack.io.mot import from_points

    a = np.array(rows, dtype=float)
    return from_points(a[:, 0], a[:, 1], a[:, 2], a[:, 3])


def test_single_process_and_torchrun_agree(root, tmp_path, run_on_two_ranks):
    cfg = PipelineConfig(tracker="greedy", video=False, min_speed=0.0, min_motion=0.0)  # stand-in: no velocity
    with pytest.warns(UserWarning):
        single = run_sequences(root, tmp_path / "one", cfg, detector=_standin(root), progress=False,
                               compare=["greedy", "sort"])
    assert single["world_size"] == 1 and set(single["sequences"]) == {"a_seq", "b_seq", "c_seq"}
    assert single["registration_error_px"]["median_of_sequence_medians"] < 0.5
    names = ("a_seq", "b_seq", "c_seq")
    gts = [read_mot(root / n / "gt.txt") for n in names]
    parked = np.concatenate([~moving_mask(g, root / n / "velocity.txt") for g, n in zip(gts, names)])
    pooled = clear_mot(*concatenate([(g, read_mot(tmp_path / "one" / n / "tracks.txt")) for g, n in zip(gts, names)]),
                       ignore=parked)
    assert single["aggregate"]["MOTA"] == pytest.approx(pooled["MOTA"])
    assert single["aggregate"]["TP"] == pooled["TP"] > 0
    # --compare: SORT ran on the same detections; its pooled scores are those of its own files.
    sort_files = [read_mot(tmp_path / "one" / n / "trackers" / "sort.txt") for n in names]
    pooled_sort = clear_mot(*concatenate(list(zip(gts, sort_files))), ignore=parked)
    assert set(single["trackers"]) == {"greedy", "sort"}
    assert single["trackers"]["sort"]["IDF1"] == pytest.approx(pooled_sort["IDF1"])
    assert single["trackers"]["greedy"]["MOTA"] == single["aggregate"]["MOTA"]

    script = tmp_path / "shard.py"
    script.write_text(
        "import sys, warnings\n"
        f"sys.path.insert(0, {str(root)!r})\n"
        "from helper import PeakDetector\n"
        "from torchtrack.pipeline.config import PipelineConfig\n"
        "from torchtrack.pipeline.sequences import destroy, run_sequences, shared_output\n"
        "warnings.simplefilter('ignore')\n"
        f"with shared_output({str(tmp_path / 'two')!r}, 'torchtrack track') as staging:\n"
        f"    run_sequences({str(root)!r}, staging, "
        "PipelineConfig(tracker='greedy', video=False, min_speed=0.0, min_motion=0.0),"
        " detector=PeakDetector(), progress=False)\n"
        "destroy()\n")
    run_on_two_ranks(script)
    two = json.loads((tmp_path / "two" / "metrics.json").read_text())
    assert two["world_size"] == 2 and set(two["sequences"]) == {"a_seq", "b_seq", "c_seq"}
    for k in ("MOTA", "IDS", "FP", "FN", "TP", "IDF1"):
        assert two["aggregate"][k] == pytest.approx(single["aggregate"][k]), k
    # Both ranks wrote into one staging folder, committed by rank 0 as one set.
    assert json.loads((tmp_path / "two" / MARKER).read_text()) == {"command": "torchtrack track", "complete": True}
    assert not (tmp_path / "two.partial").exists()
    # Each rank wrote the outputs of its own shard (a, c on rank 0; b on rank 1), all of them complete.
    for n in ("a_seq", "b_seq", "c_seq"):
        assert (tmp_path / "two" / n / "metrics.json").exists()
