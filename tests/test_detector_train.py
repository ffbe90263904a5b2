"""Detector training pieces: overfitting a tiny batch, checkpoints, config and input errors."""

import dataclasses

import numpy as np
import pytest
import torch

from torchtrack.detector.checkpoint import load_checkpoint, save_checkpoint
from torchtrack.detector.config import DetectorConfig, config_from_dict, load_config
from torchtrack.detector.dataset import PairDataset, build_cache, collate
from torchtrack.detector.inference import Detector, detector_from_checkpoint
from torchtrack.detector.losses import detection_loss
from torchtrack.errors import TorchtrackError

TINY_VIDEO = {"height": 96, "width": 96, "margin": 16, "trees": 20, "speckles": 10, "buildings": 2,
              "car_parks": 1, "highways": 1, "local_roads": 1, "lane_density": 0.04}


def tiny_config(tmp_path) -> DetectorConfig:
    return config_from_dict({
        "model": {"widths": [8, 12, 16], "head": 8},
        "data": {"train_sequences": 2, "val_sequences": 1, "frames": 3, "cache": str(tmp_path / "cache"),
                 "crop": 64, "video": TINY_VIDEO},
        "train": {"epochs": 1, "steps_per_epoch": 2, "batch": 4, "out": str(tmp_path / "run"), "val_frames": 2},
    })


def test_loss_falls_when_overfitting_a_tiny_batch(tmp_path):
    cfg = tiny_config(tmp_path)
    data = PairDataset(build_cache(cfg, "train", 0), cfg, seed=0)
    x, targets = collate([data[i] for i in range(4)])
    assert targets.centre.sum() > 4
    torch.manual_seed(0)
    net = Detector(cfg).net
    opt = torch.optim.Adam(net.parameters(), lr=5e-3)
    losses = []
    for _ in range(60):
        loss, _ = detection_loss(net(x), targets)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.4 * losses[0]
    assert np.mean(losses[-5:]) < np.mean(losses[:5])


def test_dataset_items_are_pure_functions_of_the_index(tmp_path):
    cfg = tiny_config(tmp_path)
    cache = build_cache(cfg, "train", 0)
    a, b = PairDataset(cache, cfg, 0), PairDataset(build_cache(cfg, "train", 0), cfg, 0)
    for i in (0, 3):
        xa, ta = a[i]
        xb, tb = b[i]
        assert torch.equal(xa, xb) and torch.equal(ta.heatmap, tb.heatmap)
    a.set_epoch(1)
    assert not torch.equal(a[0][0], b[0][0])


def test_truncated_and_foreign_checkpoints_are_clear_errors(tmp_path):
    cfg = tiny_config(tmp_path)
    det = Detector(cfg)
    good = tmp_path / "good.pt"
    save_checkpoint(good, {"config": dataclasses.asdict(cfg), "model": det.net.state_dict()})
    loaded = detector_from_checkpoint(load_checkpoint(good))
    for p, q in zip(loaded.net.parameters(), det.net.parameters()):
        assert torch.equal(p, q)
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(TorchtrackError, match="truncated"):
        load_checkpoint(truncated)
    foreign = tmp_path / "foreign.pt"
    torch.save(det.net.state_dict(), foreign)
    with pytest.raises(TorchtrackError, match="not a torchtrack detector checkpoint"):
        load_checkpoint(foreign)
    text = tmp_path / "text.pt"
    text.write_text("hello")
    with pytest.raises(TorchtrackError, match="text.pt"):
        load_checkpoint(text)
    other = tmp_path / "other.pt"
    bigger = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, head=12))
    save_checkpoint(other, {"config": dataclasses.asdict(bigger), "model": det.net.state_dict()})
    with pytest.raises(TorchtrackError, match="do not fit"):
        detector_from_checkpoint(load_checkpoint(other))


def test_config_with_unknown_keys_is_an_error(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("model:\n  widths: [8, 8, 8]\n  depth: 3\n")
    with pytest.raises(TorchtrackError, match="depth"):
        load_config(bad)
    bad.write_text("optimiser:\n  lr: 0.1\n")
    with pytest.raises(TorchtrackError, match="optimiser"):
        load_config(bad)
    bad.write_text("data:\n  video: {height: 128, colour: red}\n")
    with pytest.raises(TorchtrackError, match="colour"):
        load_config(bad)
    bad.write_text("data:\n  crop: 100\n")
    with pytest.raises(TorchtrackError, match="crop"):
        load_config(bad)


def test_frames_of_mismatched_sizes_are_an_error(tmp_path):
    det = Detector(tiny_config(tmp_path)).eval()
    frame = np.zeros((40, 50), np.uint8)
    with pytest.raises(TorchtrackError, match="different sizes"):
        det.detect(frame, np.zeros((40, 52), np.uint8))
    with pytest.raises(TorchtrackError, match="prev_points"):
        det.detect(frame, frame, np.zeros((3, 3)))
    with pytest.raises(TorchtrackError, match="prev_velocity"):
        det.detect(frame, frame, np.array([[10.0, 12.0]]), prev_velocity=np.zeros((2, 2)))
    out = det.detect(frame, frame, np.array([[10.0, 12.0]]))    # odd sizes are padded internally
    assert out.xy.shape[-1] == 2 and len(out.score) == len(out.xy)


def test_export_calibrates_the_threshold_on_validation(tmp_path):
    from torchtrack.detector.evaluate import evaluate_cache
    from torchtrack.detector.train import THRESHOLDS, export_weights

    cfg = tiny_config(tmp_path)
    torch.manual_seed(0)
    det = Detector(cfg)
    with torch.no_grad():
        det.net.heads.bias[:4] = 0.0       # scores near 0.5: the threshold matters
    save_checkpoint(tmp_path / "best.pt", {"config": dataclasses.asdict(cfg), "model": det.net.state_dict()})
    val = build_cache(cfg, "val", 0)
    out = export_weights(tmp_path / "best.pt", tmp_path / "w.pt", calibrate=val)
    ck = load_checkpoint(out)
    rows = ck["calibration"]
    assert [r["threshold"] for r in rows] == list(THRESHOLDS)
    thr = ck["config"].decode.threshold
    assert thr == max(rows, key=lambda r: r["f1"])["threshold"]
    again = detector_from_checkpoint(ck)
    assert evaluate_cache(again, val, cfg.train.val_frames, cfg.decode.radius)["f1"] == pytest.approx(
        max(r["f1"] for r in rows))


def test_data_loading_workers_do_not_change_the_result(tmp_path):
    from torchtrack.detector.train import train

    cfg = tiny_config(tmp_path)
    params = []
    for workers in (0, 2):
        run = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, out=str(tmp_path / f"w{workers}")))
        result = train(run, seed=0, progress=False, log=lambda *_: None, workers=workers)
        params.append(load_checkpoint(result["last"])["model"])
    assert params[0].keys() == params[1].keys()
    for k in params[0]:
        assert torch.equal(params[0][k], params[1][k]), k

