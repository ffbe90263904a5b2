"""A calibration that knows when it failed, and calibration from frames: each sign of a failed fit on a built
calibration; a harsh positions-only sensor never gives a tracker that reports nothing where the built-in one
reports tracks; ``track --frames --calibrate``, ``calibrate --from-frames`` and ``torchtrack.track(calibrate=N)``
agree with each other and with ``track --config`` of the file they write."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from test_calibrate import SIZE, _truth

import torchtrack
from torchtrack.cli import main
from torchtrack.filters.trackers.protocol import make_tracker
from torchtrack.io.mot import read_mot
from torchtrack.sim.detections import simulate_detections
from torchtrack.sim.video import VideoConfig, write_sequence
from torchtrack.tuning.calibrate import Q_GRID, Calibration
from torchtrack.tuning.calibration import calibrate
from torchtrack.tuning.decisions import frame_inputs, merged, run_frames
from torchtrack.tuning.fit_check import fit_problems, fit_warnings


def _calibration(**values) -> Calibration:
    v = {"sigma": 1.2, "p_detection": 0.85, "clutter_density": 1e-4, "q": 1.0, **values}
    return Calibration(values=v, stderr={"sigma": 0.01, "p_detection": 0.01}, loglik_before=0.0, loglik_after=1.0,
                       trace=[], frames=(1, 100), region=(0, 0, 500, 500), detections=1000, velocities=False,
                       tracks=40, detected_share=0.88)


def test_each_sign_of_a_failed_fit_is_named():
    assert fit_problems(_calibration(), 0.6) == []
    assert fit_problems(_calibration(q=float(Q_GRID[-1])), 0.6) == [f"q {float(Q_GRID[-1]):.3g} at an end of its grid"]
    assert "under half the tracks' detected share" in fit_problems(_calibration(p_detection=0.3), 0.6)[0]
    assert fit_problems(_calibration(sigma=100.0), 0.6) == ["sigma 100 at its bound"]
    assert fit_problems(_calibration(), 0.01) == ["bootstrap MOTA 0.010 under 0.05"]
    cal = _calibration()
    cal.stderr["sigma"] = float("nan")          # a warning only: sound fits on sharp sensors have them too
    assert fit_problems(cal, 0.6) == [] and fit_warnings(cal) == ["standard error of sigma not finite"]


def test_merged_sets_keys_mapping_into_mapping():
    base = {"filter": {"q": 1.0, "p_detection": 0.8}, "confirm_new": True}
    assert merged(base, {"filter": {"q": 2.0}, "birth": {"birth_weight": 0.01}}) == {
        "filter": {"q": 2.0, "p_detection": 0.8}, "confirm_new": True, "birth": {"birth_weight": 0.01}}
    assert base["filter"]["q"] == 1.0


def test_a_harsh_positions_only_sensor_never_gives_a_tracker_that_reports_nothing():
    truth = _truth(n=40, frames=70, seed=2)
    det = simulate_detections(truth, pd=0.6, sigma=3.5, clutter=250, image_size=tuple(SIZE), velocity_sigma=None,
                              generator=torch.Generator().manual_seed(5)).detections
    result = calibrate(det, (1, 50))
    assert result.status == "defaults"       # the E-step follows clutter from either start: the fit collapses
    assert "q 50 at an end of its grid" in result.problems[0]
    held_out = frame_inputs(det.select(det.frame > 50))
    calibrated = run_frames(make_tracker("gmphd", result.sections["gmphd"]), held_out)
    built_in = run_frames(make_tracker("gmphd", {}), held_out)
    assert built_in.size > 0
    assert calibrated.size > 0
    measured = result.sections["gmphd"]["positions_only"]["filter"]                    # whatever the tracks
    assert measured["clutter_density"] == pytest.approx(250 / SIZE.prod(), rel=0.2)
    assert 3.5 <= measured["sigma"] <= 1.5 * 3.5           # the sensor's 3.5 px, widened by nearby clutter
    assert "built-in options with the measured clutter density" in result.message
    assert "from consecutive frames" in result.message


@pytest.fixture(scope="module")
def camera(tmp_path_factory):
    """A short synthetic sequence of a camera other than the default one (blurred, noisier, larger vehicles)."""
    config = VideoConfig(height=256, width=256, frames=24, psf_sigma=1.6, noise_std=4.0)
    return write_sequence(config, torch.Generator().manual_seed(7), tmp_path_factory.mktemp("cam"))


def test_track_frames_calibrate_is_track_with_the_file_it_writes(camera, tmp_path):
    frames, gt = str(camera / "frames"), str(camera / "gt.txt")
    out = tmp_path / "cal"
    assert main(["track", "--frames", frames, "--gt", gt, "--calibrate", "20", "--no-video", "--no-progress",
                 "--out", str(out)]) == 0
    record = json.loads((out / "calibration.json").read_text())
    assert record["status"] in ("ok", "retried", "defaults") and record["message"]
    assert {"tracks.txt", "track.yaml", "calibration.json", "loss.png", "metrics.json"} <= {
        p.name for p in out.iterdir()}
    again = tmp_path / "config"
    assert main(["track", "--frames", frames, "--gt", gt, "--config", str(out / "track.yaml"), "--no-video",
                 "--no-progress", "--out", str(again)]) == 0
    first, second = read_mot(out / "tracks.txt"), read_mot(again / "tracks.txt")
    np.testing.assert_array_equal(first.frame, second.frame)
    np.testing.assert_allclose(first.x, second.x)
    separate = tmp_path / "separate"
    assert main(["calibrate", "--from-frames", frames, "--frames", "1", "20", "--out", str(separate)]) == 0
    assert (separate / "track.yaml").read_text().splitlines()[1:] == (out / "track.yaml").read_text().splitlines()[1:]
    api = torchtrack.track(frames=frames, calibrate=20, draw_video=False)
    rows = np.loadtxt(out / "tracks.txt", delimiter=",", ndmin=2)
    rows = rows[np.lexsort((rows[:, 1], rows[:, 0]))]
    np.testing.assert_allclose(api.tracks[:, :4], rows[:, :4], atol=6e-4)
    assert api.calibration["status"] == record["status"]
    assert {"config", "calibration", "loss", "tracks"} <= set(api.files)


def _error(capsys, argv, command) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"torchtrack {command}: error: ")
    return err[0]


def test_bad_calibrate_arguments(camera, tmp_path, capsys):
    frames = str(camera / "frames")
    assert "--velocity no" in _error(capsys, ["calibrate", "--from-frames", frames, "--velocity", "no", "--out",
                                              str(tmp_path / "a")], "calibrate")
    assert "--sequences" in _error(capsys, ["track", "--sequences", str(camera.parent), "--calibrate", "5", "--out",
                                            str(tmp_path / "b")], "track")
    assert "at least 3 frames" in _error(capsys, ["calibrate", "--from-frames", frames, "--frames", "1", "3",
                                                  "--out", str(tmp_path / "c")], "calibrate")
    assert not any((tmp_path / x).exists() for x in "abc")
