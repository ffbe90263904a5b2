"""Detection over spatial strips across two torchrun ranks (gloo, loopback; issue #28 item 5): every rank holds
the whole frame's detections, equal to one process's detector loop over the frames."""

from pathlib import Path

import numpy as np
import pytest
import torch

from torchtrack.detector.decode import Detections
from torchtrack.detector.inference import load_detector
from torchtrack.errors import TorchtrackError
from torchtrack.pipeline.strips import detect_strips, merge_strips, strip_rows
from torchtrack.sim.video import VideoConfig, generate_sequence
from torchtrack.threads import torch_threads

ROOT = Path(__file__).resolve().parents[1]
SIZE, FRAMES, SEED, TILE = (384, 320), 4, 20_028_005, 128


def _frames() -> list[np.ndarray]:
    cfg = VideoConfig(height=SIZE[0], width=SIZE[1], frames=FRAMES)
    return [f.image for f in generate_sequence(cfg, torch.Generator().manual_seed(SEED))]


def test_strip_rows_partition_the_frame_on_the_stride():
    assert strip_rows(384, 2) == [(0, 192), (192, 384)]
    assert strip_rows(420, 3) == [(0, 144), (144, 288), (288, 420)]
    assert strip_rows(20, 2) == [(0, 16), (16, 20)]
    assert strip_rows(420, 1) == [(0, 420)]
    with pytest.raises(TorchtrackError, match="strips"):
        strip_rows(20, 3)


def test_merge_strips_orders_by_score_then_strip():
    top = Detections(torch.tensor([[1.0, 2.0], [3.0, 4.0]]), torch.tensor([0.9, 0.5]), torch.zeros(2, 2),
                     torch.ones(2, dtype=torch.bool))
    bottom = Detections(torch.tensor([[5.0, 30.0], [6.0, 40.0]]), torch.tensor([0.95, 0.5]), torch.ones(2, 2),
                        torch.ones(2, dtype=torch.bool))
    merged = merge_strips([top, bottom])
    assert merged.xy[:, 1].tolist() == [30.0, 2.0, 4.0, 40.0]
    assert merged.velocity[:, 0].tolist() == [1.0, 0.0, 0.0, 1.0] and len(merged) == 4


def test_two_ranks_over_strips_equal_one_process(tmp_path, run_on_two_ranks):
    det = load_detector(tile=TILE)
    frames = _frames()
    one, prev = [], None
    # one process: the detector's own loop, the whole prior; one thread as each rank (the thread count changes
    # the float rounding, and so the order of near-equal scores)
    with torch_threads(1):
        for frame in frames:
            found = det.detect(frame, None if prev is None else frames[len(one) - 1], None if prev is None else prev.xy,
                               prev_velocity=None if prev is None else prev.velocity)
            one.append(found)
            prev = found
        # no process group: detect_strips is that same loop
        for a, b in zip(detect_strips(det, frames), one):
            torch.testing.assert_close(a.xy, b.xy, rtol=0, atol=0)
    assert all(len(f) > 20 for f in one)

    script = tmp_path / "strips.py"
    script.write_text(
        "import sys, torch, torch.distributed as dist\n"
        f"sys.path.insert(0, {str(ROOT / 'tests')!r})\n"
        "from test_pipeline_strips import TILE, _frames\n"
        "from torchtrack.detector.inference import load_detector\n"
        "from torchtrack.pipeline.strips import detect_strips\n"
        "dist.init_process_group('gloo')\n"
        "found = [tuple(d[:3]) for d in detect_strips(load_detector(tile=TILE), _frames())]\n"
        f"torch.save(found, {str(tmp_path)!r} + f'/rank{{dist.get_rank()}}.pt')\n"
        "dist.destroy_process_group()\n")
    run_on_two_ranks(script)
    for rank in (0, 1):                        # every rank holds the whole frame's detections
        two = torch.load(tmp_path / f"rank{rank}.pt")
        assert len(two) == FRAMES
        for (xy, score, velocity), ref in zip(two, one):
            assert len(xy) == len(ref)
            torch.testing.assert_close(xy, ref.xy, rtol=0, atol=1e-5)
            torch.testing.assert_close(score, ref.score, rtol=0, atol=1e-5)
            torch.testing.assert_close(velocity, ref.velocity, rtol=0, atol=1e-5)
        # both strips found detections, on either side of the seam at row 192
        assert (two[-1][0][:, 1] < 192).any() and (two[-1][0][:, 1] >= 192).any()
