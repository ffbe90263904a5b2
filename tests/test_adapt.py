"""train-detector --adapt: self-training rounds on a video without labels, and its bad input."""

import subprocess
import sys

import cv2
import numpy as np
import pytest
import torch

import torchtrack.pipeline.adapt as adapt_module
from tests.test_registration_homography import _texture
from torchtrack.detector import load_detector
from torchtrack.detector.checkpoint import load_checkpoint
from torchtrack.detector.config import FinetuneConfig
from torchtrack.io.frames import FolderSource
from torchtrack.pipeline.adapt import AdaptSettings, adapt, label_change
from torchtrack.pipeline.pseudo_labels import pseudo_labels
from torchtrack.sim.video import VideoConfig, write_sequence

QUICK = FinetuneConfig(steps=2, batch=2, synthetic_sequences=1, unlabelled_static="negative")


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    seq = write_sequence(VideoConfig(height=192, width=192, frames=16), torch.Generator().manual_seed(4),
                         tmp_path_factory.mktemp("adapt") / "seq")
    return np.stack([f.image for f in FolderSource(seq / "frames")])


def test_rounds_fine_tune_on_confident_tracks_with_unsure_cells_dont_care(frames, tmp_path, monkeypatch):
    seen = []
    real = adapt_module.finetune

    def spy(cfg, weights, data, region, **kw):
        seen.append((cfg.finetune.unlabelled_static, sum(len(p) for p in data.xy)))
        return real(cfg, weights, data, region, **kw)

    monkeypatch.setattr(adapt_module, "finetune", spy)
    report = adapt(frames, tmp_path, settings=AdaptSettings(rounds=2, min_length=6, stop_change=0.0),
                   finetune_config=QUICK, progress=False, log=lambda *a: None)
    # unsure cells (detections no confident track explains) are never taught as background
    assert [s for s, _ in seen] == ["dont_care", "dont_care"]
    assert [n for _, n in seen] == [r["pseudo_labels"] for r in report["rounds"]]
    weights = tmp_path / report["weights"]
    start, end = load_checkpoint(adapt_module.DEFAULT_WEIGHTS)["model"], load_checkpoint(weights)["model"]
    assert any(not torch.equal(start[k], end[k]) for k in start)
    assert load_detector(weights) is not None                  # the shipped format: track --weights takes it
    assert (tmp_path / "report.json").is_file() and (tmp_path / "adapt.png").is_file()


def test_label_change_counts_points_without_a_counterpart(frames):
    a = pseudo_labels(frames[:2], _rows([(1, 1, 10, 10), (2, 1, 12, 10)]), [np.eye(3)] * 2, 1)
    b = pseudo_labels(frames[:2], _rows([(1, 1, 10.5, 10), (2, 1, 40, 40)]), [np.eye(3)] * 2, 1)
    assert label_change(a, a, 2.0) == 0.0
    assert label_change(a, b, 2.0) == pytest.approx(2 / 4)


def _rows(points):
    from torchtrack.io.mot import from_points
    f, i, x, y = (np.array(c, float) for c in zip(*points))
    return from_points(f.astype(int), i.astype(int), x, y)


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "torchtrack", "train-detector", *args], capture_output=True,
                          text=True, timeout=300)


def _one_line_error(r, *words):
    assert r.returncode != 0 and r.stderr.strip().count("\n") == 0, r.stderr
    assert r.stderr.startswith("torchtrack train-detector: error:") and all(w in r.stderr for w in words), r.stderr


def test_bad_input_is_a_one_line_error(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    _one_line_error(_cli("--adapt", "--frames", str(empty), "--export", str(tmp_path / "w.pt")), "empty")
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    cv2.imwrite(str(mixed / "1.png"), _texture((64, 64), 1))
    cv2.imwrite(str(mixed / "2.png"), _texture((48, 64), 1))
    _one_line_error(_cli("--adapt", "--frames", str(mixed), "--export", str(tmp_path / "w.pt")), "2.png", "64x48")
    short = tmp_path / "short"
    short.mkdir()
    for k in range(3):
        cv2.imwrite(str(short / f"{k + 1}.png"), _texture((96, 96), 1))
    _one_line_error(_cli("--adapt", "--frames", str(short), "--export", str(tmp_path / "w.pt"), "--out",
                         str(tmp_path / "o")), "no track")
    _one_line_error(_cli("--adapt", "--frames", str(short)), "--export")
    assert not (tmp_path / "w.pt").exists()
