"""One definition of "moving vehicles" (:func:`torchtrack.io.moving.moving_mask`): ``torchtrack eval --moving``
on a sequence's ``gt.txt`` and a command's tracks gives the scores that command printed — the demo,
``track --sequences``, ``track --frames/--detections --gt`` (``--score moving``, the default) and the WPAFB
benchmark; ``track --score all`` scores as ``eval`` without ``--moving``."""

import json
import re

import numpy as np
import pytest
import torch

from torchtrack.cli import main
from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import from_points, read_mot
from torchtrack.io.moving import displacement_rule, flags_beside, moving_mask
from torchtrack.metrics.evaluation import evaluate_scores as evaluate
from torchtrack.pipeline.demo import run_demo
from torchtrack.pipeline.wpafb_benchmark import BenchmarkConfig, SimulatedDetector, run_benchmark
from torchtrack.sim.video import VideoConfig, write_sequence

SHORT = VideoConfig(height=256, width=256, frames=8)
SCORED = ("GT", "GT_objects", "TP", "FP", "FN", "IDS", "MT", "PT", "ML")
COUNTED = ("MOTA", "IDF1")
LOCALISED = ("MOTP", "HOTA", "DetA", "AssA")


def _eval_moving(tmp_path, gt, pred, moving: bool = True) -> dict:
    js = tmp_path / "eval.json"
    assert main(["eval", "--gt", str(gt), "--pred", str(pred), *(["--moving"] if moving else []),
                 "--json", str(js)]) == 0
    return json.loads(js.read_text())


def _printed_mota(text: str) -> tuple[str, str]:
    """The protocol line and the MOTA (%) cell of the one-row scores table printed in ``text``."""
    lines = text.splitlines()
    at = next(i for i, line in enumerate(lines) if "MOTA (%)" in line)
    header, row = re.split(r"\s{2,}", lines[at].strip()), lines[at + 2].split()
    return lines[at - 1], row[header.index("MOTA (%)")]


def _same_scores(got: dict, printed: dict, what: str) -> None:
    for key in SCORED:
        assert got[key] == printed[key], (what, key)
    for key in COUNTED:
        assert got[key] == pytest.approx(printed[key], abs=1e-12), (what, key)
    for key in LOCALISED:  # the files hold rounded positions: distances agree to about 1e-5 px
        assert got[key] == pytest.approx(printed[key], abs=1e-3), (what, key)


def test_eval_moving_reproduces_the_demo(tmp_path):
    m = run_demo(tmp_path, seed=1, video_config=SHORT, progress=False)
    seq = tmp_path / "sequence"
    gt = read_mot(seq / "gt.txt")
    flags = flags_beside(seq / "gt.txt")
    assert flags == seq / "velocity.txt"
    # the two candidate definitions disagree on this sequence, so the test tells which one eval uses
    assert (moving_mask(gt, flags) != displacement_rule(gt)).any()
    for name, printed in m["trackers"].items():
        pred = tmp_path / ("tracks.txt" if name == m["tracker"] else f"trackers/{name}.txt")
        got = _eval_moving(tmp_path, seq / "gt.txt", pred)
        assert got["GT_objects"] > 0
        _same_scores(got, printed, name)


def test_eval_moving_reproduces_track_sequences(tmp_path, capsys):
    root = tmp_path / "root"
    write_sequence(SHORT, torch.Generator().manual_seed(20_000_002), root / "s1", progress=False)
    out = tmp_path / "out"
    assert main(["track", "--sequences", str(root), "--out", str(out), "--no-video", "--no-progress"]) == 0
    printed = json.loads((out / "metrics.json").read_text())["sequences"]["s1"]["clear_mot"]
    got = _eval_moving(tmp_path, root / "s1" / "gt.txt", out / "s1" / "tracks.txt")
    _same_scores(got, printed, "track --sequences")


def test_track_gt_prints_the_mota_of_eval_moving(tmp_path, capsys):
    seq = write_sequence(SHORT, torch.Generator().manual_seed(20_000_003), tmp_path / "seq", progress=False)
    gt = seq / "gt.txt"
    out = tmp_path / "frames"
    assert main(["track", "--frames", str(seq / "frames"), "--gt", str(gt), "--out", str(out), "--no-video",
                 "--no-progress"]) == 0
    title, mota = _printed_mota(capsys.readouterr().out)
    moving = _eval_moving(tmp_path, gt, out / "tracks.txt")
    every = _eval_moving(tmp_path, gt, out / "tracks.txt", moving=False)
    assert f"{moving['MOTA']:.4f}" != f"{every['MOTA']:.4f}"     # the protocols differ on this sequence
    capsys.readouterr()
    assert mota == f"{100 * moving['MOTA']:.2f}" and title.startswith("scored on moving vehicles")
    # the detections it wrote, tracked from the file: the same rule
    assert main(["track", "--detections", str(out / "detections.txt"), "--gt", str(gt), "--out",
                 str(tmp_path / "det")]) == 0
    title, mota = _printed_mota(capsys.readouterr().out)
    assert mota == f"{100 * _eval_moving(tmp_path, gt, tmp_path / 'det' / 'tracks.txt')['MOTA']:.2f}"
    assert title.startswith("scored on moving vehicles")
    capsys.readouterr()
    # --score all: every object a target, as eval without --moving
    assert main(["track", "--frames", str(seq / "frames"), "--gt", str(gt), "--out", str(out), "--no-video",
                 "--no-progress", "--score", "all"]) == 0
    title, mota = _printed_mota(capsys.readouterr().out)
    assert mota == f"{100 * every['MOTA']:.2f}" and title.startswith("scored on all objects")


def test_eval_moving_reproduces_the_benchmark(tmp_path):
    # 40 frames: object 1 drives 3 px/frame, object 2 is parked, object 3 starts driving at frame 21
    k = np.arange(1, 41)
    x3 = np.where(k <= 20, 300.0, 300.0 + 4.0 * (k - 20))
    truth = from_points(np.r_[k, k, k], np.repeat([1, 2, 3], 40), np.r_[10 + 3.0 * k, np.full(40, 200.0), x3],
                        np.r_[np.full(40, 50.0), np.full(40, 120.0), np.full(40, 250.0)])
    config = BenchmarkConfig(detections=SimulatedDetector(pd=0.9, sigma=1.0, clutter=2.0, image_size=(400, 300)),
                             subsets=["moving"], trackers=["sort", "greedy"])
    found = run_benchmark(config, truth, tmp_path, seed=3)["moving"]
    assert 0 < found.targets.size < truth.size          # the parked object and the first frames are don't-care
    for name, printed in found.results.items():
        got = evaluate(tmp_path / "moving" / "gt.txt", tmp_path / "moving" / name / "tracks.txt", moving=True)
        _same_scores(got, printed, name)


def test_flags_beside_both_layouts_and_none(tmp_path):
    (tmp_path / "a" / "gt").mkdir(parents=True)
    (tmp_path / "a" / "velocity.txt").write_text("1,1,0.0,0.0,1\n")
    assert flags_beside(tmp_path / "a" / "gt.txt") == tmp_path / "a" / "velocity.txt"
    assert flags_beside(tmp_path / "a" / "gt" / "gt.txt") == tmp_path / "a" / "velocity.txt"
    assert flags_beside(tmp_path / "b" / "gt.txt") is None


def test_flags_mark_lines_and_a_bad_file_is_named(tmp_path):
    gt = from_points(np.array([1, 1, 2]), np.array([1, 2, 1]), np.zeros(3), np.zeros(3))
    flags = tmp_path / "velocity.txt"
    flags.write_text("1,1,,,1\n1,2,0.0,0.0,0\n2,1,3.0,0.0,1\n")
    np.testing.assert_array_equal(moving_mask(gt, flags), [True, False, True])
    flags.write_text("1,1,not,a,flag\n")
    with pytest.raises(TorchtrackError, match="velocity.txt"):
        moving_mask(gt, flags)
