"""The second fault suite, one test per kind: crashes by signal (frame names that are not UTF-8, thousands of
threads), a hang (a tracker across a gap of 10⁹ frames), and foreign exceptions turned into one-line errors."""

import os
import subprocess
import sys

import cv2
import numpy as np
import pytest
import torch

from torchtrack.cli import main
from torchtrack.filters.trackers.protocol import make_tracker, tracker_names
from torchtrack.io.frames import open_frames
from torchtrack.threads import available_cores, torch_threads


def test_frame_names_that_are_not_utf8_are_read(tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    image = (np.arange(64 * 48) % 251).astype(np.uint8).reshape(48, 64)
    for k in (1, 2):
        name = os.fsdecode(b"frame\xff" + str(k).encode() + b".png")     # a surrogate-escaped byte, as the OS gives
        ok, data = cv2.imencode(".png", image)
        (folder / name).write_bytes(data.tobytes())
    frames = list(open_frames(folder))
    assert len(frames) == 2 and np.array_equal(frames[0].image, image)


def test_frame_names_that_are_not_utf8_do_not_crash_the_command(tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    ok, data = cv2.imencode(".png", np.zeros((40, 40), np.uint8))
    (folder / os.fsdecode(b"a\xff.png")).write_bytes(data.tobytes())
    proc = subprocess.run([sys.executable, "-m", "torchtrack", "track", "--frames", str(folder), "--out",
                           str(tmp_path / "out"), "--no-progress", "--no-video"], capture_output=True, text=True)
    assert proc.returncode in (0, 2), proc.stderr          # a result or a one-line error, never a signal
    assert "Traceback" not in proc.stderr


def test_more_threads_than_cores_are_clamped_with_a_note(capsys):
    before = torch.get_num_threads()
    with torch_threads(10_000):
        assert torch.get_num_threads() == available_cores()
    assert torch.get_num_threads() == before
    assert "10000 threads asked for" in capsys.readouterr().err


@pytest.mark.parametrize("name", tracker_names())
def test_every_tracker_crosses_a_gap_of_a_billion_frames(name):
    tracker = make_tracker(name)
    z = torch.tensor([[10.0, 10.0], [50.0, 50.0]], dtype=torch.float64)
    for frame in (1, 2, 3):
        tracker.step(frame, z + frame)
    ids, positions = tracker.step(1_000_000_000, z)
    assert positions.shape[-1] == 2 and ids.shape[0] == positions.shape[0]


def test_the_glmb_skips_the_empty_frames_of_a_gap_only_where_nothing_changes():
    """Stepping through every frame of a gap and stopping at the fixed point give the same tracks after it."""
    rng = np.random.default_rng(3)
    frames = {k: torch.as_tensor(np.array([[20.0 + 3 * k, 30.0], [80.0, 20.0 + 2 * k]]) + rng.normal(0, 0.5, (2, 2)))
              for k in list(range(1, 9)) + list(range(300, 306))}

    def run(stop_early: bool):
        tracker = make_tracker("glmb")
        if not stop_early:
            tracker._empty = lambda: False
        return [tuple(t.tolist() for t in tracker.step(k, z)) for k, z in frames.items()]

    assert run(True) == run(False)


def test_a_foreign_exception_is_one_line_with_exit_1(monkeypatch, capsys):
    import torchtrack.cli.eval as eval_command

    def broken(args):
        raise ZeroDivisionError("division by zero\nin a second line")

    monkeypatch.setattr(eval_command, "run", broken)
    assert main(["eval", "--gt", "a", "--pred", "b"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("torchtrack eval: error: internal failure (ZeroDivisionError")
    assert "report" in err


def test_an_os_error_is_an_input_error_naming_the_file(monkeypatch, capsys, tmp_path):
    import torchtrack.cli.eval as eval_command

    def unreadable(args):
        raise PermissionError(13, "Permission denied", str(tmp_path / "gt.txt"))

    monkeypatch.setattr(eval_command, "run", unreadable)
    assert main(["eval", "--gt", "a", "--pred", "b"]) == 2
    assert capsys.readouterr().err.strip() == f"torchtrack eval: error: {tmp_path / 'gt.txt'}: Permission denied"


def test_two_runs_on_one_output_folder_the_second_is_refused_and_a_killed_holder_frees_it(tmp_path):
    from torchtrack.errors import TorchtrackError
    from torchtrack.io.outputs import OutputFolder

    out = tmp_path / "out"
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from torchtrack.io.outputs import OutputFolder\n"
        f"with OutputFolder(r'{out}', 'torchtrack track') as staging:\n"
        "    (staging / 'tracks.txt').write_text('1,1,0,0,8,8,1,-1,-1,-1\\n')\n"
        "    print('in', flush=True); time.sleep(600)")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "in"
        with pytest.raises(TorchtrackError, match=rf"another run is writing there \(process {holder.pid}\)"):
            with OutputFolder(out, "torchtrack track"):
                pass
        assert (tmp_path / "out.partial" / "tracks.txt").is_file()       # the holder's work is untouched
    finally:
        holder.kill()                                                     # kill -9: the lock dies with it
        holder.wait()
    with OutputFolder(out, "torchtrack track") as staging:               # taken over; the stale staging cleared
        assert not (staging / "tracks.txt").exists()
        (staging / "tracks.txt").write_text("2,1,0,0,8,8,1,-1,-1,-1\n")
    assert (out / "tracks.txt").read_text().startswith("2,1") and sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_simulated_detections_on_timestamp_frames_use_the_frames_present(tmp_path):
    from torchtrack.io.mot import from_points
    from torchtrack.sim.detections import simulate_detections

    truth = from_points([1, 1_700_000_000, 1_700_000_001], [1, 1, 1], [10.0, 12.0, 14.0], [10.0, 10.0, 10.0])
    det = simulate_detections(truth, pd=1.0, sigma=0.0, clutter=3.0, image_size=(100, 100),
                              generator=torch.Generator().manual_seed(0)).detections
    assert set(det.frames().tolist()) == {1, 1_700_000_000, 1_700_000_001}


def test_train_detector_refuses_an_out_under_a_file_before_any_work(tmp_path, monkeypatch, capsys):
    (tmp_path / "afile").write_text("")
    monkeypatch.chdir(tmp_path)
    assert main(["train-detector", "--out", "afile/sub", "--epochs", "1", "--no-progress"]) == 2
    assert "afile is a file, not a folder" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]        # no data cache built either


@pytest.mark.parametrize("text", [".inf", "-.inf", ".nan", "1e999"])
def test_an_infinite_config_value_is_refused_where_it_is_read(tmp_path, text, capsys):
    config = tmp_path / "video.yaml"
    config.write_text(f"frames: 3\nheight: 128\nwidth: 128\nnoise_std: {text}\n")
    assert main(["simulate-video", "--config", str(config), "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    assert "noise_std must be a finite number" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_an_output_folder_whose_parents_do_not_exist_yet(tmp_path):
    from torchtrack.io.outputs import OutputFolder

    with OutputFolder(tmp_path / "a" / "b" / "out", "torchtrack track") as staging:
        (staging / "x.txt").write_text("x")
    assert (tmp_path / "a" / "b" / "out" / "x.txt").is_file()
    assert sorted(p.name for p in (tmp_path / "a" / "b").iterdir()) == ["out"]


def test_a_64_bit_seed_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as caught:
        main(["simulate-video", "--out", "o", "--seed", str(2**64 + 1)])
    assert caught.value.code == 2
    err = capsys.readouterr().err
    assert "argument --seed: must be in [0," in err and "Traceback" not in err
