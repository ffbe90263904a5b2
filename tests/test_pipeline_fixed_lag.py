"""Fixed-lag output (backfill, gap filling, trimming) and the weak detections given to a tracker, on
hand-built streams whose right answer is known."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.pipeline.config import PipelineConfig
from torchtrack.pipeline.fixed_lag import FixedLagTracks
from torchtrack.pipeline.frame_detections import FrameDetections
from torchtrack.pipeline.tracker_stream import TrackerStream

V = np.array([5.0, 0.0])


def run(lag, frames):
    """Push ``frames`` = [(ids, positions, detections)] (velocity V for every detection); return
    {frame: {id: position}} of the output, checking that every frame comes out once and in order."""
    out = FixedLagTracks(lag=lag, distance=3.0)
    final = []
    for k, (ids, pos, dets) in enumerate(frames, start=1):
        dets = np.asarray(dets, float).reshape(-1, 2)
        got = out.push(k, np.asarray(ids), np.asarray(pos, float).reshape(-1, 2), dets, np.tile(V, (len(dets), 1)))
        assert len(out._pending) == min(lag, k)  # bounded memory: lag frames
        final += got
    final += out.finish()
    assert [f.index for f in final] == list(range(1, len(frames) + 1))
    return {f.index: dict(zip(f.ids.tolist(), f.positions)) for f in final}


def car(k):
    return [10.0 + 5.0 * k, 20.0]


def test_lag_zero_is_the_online_output():
    frames = [([1], [car(k)], []) for k in range(1, 5)]  # not even supported by a detection: kept as is
    res = run(0, frames)
    assert all(list(res[k]) == [1] for k in range(1, 5))


def test_new_track_is_backfilled_along_its_detections():
    # Detected from frame 1, reported by the tracker only from frame 4.
    frames = [([], [], [car(k)]) for k in (1, 2, 3)] + [([7], [car(k)], [car(k)]) for k in (4, 5, 6)]
    res = run(3, frames)
    for k in range(1, 7):
        assert list(res[k]) == [7]
        np.testing.assert_allclose(res[k][7], car(k))
    # With a lag of 2 only two frames can be filled in.
    res = run(2, frames)
    assert res[1] == {} and list(res[2]) == [7] and list(res[3]) == [7]


def test_backfill_stops_at_a_detection_another_track_holds_or_off_the_path():
    held = [([3], [car(1)], [car(1)]), ([], [], [car(2)]), ([7], [car(3)], [car(3)])]
    res = run(3, held)
    assert list(res[2]) == [7] and list(res[1]) == [3]  # frame 1's detection belongs to track 3
    off_path = [([], [], [[car(1)[0], 30.0]]), ([7], [car(2)], [car(2)])]  # 10 px off p - v
    assert run(3, off_path)[1] == {}


def test_gap_is_interpolated_up_to_the_lag():
    frames = [([1], [car(1)], [car(1)]), ([1], [car(2)], [car(2)]), ([], [], []), ([], [], []),
              ([1], [car(5)], [car(5)])]
    res = run(3, frames)
    for k in (3, 4):
        np.testing.assert_allclose(res[k][1], car(k))
    assert run(1, frames)[3] == {} and run(1, frames)[4] == {}  # a gap of two frames is more than lag 1


def test_coasting_tail_is_trimmed_and_coasting_through_a_miss_kept():
    tail = [([1], [car(k)], [car(k)]) for k in (1, 2)] + [([1], [car(k)], []) for k in (3, 4, 5, 6, 7, 8)]
    res = run(3, tail)
    assert all(1 in res[k] for k in (1, 2)) and all(1 not in res[k] for k in (3, 4, 5))
    assert all(1 in res[k] for k in (6, 7, 8))  # the last lag frames: their future is unknown, kept
    through = [([1], [car(1)], [car(1)]), ([1], [car(2)], []), ([1], [car(3)], []), ([1], [car(4)], [car(4)])]
    res = run(3, through)
    assert all(1 in res[k] for k in (1, 2, 3, 4))
    assert 1 not in run(1, through)[2]  # re-acquired 2 frames later: beyond a lag of 1


def test_bad_lag_is_refused():
    with pytest.raises(TorchtrackError, match="lag"):
        FixedLagTracks(lag=-1)


class Recording:
    def __init__(self):
        self.seen = []

    def step(self, frame, positions, velocities):
        self.seen.append(positions.numpy().copy())
        return torch.arange(len(positions)), positions


def frame(k, pos, scores, strong):
    pos = np.asarray(pos, float)
    vel = np.tile(V, (len(pos), 1))
    return FrameDetections(k, np.eye(3), pos, vel, np.asarray(scores, float), pos, vel, np.full(len(pos), 50.0),
                           np.asarray(strong))


@pytest.mark.parametrize("weak_threshold", [0.15, None])
def test_weak_detections_only_continue_tracks(weak_threshold):
    tracker = Recording()
    stream = TrackerStream(tracker, PipelineConfig(weak_threshold=weak_threshold, output_lag=0, min_speed=0.0,
                                                   min_motion=0.0))
    stream.step(frame(1, [car(1)], [0.9], [True]))
    # Frame 2: the car again but weak (continues frame 1's position by its velocity), a weak detection
    # elsewhere (continues nothing), and one weaker than weak_threshold on the car's path.
    stream.step(frame(2, [car(2), [200.0, 200.0], car(2)], [0.2, 0.2, 0.1], [False, False, False]))
    expected = [car(2)] if weak_threshold is not None else np.zeros((0, 2))
    np.testing.assert_allclose(tracker.seen[1].reshape(-1, 2), expected)


class Pending(Recording):
    """Reports nothing; holds its input's positions as new tracks waiting for confirmation."""

    def step(self, frame, positions, velocities):
        super().step(frame, positions, velocities)
        self.pending_positions = positions
        return torch.zeros(0, dtype=torch.long), positions[:0]


@pytest.mark.parametrize("continues_pending", [False, True])
def test_weak_detections_continue_pending_tracks_only_when_asked(continues_pending):
    tracker = Pending()
    stream = TrackerStream(tracker, PipelineConfig(output_lag=0, min_speed=0.0, min_motion=0.0,
                                                   weak_continues_pending=continues_pending))
    stream.step(frame(1, [car(1)], [0.9], [True]))
    stream.step(frame(2, [car(2), [200.0, 200.0]], [0.2, 0.2], [False, False]))
    np.testing.assert_allclose(tracker.seen[1].reshape(-1, 2), [car(2)] if continues_pending else np.zeros((0, 2)))


def test_gmphd_tracker_exposes_new_labels_waiting_for_confirmation():
    from torchtrack.filters.trackers.protocol import make_tracker

    tracker = make_tracker("gmphd", {"dtype": "float64", "confirm_new": 3})
    pending = []
    for k in range(1, 7):
        z = torch.tensor([[100.0 + 5.0 * k, 50.0]], dtype=torch.float64)
        ids, pos = tracker.step(k, z, torch.tensor([[5.0, 0.0]], dtype=torch.float64))
        pending.append((len(ids), tracker.pending_positions.shape[0]))
        if tracker.pending_positions.shape[0]:
            np.testing.assert_allclose(tracker.pending_positions.numpy(), z.numpy(), atol=1.0)
    first = next(k for k, (_, p) in enumerate(pending) if p)
    assert pending[first:first + 3] == [(0, 1), (0, 1), (1, 0)]     # extracted twice unreported, then reported


def test_tracker_stream_output_is_that_of_fixed_lag_tracks():
    tracker = SimpleNamespace(step=lambda k, p, v: (torch.full((len(p),), 4), p))
    stream = TrackerStream(tracker, PipelineConfig(output_lag=2, min_speed=0.0, min_motion=0.0))
    outs = [stream.step(frame(k, [car(k)], [0.9], [True]))[2] for k in (1, 2, 3)]
    assert [len(o) for o in outs] == [0, 0, 1] and outs[2][0].index == 1
    assert [f.index for f in stream.finish()] == [2, 3]
