"""The video pipeline over strips (``torchtrack track --frames DIR --strips``, issue #28 item 5) on two gloo ranks
against ``torchtrack track --frames DIR`` in one process: the same detections, and the same tracks up to the
handover rule of :mod:`torchtrack.pipeline.strip_tracking`."""

import json

import numpy as np
import torch

from torchtrack.cli import main
from torchtrack.io.mot import read_mot
from torchtrack.metrics.clear_mot import clear_mot
from torchtrack.pipeline.config import SELECTED_TRACKERS
from torchtrack.pipeline.strip_tracking import BAND
from torchtrack.sim.video import write_sequence
from torchtrack.sim.video_config import VideoConfig

HEIGHT, WIDTH, FRAMES, SEED = 768, 512, 8, 3
SEAM = 384.0                # strip_rows(768, 2): the detector's seam, and the tracker's in the first frame's rows
DRIFT = 4.0                 # px: the most the simulated camera moves the seam's reference row in these frames


def test_track_frames_on_two_ranks_equals_one_process_up_to_the_handover(tmp_path, run_on_two_ranks):
    write_sequence(VideoConfig(height=HEIGHT, width=WIDTH, frames=FRAMES), torch.Generator().manual_seed(SEED),
                   tmp_path / "seq")
    # the pipeline's own options, the tracker in float64: the strips then equal one process to float rounding
    # away from the seam (in float32 different component counts round differently, 1e-4 px)
    config = tmp_path / "pipeline.yaml"
    config.write_text(json.dumps({"trackers": {"gmphd": {**SELECTED_TRACKERS["gmphd"], "dtype": "float64"}}}))
    args = ["track", "--frames", str(tmp_path / "seq" / "frames"), "--gt", str(tmp_path / "seq" / "gt.txt"),
            "--pipeline-config", str(config), "--no-video", "--no-progress"]
    script = tmp_path / "track.py"
    script.write_text("import sys\nfrom torchtrack.cli import main\n"
                      f"sys.exit(main({[*args, '--strips', '--out', str(tmp_path / 'two')]!r}))\n")
    run_on_two_ranks(script)
    assert main([*args, "--out", str(tmp_path / "one")]) == 0
    # rank 1 wrote nothing; rank 0 wrote the folder one process writes, its metrics naming the strips
    assert sorted(p.name for p in tmp_path.iterdir()) == ["one", "pipeline.yaml", "seq", "track.py", "two"]
    assert sorted(p.name for p in (tmp_path / "two").iterdir()) == sorted(p.name for p in (tmp_path / "one").iterdir())
    metrics = json.loads((tmp_path / "two" / "metrics.json").read_text())
    assert metrics["strips"] == 2 and metrics["band"] == BAND and metrics["strip_height"] == HEIGHT
    assert metrics["cap_hits"] == 0

    # detection: every rank detects its strip, the all-gathered detections are one process's, as written
    assert (tmp_path / "two" / "detections.txt").read_bytes() == (tmp_path / "one" / "detections.txt").read_bytes()

    one, two = (read_mot(tmp_path / name / "tracks.txt") for name in ("one", "two"))
    c1, c2 = one.centers(), two.centers()
    crossing = [i for i in np.unique(one.id) if len(np.unique(c1[one.id == i, 1] >= SEAM)) == 2]
    assert len(crossing) >= 3
    # tracks that stay farther than the band from the seam: the same lines (to the file's 1e-3 px), ids one-to-one
    near = np.unique(one.id[np.abs(c1[:, 1] - SEAM) <= BAND + DRIFT])
    far = np.flatnonzero(~np.isin(one.id, near))
    assert len(far) > 150
    pairs = set()
    for k in far:
        same = np.flatnonzero((two.frame == one.frame[k]) & (np.abs(c2 - c1[k]).max(axis=1) <= 1.5e-3))
        assert len(same) == 1, (one.frame[k], one.id[k], c1[k])
        pairs.add((int(one.id[k]), int(two.id[same[0]])))
    assert len(pairs) == len({a for a, _ in pairs}) == len({b for _, b in pairs})
    # near the seam the handover rule: a crossing vehicle faster than about band / 3 px per frame may be missed
    # for a frame or two after it crosses, or switch identity there (this scene's vehicles run at up to 40 px/frame)
    mot = clear_mot(one, two, threshold=1.0)
    assert mot["IDS"] <= len(crossing) and mot["FP"] + mot["FN"] <= 2 * len(crossing), mot
