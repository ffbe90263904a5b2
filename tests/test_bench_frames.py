"""``torchtrack bench scale --frame-sizes``: the pipeline over frame sizes, its JSON rows and its scores
recomputed from the files it wrote."""

import json

import numpy as np
import pytest

from torchtrack.bench import frames
from torchtrack.cli import main
from torchtrack.io.mot import concat_mot, read_mot
from torchtrack.metrics.clear_mot import clear_mot

ROW_KEYS = {"size", "sequences", "frames", "megapixels", "seconds", "cpu_seconds", "mpx_per_s", "mpx_per_cpu_s",
            "stage_mpx_per_s", "peak_memory_mb", "process_peak_mb", "mota", "detection_f1", "detection_precision",
            "detection_recall", "registration_error_px", "registration_error_max_px", "moving_truth"}


def parked(gt, velocity_txt):
    """Truth lines not flagged moving in the generator's velocity.txt (frame,id,vx,vy,moving)."""
    moving = {(int(r[0]), int(r[1])) for r in np.genfromtxt(velocity_txt, delimiter=",", ndmin=2) if r[4] == 1}
    return np.array([(int(f), int(i)) not in moving for f, i in zip(gt.frame, gt.id)])


def pooled(parts):
    """``(gt, pred, ignore)`` parts pooled with frames and identities offset so that sequences never mix."""
    gts, preds, masks, frame_off, id_off = [], [], [], 0, 0
    for gt, pred, ignore in parts:
        gts.append(gt._replace(frame=gt.frame + frame_off, id=gt.id + id_off))
        preds.append(pred._replace(frame=pred.frame + frame_off, id=pred.id + id_off))
        masks.append(ignore)
        frame_off += 1000
        id_off += 10**6
    return concat_mot(gts), concat_mot(preds), np.concatenate(masks)


def test_rows_and_scores_recomputed_from_the_written_files(tmp_path):
    out, report = tmp_path / "out", tmp_path / "bench.json"
    assert main(["bench", "scale", "--frame-sizes", "128", "192", "--frames", "5", "--sequences", "2", "1",
                 "--out", str(out), "--json", str(report), "--plot", str(tmp_path / "frames.png")]) == 0
    payload = json.loads(report.read_text())
    assert payload["unit"] == "megapixels" and payload["reference"] == "128x128"
    assert {r["size"]: r["sequences"] for r in payload["rows"]} == {128: 2, 192: 1}
    assert json.loads((out / "bench.json").read_text())["rows"][0]["size"] == 128
    for row in payload["rows"]:
        assert set(row) == ROW_KEYS and set(row["stage_mpx_per_s"]) == set(frames.STAGES)
        size = row["size"]
        assert row["megapixels"] == pytest.approx(row["sequences"] * 5 * size * size / 1e6)
        assert row["mpx_per_s"] == pytest.approx(row["megapixels"] / row["seconds"])
        assert row["registration_error_px"] < 1.0
        tracks, detections = [], []
        for seq in sorted((out / str(size) / "sequences").iterdir()):
            gt = read_mot(seq / "gt.txt")
            ignore = parked(gt, seq / "velocity.txt")
            run = out / str(size) / "run" / seq.name
            tracks.append((gt, read_mot(run / "tracks.txt"), ignore))
            det = read_mot(run / "detections.txt")
            detections.append((gt, det._replace(id=np.arange(det.size)), ignore))
        assert len(tracks) == row["sequences"]
        mot = clear_mot(*pooled(tracks)[:2], threshold=10.0, ignore=pooled(tracks)[2])
        assert row["mota"] == pytest.approx(mot["MOTA"], abs=1e-12)
        assert row["moving_truth"] == mot["GT"] > 0
        found = clear_mot(*pooled(detections)[:2], threshold=10.0, ignore=pooled(detections)[2])
        tp, fp, fn = found["TP"], found["FP"], found["FN"]
        assert tp > 0
        assert row["detection_f1"] == pytest.approx(2 * tp / (2 * tp + fp + fn), abs=1e-12)
        assert row["detection_recall"] == pytest.approx(tp / (tp + fn), abs=1e-12)
    assert (tmp_path / "frames.png").read_bytes()[:4] == b"\x89PNG"


def test_default_sequences_give_each_size_the_pixels_of_the_largest():
    assert frames.default_sequences([512, 1024, 2048, 4096]) == [32, 16, 4, 1]
    assert frames.default_sequences([300, 400]) == [2, 1]


def test_the_vehicle_options_are_refused_with_frame_sizes(capsys):
    assert main(["bench", "scale", "--frame-sizes", "64", "--trackers", "sort"]) == 2
    assert "--trackers do not apply to --frame-sizes" in capsys.readouterr().err
    assert main(["bench", "scale", "--frame-sizes", "64", "128", "--sequences", "1", "2", "3"]) == 2
    assert "--sequences: give one count or one per frame size (2)" in capsys.readouterr().err
