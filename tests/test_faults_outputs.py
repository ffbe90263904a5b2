"""Outputs whole or not at all (issue 25): a rerun into the same folder that fails or is killed (SIGINT,
SIGKILL) leaves the previous complete set byte for byte, with metrics that agree with the tracks beside
them; the next run cleans up; foreign folders, files and unwritable places are refused before any work."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from torchtrack.cli import main
from torchtrack.io.mot import from_points, read_mot, write_motdata
from torchtrack.io.outputs import MARKER, OutputFolder
from torchtrack.metrics.evaluation import evaluate_scores

ROOT = Path(__file__).resolve().parents[1]
SCORED = ("MOTA", "FP", "FN", "IDS", "TP")


def _targets(frames: int, n: int = 6, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame numbers, ids and centres (K, 2) of ``n`` targets on straight lines over ``frames`` frames."""
    rng = np.random.default_rng(seed)
    start, vel = rng.uniform(60, 400, (n, 2)), rng.uniform(-0.5, 0.5, (n, 2))
    xy = (start[None] + vel[None] * np.arange(frames)[:, None, None]).reshape(-1, 2)
    return np.repeat(np.arange(1, frames + 1), n), np.tile(np.arange(1, n + 1), frames), xy


def _detection_files(folder: Path, frames: int) -> tuple[Path, Path]:
    """``gt.txt`` and ``det.txt`` (the truth plus 0.5 px noise, unlabelled) of :func:`_targets` in ``folder``."""
    f, ids, xy = _targets(frames)
    folder.mkdir(parents=True, exist_ok=True)
    write_motdata(folder / "gt.txt", from_points(f, ids, xy[:, 0], xy[:, 1]))
    det = xy + np.random.default_rng(1).normal(0, 0.5, xy.shape)
    write_motdata(folder / "det.txt", from_points(f, np.full(f.size, -1), det[:, 0], det[:, 1]))
    return folder / "gt.txt", folder / "det.txt"


def _benchmark_config(folder: Path, frames: int) -> Path:
    """A WPAFB-style truth CSV of :func:`_targets` and a benchmark config on it (two trackers, one subset)."""
    f, ids, xy = _targets(frames)
    n = int(ids.max())
    folder.mkdir(parents=True, exist_ok=True)
    header = ["Frame Number"] + [f"obj_{i}_{c}" for i in range(1, n + 1) for c in ("px", "py", "vx", "vy", "ax", "ay")]
    rows = [",".join(header)]
    for k in range(frames):
        cells = [str(100 + k)]
        for cx, cy in xy[f == k + 1]:
            cells += [f"{cy:.3f}", f"{cx:.3f}", "0", "0", "0", "0"]  # px is the row, py the column
        rows.append(",".join(cells))
    rows.append(",".join(["0"] * len(header)))
    (folder / "truth.csv").write_text("\n".join(rows) + "\n")
    config = {"truth": str(folder / "truth.csv"), "subsets": ["all"], "trackers": ["gmphd", "sort"],
              "detections": {"pd": 0.9, "sigma": 1.0, "clutter": 2.0, "velocity_sigma": 1.0,
                             "image_size": [500, 500]}}
    (folder / "benchmark.yaml").write_text(json.dumps(config))  # JSON is YAML
    return folder / "benchmark.yaml"


def _snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (relative path → bytes)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _assert_metrics_match_tracks(run: Path, gt: Path, moving: bool = True) -> None:
    """``run/metrics.json`` holds the CLEAR-MOT of ``run/tracks.txt`` against ``gt`` (10 px; ``moving``: the
    moving vehicles, track's default protocol, as ``eval --moving``; else every object)."""
    metrics = json.loads((run / "metrics.json").read_text())
    rescored = evaluate_scores(gt, run / "tracks.txt", threshold=10.0, moving=moving)
    assert {k: metrics[k] for k in SCORED} == pytest.approx({k: rescored[k] for k in SCORED})


def _interrupt_when_writing(argv: list[str], watch: Path, sig: int, log: Path) -> int:
    """Run ``torchtrack ARGV`` in a subprocess, send ``sig`` once ``watch`` holds data; its exit status."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    with open(log, "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "torchtrack", *argv], env=env, stdout=subprocess.DEVNULL,
                                stderr=err)
        deadline = time.monotonic() + 120
        while not (watch.is_file() and watch.stat().st_size > 0):
            if proc.poll() is not None:
                pytest.fail(f"finished (status {proc.returncode}) before it was interrupted: {log.read_text()[-2000:]}")
            if time.monotonic() > deadline:
                proc.kill()
                pytest.fail(f"never wrote {watch}")
            time.sleep(0.01)
        proc.send_signal(sig)
        return proc.wait(timeout=120)


def _check_interrupted(out: Path, before: dict[str, bytes], sig: int, status: int, log: Path) -> None:
    """After the signal: the previous set byte for byte; SIGINT cleans up, SIGKILL leaves OUT.partial
    marked incomplete (nothing else)."""
    assert _snapshot(out) == before
    staging = out.with_name(out.name + ".partial")
    if sig == signal.SIGINT:
        assert status == 130 and "interrupted" in log.read_text()
        assert not staging.exists()
    else:
        assert status == -signal.SIGKILL
        assert json.loads((staging / MARKER).read_text())["complete"] is False
    assert sorted(p.name for p in out.parent.iterdir() if p.name.startswith(out.name)) == sorted(
        [out.name] + ([staging.name] if sig == signal.SIGKILL else []))


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["SIGINT", "SIGKILL"])
def test_track_detections_rerun_interrupted_keeps_the_previous_set(tmp_path, sig):
    gt, det = _detection_files(tmp_path / "small", 150)
    out = tmp_path / "out"
    assert main(["track", "--detections", str(det), "--gt", str(gt), "--out", str(out)]) == 0
    before = _snapshot(out)
    assert set(before) == {MARKER, "tracks.txt", "metrics.json"}
    _assert_metrics_match_tracks(out, gt)

    big_gt, big_det = _detection_files(tmp_path / "big", 4000)
    log = tmp_path / "stderr.txt"
    status = _interrupt_when_writing(["track", "--detections", str(big_det), "--gt", str(big_gt), "--tracker", "sort",
                                      "--out", str(out)], tmp_path / "out.partial" / "tracks.partial.txt", sig, log)
    _check_interrupted(out, before, sig, status, log)
    _assert_metrics_match_tracks(out, gt)

    # the next run succeeds, replaces the set whole and removes what the killed one left
    assert main(["track", "--detections", str(det), "--gt", str(gt), "--tracker", "sort", "--out", str(out)]) == 0
    assert not (tmp_path / "out.partial").exists()
    assert json.loads((out / "metrics.json").read_text())["tracker"] == "sort"
    _assert_metrics_match_tracks(out, gt)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["SIGINT", "SIGKILL"])
def test_track_benchmark_rerun_interrupted_keeps_the_previous_set(tmp_path, sig):
    small = _benchmark_config(tmp_path / "small", 120)
    out = tmp_path / "out"
    assert main(["track", "--benchmark", str(small), "--out", str(out)]) == 0
    before = _snapshot(out)
    assert {"benchmark.json", "all/gt.txt", "all/det.txt", "all/gmphd/tracks.txt", "all/sort/metrics.json",
            MARKER} < set(before)
    for tracker in ("gmphd", "sort"):
        _assert_metrics_match_tracks(out / "all" / tracker, out / "all" / "gt.txt", moving=False)

    big = _benchmark_config(tmp_path / "big", 3000)
    log = tmp_path / "stderr.txt"
    watch = tmp_path / "out.partial" / "all" / "gmphd" / "tracks.partial.txt"
    status = _interrupt_when_writing(["track", "--benchmark", str(big), "--out", str(out)], watch, sig, log)
    _check_interrupted(out, before, sig, status, log)
    for tracker in ("gmphd", "sort"):
        _assert_metrics_match_tracks(out / "all" / tracker, out / "all" / "gt.txt", moving=False)

    assert main(["track", "--benchmark", str(small), "--out", str(out), "--seed", "1"]) == 0
    assert not (tmp_path / "out.partial").exists()
    assert json.loads((out / "benchmark.json").read_text())["seed"] == 1


def test_simulate_video_killed_rerun_then_a_shorter_run_leaves_no_stale_frame(tmp_path):
    out = tmp_path / "seq"
    assert main(["simulate-video", "--out", str(out), "--frames", "4", "--size", "96", "96", "--seed", "1"]) == 0
    before = _snapshot(out)
    log = tmp_path / "stderr.txt"
    status = _interrupt_when_writing(["simulate-video", "--out", str(out), "--frames", "400", "--size", "256", "256"],
                                     tmp_path / "seq.partial" / "frames" / "000002.png", signal.SIGKILL, log)
    _check_interrupted(out, before, signal.SIGKILL, status, log)
    assert main(["simulate-video", "--out", str(out), "--frames", "2", "--size", "96", "96"]) == 0
    assert sorted(p.name for p in (out / "frames").iterdir()) == ["000001.png", "000002.png"]
    assert not (tmp_path / "seq.partial").exists()
    assert len(json.loads((out / "camera.json").read_text())["homographies"]) == 2


def test_demo_killed_rerun_keeps_the_previous_set_and_the_next_leaves_nothing_stale(tmp_path):
    out = tmp_path / "demo"
    assert main(["demo", "--frames", "3", "--out", str(out), "--no-progress"]) == 0
    before = _snapshot(out)
    assert {"tracks.txt", "metrics.json", "scores.png", "trackers/sort.txt", "sequence/frames/000003.png"} < set(before)
    log = tmp_path / "stderr.txt"
    status = _interrupt_when_writing(["demo", "--frames", "200", "--out", str(out), "--no-progress"],
                                     tmp_path / "demo.partial" / "sequence" / "frames" / "000002.png",
                                     signal.SIGKILL, log)
    _check_interrupted(out, before, signal.SIGKILL, status, log)
    assert main(["demo", "--frames", "2", "--out", str(out), "--no-progress"]) == 0
    assert sorted(p.name for p in (out / "sequence" / "frames").iterdir()) == ["000001.png", "000002.png"]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["demo"]["frames"] == 2 and not (tmp_path / "demo.partial").exists()
    for name in ("sort", "greedy"):  # every tracker file is this run's: no frame beyond the second
        assert set(read_mot(out / "trackers" / f"{name}.txt").frames().tolist()) <= {1, 2}


def test_a_failing_rerun_keeps_the_previous_set(tmp_path, capsys):
    gt, det = _detection_files(tmp_path, 40)
    out = tmp_path / "out"
    assert main(["track", "--detections", str(det), "--gt", str(gt), "--out", str(out)]) == 0
    before = _snapshot(out)
    bad = tmp_path / "bad.txt"
    bad.write_text("1,-1,10,10,8,8,1,-1,-1,-1\n2,-1,oops,10,8,8,1,-1,-1,-1\n")
    assert main(["track", "--detections", str(bad), "--gt", str(gt), "--out", str(out)]) == 2
    assert "bad.txt" in capsys.readouterr().err
    assert _snapshot(out) == before and not (tmp_path / "out.partial").exists()
    # an argument error is found before anything is read or written
    with pytest.raises(SystemExit) as exc:             # argparse's usage error, before anything is read
        main(["track", "--detections", str(det), "--gt", str(gt), "--out", str(out), "--threshold", "-5"])
    assert exc.value.code == 2
    assert "argument --threshold: must be > 0; got -5.0" in capsys.readouterr().err
    assert _snapshot(out) == before and not (tmp_path / "out.partial").exists()


def test_a_failing_video_pipeline_rerun_keeps_the_previous_set(tmp_path, capsys):
    import cv2

    sequence = tmp_path / "seq"
    assert main(["simulate-video", "--out", str(sequence), "--frames", "4", "--size", "256", "256"]) == 0
    out = tmp_path / "out"
    argv = ["--gt", str(sequence / "gt.txt"), "--out", str(out), "--no-progress"]
    assert main(["track", "--frames", str(sequence / "frames"), *argv]) == 0
    before = _snapshot(out)
    assert {"tracks.txt", "detections.txt", "annotated.mp4", "metrics.json"} < set(before)
    broken = tmp_path / "broken"
    broken.mkdir()
    for k, frame in enumerate(sorted((sequence / "frames").iterdir()), start=1):
        image = cv2.imread(str(frame), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(broken / frame.name), image if k != 3 else image[:100])  # frame 3 changes size
    capsys.readouterr()
    assert main(["track", "--frames", str(broken), *argv]) == 2
    assert "000003.png: frame size" in capsys.readouterr().err
    assert _snapshot(out) == before and not (tmp_path / "out.partial").exists()


def test_a_foreign_folder_is_refused_unless_forced(tmp_path, capsys):
    gt, det = _detection_files(tmp_path / "in", 20)
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    argv = ["track", "--detections", str(det), "--gt", str(gt), "--out", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--force" in err and "not a torchtrack output folder" in err
    assert _snapshot(out) == {"notes.txt": b"mine"}
    assert main([*argv, "--force"]) == 0
    assert set(_snapshot(out)) == {MARKER, "tracks.txt", "metrics.json"}
    # another command's output is refused too, naming that command
    sequence = tmp_path / "seq"
    assert main(["simulate-video", "--out", str(sequence), "--frames", "2", "--size", "96", "96"]) == 0
    capsys.readouterr()
    assert main(["track", "--detections", str(det), "--gt", str(gt), "--out", str(sequence)]) == 2
    assert "the output of torchtrack simulate-video" in capsys.readouterr().err
    # an empty folder is free to use
    (tmp_path / "empty").mkdir()
    assert main(["track", "--detections", str(det), "--out", str(tmp_path / "empty")]) == 0


def test_force_never_replaces_the_current_folder_nor_the_inputs(tmp_path, monkeypatch, capsys):
    gt, det = _detection_files(tmp_path / "in", 5)
    (tmp_path / "work").mkdir()
    (tmp_path / "work" / "notes.txt").write_text("mine")
    monkeypatch.chdir(tmp_path / "work")
    assert main(["track", "--detections", str(det), "--out", ".", "--force"]) == 2
    assert "will not replace the current folder" in capsys.readouterr().err
    assert main(["track", "--detections", str(det), "--out", "..", "--force"]) == 2
    assert main(["track", "--detections", str(det), "--gt", str(gt), "--out", str(tmp_path / "in"), "--force"]) == 2
    assert f"holds the input {det}" in capsys.readouterr().err
    assert (tmp_path / "work" / "notes.txt").exists() and sorted(p.name for p in (tmp_path / "in").iterdir()) == [
        "det.txt", "gt.txt"]


@pytest.mark.parametrize("argv", [
    ["track", "--detections", "{det}", "--out", "{target}"],
    ["simulate-video", "--frames", "2", "--out", "{target}"],
    ["simulate-detections", "--gt", "{gt}", "--out", "{target}"],
    ["convert-wpafb", "{det}", "--out", "{target}"],
    ["eval", "--gt", "{gt}", "--pred", "{gt}", "--json", "{target}"],
], ids=["track", "simulate-video", "simulate-detections", "convert-wpafb", "eval-json"])
@pytest.mark.parametrize("where", ["under-a-file", "read-only"])
def test_an_unwritable_output_is_one_line_before_any_work(tmp_path, capsys, argv, where):
    gt, det = _detection_files(tmp_path / "in", 5)
    if where == "under-a-file":
        target = det / "sub" / "out"
        expected = "is a file, not a folder"
    else:
        locked = tmp_path / "locked"
        locked.mkdir()
        locked.chmod(0o555)
        if os.access(locked, os.W_OK):
            pytest.skip("permissions do not bind for this user (root)")
        target = locked / "out"
        expected = "is not writable"
    flag = "--json" if "--json" in argv else "--out"
    args = [a.format(det=det, gt=gt, target=target) for a in argv]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{flag} {target}: cannot be written" in err and expected in err
    assert sorted(p.name for p in (tmp_path / "in").iterdir()) == ["det.txt", "gt.txt"]


@pytest.mark.parametrize("argv", [
    ["track", "--detections", "{det}", "--out", "{target}"],
    ["simulate-video", "--frames", "2", "--out", "{target}"],
    ["tune", "--config", "tune-kalman", "--out", "{target}"],
])
def test_out_naming_an_existing_file_is_refused(tmp_path, capsys, argv):
    gt, det = _detection_files(tmp_path, 5)
    target = tmp_path / "results.txt"
    target.write_text("keep me")
    assert main([a.format(det=det, target=target) for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"--out {target}: is a file, not a folder" in err
    assert target.read_text() == "keep me"


@pytest.mark.parametrize("command", ["simulate-detections", "convert-wpafb"])
def test_a_single_file_output_naming_a_folder_is_refused(tmp_path, capsys, command):
    gt, det = _detection_files(tmp_path / "in", 5)
    source = ["--gt", str(gt)] if command == "simulate-detections" else [str(det)]
    assert main([command, *source, "--out", str(tmp_path / "in")]) == 2
    assert "is a folder; give a file name" in capsys.readouterr().err


def _complete_set(folder: Path, text: str, command: str = "torchtrack track") -> None:
    folder.mkdir()
    (folder / "tracks.txt").write_text(text)
    (folder / MARKER).write_text(json.dumps({"command": command, "complete": True}))


class _Failed(Exception):
    pass


def _enter_and_fail(out: Path) -> None:
    """A run that repairs the folder on entering and then fails (so the repair alone is seen)."""
    with pytest.raises(_Failed), OutputFolder(out, "torchtrack track"):
        raise _Failed


def test_a_commit_killed_between_its_renames_is_finished_by_the_next_run(tmp_path):
    out = tmp_path / "out"
    _complete_set(tmp_path / "out.replaced", "old")
    _complete_set(tmp_path / "out.partial", "new")
    _enter_and_fail(out)
    assert (out / "tracks.txt").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_commit_killed_after_its_renames_leaves_only_the_old_set_to_remove(tmp_path):
    out = tmp_path / "out"
    _complete_set(out, "new")
    _complete_set(tmp_path / "out.replaced", "old")
    _enter_and_fail(out)
    assert (out / "tracks.txt").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_staging_folder_that_is_not_ours_is_left_alone(tmp_path, capsys):
    gt, det = _detection_files(tmp_path / "in", 5)
    (tmp_path / "out.partial").mkdir()
    (tmp_path / "out.partial" / "thesis.tex").write_text("precious")
    assert main(["track", "--detections", str(det), "--out", str(tmp_path / "out")]) == 2
    assert "is not a torchtrack staging folder" in capsys.readouterr().err
    assert (tmp_path / "out.partial" / "thesis.tex").read_text() == "precious"


def test_staged_paths_name_their_final_place(tmp_path):
    folder = OutputFolder(tmp_path / "out", "torchtrack track")
    with folder as staging:
        (staging / "sub").mkdir()
        (staging / "sub" / "a.txt").write_text("a")
        final = folder.final(staging / "sub" / "a.txt")
    assert final == tmp_path / "out" / "sub" / "a.txt" and final.read_text() == "a"


def test_scenario_figures_are_one_set_and_a_foreign_folder_is_refused_before_the_experiment(tmp_path, capsys):
    plots = tmp_path / "plots"
    assert main(["scenario", "maneuver", "--runs", "2", "--plot", str(plots)]) == 0
    first = _snapshot(plots)
    assert {"stationary.png", "constant_velocity.png", "maneuver.png"} <= {Path(p).name for p in first}
    assert main(["scenario", "maneuver", "--runs", "2", "--plot", str(plots)]) == 0      # our own: replaced
    assert not (tmp_path / "plots.partial").exists()
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "keep.txt").write_text("mine")
    capsys.readouterr()
    assert main(["scenario", "maneuver", "--runs", "2", "--plot", str(foreign)]) == 2
    captured = capsys.readouterr()
    assert "--force" in captured.err and "RMSE" not in captured.out        # refused before the experiment ran
    assert _snapshot(foreign) == {"keep.txt": b"mine"} and not (tmp_path / "foreign.partial").exists()
