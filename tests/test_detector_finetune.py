"""Fine-tuning on labelled frames: the region mask, region-restricted scores, bad truth, and a fine-tune on
a synthetic "other sensor" that raises its held-out F1."""

import dataclasses

import cv2
import numpy as np
import pytest
import torch

from torchtrack.cli import main
from torchtrack.detector.checkpoint import load_checkpoint
from torchtrack.detector.config import config_from_dict
from torchtrack.detector.dataset import PairDataset
from torchtrack.detector.decode import Detections
from torchtrack.detector.finetune import finetune
from torchtrack.detector.inference import Detector, detector_from_checkpoint
from torchtrack.detector.labelled import evaluate_labelled, label_frames
from torchtrack.detector.losses import detection_loss
from torchtrack.detector.region import Region
from torchtrack.detector.unlabelled import dont_care_mask, unlabelled_detections
from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import from_points
from torchtrack.sim.video import generate_sequence
from torchtrack.sim.video_config import from_dict

TINY_VIDEO = {"height": 96, "width": 96, "margin": 16, "trees": 20, "speckles": 10, "buildings": 2,
              "car_parks": 1, "highways": 1, "local_roads": 1, "lane_density": 0.04}


def tiny_config(tmp_path, **finetune):
    return config_from_dict({
        "model": {"widths": [8, 12, 16], "head": 8},
        "data": {"train_sequences": 2, "val_sequences": 1, "frames": 3, "cache": str(tmp_path / "cache"),
                 "crop": 64, "video": TINY_VIDEO},
        "train": {"epochs": 1, "steps_per_epoch": 2, "batch": 4, "out": str(tmp_path / "run"), "val_frames": 2},
        "finetune": {"out": str(tmp_path / "ft"), **finetune},
    })


def labelled_sequence(video: dict, seed: int, frames: int, keep=None):
    """LabelledFrames of a generated sequence; its truth as points (``keep(xy)``: which points to label)."""
    seq = list(generate_sequence(from_dict({**video, "frames": frames}), torch.Generator().manual_seed(seed)))
    rows = [(k, i, x, y) for k, f in enumerate(seq, start=1) for i, (x, y) in zip(f.ids, f.xy)
            if keep is None or keep(np.array([[x, y]]))[0]]
    k, i, x, y = (np.array(c) for c in zip(*rows))
    truth = from_points(k.astype(np.int64), i.astype(np.int64), x, y)
    return label_frames(np.stack([f.image for f in seq]), truth, "<generated>")


def test_cells_outside_the_region_are_neither_positive_nor_negative(tmp_path):
    cfg = tiny_config(tmp_path)
    region = Region(0, 0, 40, 96)
    # only the region is labelled: vehicles right of it are in the image but not in the truth
    data = labelled_sequence(TINY_VIDEO, 3, 3, keep=region.contains)
    pairs = PairDataset(data.as_cache(), cfg, 0, region=region)
    x, tg = pairs[0]
    assert 0 < tg.labelled.sum() < tg.labelled.numel()
    assert tg.labelled.sum() == (40 // 2) * (64 // 2)            # the crop covers the 40-px-wide region
    net = Detector(cfg).net
    torch.manual_seed(0)
    hm, off, vel = net(x[None])
    batch = type(tg)(*(t[None] for t in tg))
    outside = ~tg.labelled[None, None]
    firing = torch.where(outside, torch.full_like(hm, 8.0), hm)   # fires everywhere outside
    quiet = torch.where(outside, torch.full_like(hm, -8.0), hm)
    loud, _ = detection_loss((firing, torch.where(outside, off + 3, off), torch.where(outside, vel + 3, vel)), batch)
    calm, _ = detection_loss((quiet, off, vel), batch)
    assert loud.item() == pytest.approx(calm.item(), rel=1e-6)
    unmasked = batch._replace(labelled=torch.ones_like(batch.labelled))
    assert detection_loss((firing, off, vel), unmasked)[0] > detection_loss((quiet, off, vel), unmasked)[0] + 1


class FixedDetector:
    """Stands in for the detector: the same detections on every frame."""

    def __init__(self, cfg, xy):
        self.config, self.xy = cfg, torch.tensor(xy, dtype=torch.float32)

    def detect(self, frame, prev_frame=None, prev_points=None, prev_velocity=None):
        n = len(self.xy)
        return Detections(self.xy, torch.ones(n), torch.zeros(n, 2), torch.ones(n, dtype=torch.bool))


def test_scores_count_only_what_lies_inside_the_region(tmp_path):
    cfg = dataclasses.replace(tiny_config(tmp_path), data=dataclasses.replace(tiny_config(tmp_path).data,
                                                                               register=False))
    frames = np.random.default_rng(0).integers(0, 255, (2, 40, 60), dtype=np.uint8)
    truth = from_points(np.array([1, 1, 2, 2]), np.array([1, 2, 1, 2]), np.array([10.0, 50, 10, 50]),
                        np.array([10.0, 10, 10, 10]))
    data = label_frames(frames, truth, "gt.txt")
    # a hit inside, a false detection inside, a false one outside; truth at x = 50 (outside) undetected
    det = FixedDetector(cfg, [[10.5, 10.0], [20.0, 30.0], [45.0, 30.0]])
    inside = evaluate_labelled(det, data, Region(0, 0, 30, 40))["all"]
    assert (inside["tp"], inside["fp"], inside["fn"]) == (2, 2, 0)
    everywhere = evaluate_labelled(det, data)["all"]
    assert (everywhere["tp"], everywhere["fp"], everywhere["fn"]) == (2, 4, 2)


def test_vehicles_the_truth_does_not_list_are_neither_positive_nor_negative(tmp_path):
    """A detection of the starting weights far from every truth point (an unlisted parked car) is
    don't-care within ``unlabelled_radius``; the truth points stay positive."""
    cfg = dataclasses.replace(tiny_config(tmp_path), data=dataclasses.replace(tiny_config(tmp_path).data,
                                                                               register=False))
    frames = np.random.default_rng(1).integers(0, 255, (2, 64, 64), dtype=np.uint8)
    corners = np.array([[10.0, 10], [53, 10], [10, 53], [53, 53]])   # a set every flip/transposition keeps
    truth = from_points(np.repeat([1, 2], 4), np.tile(np.arange(1, 5), 2), np.tile(corners[:, 0], 2),
                        np.tile(corners[:, 1], 2))
    data = label_frames(frames, truth, "gt.txt")
    det = FixedDetector(cfg, [[12.0, 16.0], [31.5, 31.5]])     # the first is the vehicle at (10, 10)
    unlisted = unlabelled_detections(det, data)
    assert [p.tolist() for p in unlisted] == [[[31.5, 31.5]]] * 2
    radius = cfg.finetune.unlabelled_radius
    pairs = PairDataset(data.as_cache(), cfg, 0, dont_care=dont_care_mask(unlisted, (64, 64), radius)[None])
    x, tg = pairs[0]
    # brute force: a 2 x 2-pixel cell is don't-care when one of its pixels lies within the radius
    rows, cols = np.mgrid[0:64, 0:64]
    near = ((cols - 31.5) ** 2 + (rows - 31.5) ** 2 <= radius ** 2).reshape(32, 2, 32, 2).any(3).any(1)
    assert near.sum() > 0
    assert np.array_equal(tg.labelled.numpy(), ~near)
    assert tg.centre.sum() == 4 and tg.labelled[tg.centre].all()
    assert torch.equal(tg.heatmap[0][tg.centre], torch.ones(4))
    net = Detector(cfg).net
    torch.manual_seed(0)
    hm, off, vel = net(x[None])
    batch = type(tg)(*(t[None] for t in tg))
    unknown = ~tg.labelled[None, None]
    firing = torch.where(unknown, torch.full_like(hm, 8.0), hm)   # fires on the unlisted vehicle
    quiet = torch.where(unknown, torch.full_like(hm, -8.0), hm)
    assert detection_loss((firing, off, vel), batch)[0].item() == pytest.approx(
        detection_loss((quiet, off, vel), batch)[0].item(), rel=1e-6)
    negative = batch._replace(labelled=torch.ones_like(batch.labelled))  # unlabelled_static: negative
    assert detection_loss((firing, off, vel), negative)[0] > detection_loss((quiet, off, vel), negative)[0] + 1


def write_frames(folder, n=2, shape=(40, 60)):
    folder.mkdir()
    for k in range(n):
        cv2.imwrite(str(folder / f"f{k + 1}.png"), np.full(shape, 60 + k, np.uint8))
    return folder


def test_images_are_scored_on_the_real_frames_as_eval_detector_scores_them(wpafb_data, tmp_path):
    """On the whole frame, without registration, the scores of --images equal the WPAFB part's."""
    from torchtrack.detector.inference import load_detector
    from torchtrack.detector.labelled import read_images
    from torchtrack.detector.wpafb import evaluate_wpafb
    from torchtrack.io.wpafb import read_wpafb_csv

    det = load_detector()
    data = label_frames(read_images(wpafb_data / "frames"),
                        read_wpafb_csv(wpafb_data / "transformed_object_states.csv"), "csv")
    got, want = evaluate_labelled(det, data), evaluate_wpafb(det, wpafb_data)
    for part in ("all", "moving"):
        assert [got[part][k] for k in ("tp", "fp", "fn")] == [want[part][k] for k in ("tp", "fp", "fn")]


def test_bad_truth_and_regions_are_one_line_errors(tmp_path, capsys):
    images = write_frames(tmp_path / "frames")
    gt = tmp_path / "gt.txt"
    gt.write_text("1,1,5,5,10,10,1,-1,-1,-1\n2,1,70,5,10,10,1,-1,-1,-1\n")   # centre x = 75: outside 60 px
    args = ["eval-detector", "--images", str(images), "--gt", str(gt)]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert "gt.txt: frame 2, object 1 at (75.0, 10.0) lies outside the 60 x 40 frames" in err
    assert len(err.splitlines()) == 1
    gt.write_text("1,1,5,5,10,10,1,-1,-1,-1\n")
    for region, why in (("10 5 10 30", "empty"), ("0 0 61 40", "reaches outside")):
        assert main(args + ["--region", *region.split()]) == 2
        err = capsys.readouterr().err.strip()
        assert f"--region {region}: {why}" in err and len(err.splitlines()) == 1
    assert main(["eval-detector", "--images", str(images)]) == 2
    assert "--images needs its truth" in capsys.readouterr().err
    with pytest.raises(TorchtrackError, match="<generated>: frame 1"):
        label_frames(np.zeros((2, 10, 10), np.uint8), from_points(np.array([1]), np.array([1]), np.array([-1.0]),
                                                                  np.array([3.0])), "<generated>")


def test_finetune_on_another_sensor_raises_its_held_out_f1(tmp_path):
    """Points-only labels of three frames of a sensor whose vehicles are all dark and of low contrast on a
    smooth ground teach a tiny untrained detector to find them on another sequence of that sensor."""
    scene = {"height": 96, "width": 96, "margin": 16, "trees": 0, "speckles": 0, "buildings": 0,
             "forest_fraction": 0.0, "car_parks": 1, "highways": 1, "local_roads": 1, "lane_density": 0.04,
             "bright_fraction": 0.0, "dark_tone": [20.0, 35.0], "background_std": 6.0}
    cfg = config_from_dict({
        "model": {"widths": [8, 8, 8], "head": 8, "motion": 4, "radius": 2},
        "data": {"cache": str(tmp_path / "cache"), "crop": 48, "video": scene, "register": False},
        "decode": {"threshold": 0.2, "refine_radius": 0},
        "finetune": {"out": str(tmp_path / "ft"), "steps": 40, "batch": 8, "lr": 0.01, "synthetic_share": 0.0},
    })
    torch.manual_seed(0)
    base = Detector(cfg).eval()
    held_out = labelled_sequence(scene, 12, 3)
    before = evaluate_labelled(base, held_out)["all"]["f1"]
    result = finetune(cfg, base.net.state_dict(), labelled_sequence(scene, 11, 3), Region(0, 0, 96, 96), seed=0,
                      progress=False)
    after = evaluate_labelled(detector_from_checkpoint(load_checkpoint(result["last"])), held_out)["all"]
    assert before < 0.1 and after["f1"] > 0.4, (before, after)
    assert after["tp"] > 0.5 * (after["tp"] + after["fn"])


def test_finetune_and_eval_commands_run_as_documented(tmp_path, capsys):
    import json

    import yaml

    from torchtrack.detector.checkpoint import save_checkpoint

    cfg = tiny_config(tmp_path)
    weights = tmp_path / "base.pt"
    save_checkpoint(weights, {"config": dataclasses.asdict(cfg), "model": Detector(cfg).net.state_dict()})
    seq = list(generate_sequence(from_dict({**TINY_VIDEO, "frames": 3}), torch.Generator().manual_seed(5)))
    images = tmp_path / "frames"
    images.mkdir()
    lines = []
    for k, f in enumerate(seq, start=1):
        cv2.imwrite(str(images / f"{k:06d}.png"), f.image)
        lines += [f"{k},{i},{x - 5:.2f},{y - 5:.2f},10,10,1,-1,-1,-1" for i, (x, y) in zip(f.ids, f.xy)]
    gt = tmp_path / "gt.txt"
    gt.write_text("\n".join(lines) + "\n")
    settings = tmp_path / "ft.yaml"
    settings.write_text(yaml.safe_dump({"finetune": {"steps": 2, "batch": 2, "synthetic_share": 0.5,
                                                     "synthetic_sequences": 1, "registration": "none"}}))
    out = tmp_path / "adapted.pt"
    assert main(["train-detector", "--finetune", str(weights), "--images", str(images), "--gt", str(gt),
                 "--region", "0", "0", "48", "96", "--config", str(settings), "--out", str(tmp_path / "ft"),
                 "--export", str(out), "--no-progress", "--seed", "1"]) == 0
    exported = load_checkpoint(out)
    assert exported["config"].finetune.steps == 2 and exported["config"].model == cfg.model
    assert "--region 0 0 48 96" in exported["command"]
    report = tmp_path / "eval.json"
    assert main(["eval-detector", "--weights", str(out), "--images", str(images), "--gt", str(gt),
                 "--region", "48", "0", "96", "96", "--json", str(report)]) == 0
    scores = json.loads(report.read_text())
    assert scores["region"] == [48, 0, 96, 96]
    assert set(scores["images"]) == {"all", "moving"} and {"precision", "recall", "f1"} <= set(scores["images"]["all"])
    assert main(["train-detector", "--finetune", str(weights), "--images", str(images), "--gt", str(gt),
                 "--epochs", "3"]) == 2
    assert "--epochs does not apply to --finetune" in capsys.readouterr().err


def test_labels_link_ids_mark_repeats_and_moving_vehicles():
    frames = np.zeros((3, 20, 40), np.uint8)
    frames[0, 0, 0] = frames[1, 0, 0] = 9                     # frame 2 repeats frame 1
    # id 1 moves 3 px a frame (to frame 4, beyond the images); id 2 stays; id -1 (unlabelled) twice
    ident = np.array([1, 1, 1, 1, 2, 2, 2, -1, -1])
    frame = np.array([1, 2, 3, 4, 1, 2, 3, 2, 3])
    x = np.array([5.0, 8, 11, 14, 20, 20, 20, 30, 35])
    data = label_frames(frames, from_points(frame, ident, x, np.full(9, 10.0)), "gt.txt")
    assert data.repeated.tolist() == [False, True, False]
    # moving: more than 5 px from here at some later frame (9, 6, then only 3 px to go)
    assert [d.tolist() for d in data.moving] == [[True, False], [True, False, False], [False, False, False]]
    assert np.isnan(data.velocity[0]).all() and np.isnan(data.velocity[1]).all()      # first and repeated
    np.testing.assert_array_equal(data.velocity[2][:2], [[3.0, 0.0], [0.0, 0.0]])
    assert np.isnan(data.velocity[2][2]).all()                                         # id -1 never links
