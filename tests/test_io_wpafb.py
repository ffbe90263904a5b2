"""The WPAFB truth CSV reader, the moving-object rule and ``torchtrack convert-wpafb``."""

import json
from pathlib import Path

import numpy as np
import pytest

from torchtrack.cli import main
from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import read_mot
from torchtrack.io.moving import moving_mask
from torchtrack.io.wpafb import read_wpafb_csv


def write_csv(path: Path, rows, ids=(7, 3)) -> Path:
    cols = ["Frame Number"] + [f"obj_{i}_{c}" for i in ids for c in ("px", "py", "vx", "vy", "ax", "ay")]
    lines = [",".join(cols) + ",,,,,,"]  # like the published file: six unnamed trailing columns
    for frame, *objs in rows:
        vals = [frame]
        for px, py in objs:
            vals += [px, py, 0, 0, 0, 0]
        lines.append(",".join(str(v) for v in vals + [0] * 6))
    lines.append(",".join(["0"] * (len(cols) + 6)))  # trailing all-zero row
    path.write_text("\r\n".join(lines) + "\r\n")
    return path


def test_rows_columns_absent_objects_and_renumbering(tmp_path):
    p = write_csv(tmp_path / "t.csv", [(100, (10, 20), (0, 0)), (101, (11, 22), (5, 6)), (102, (0, 0), (7, 8))])
    d = read_wpafb_csv(p)
    np.testing.assert_array_equal(d.frame, [1, 2, 2, 3])
    np.testing.assert_array_equal(d.id, [7, 3, 7, 3])  # sorted by frame, then id
    # px is the row (y), py the column (x)
    np.testing.assert_allclose(d.centers(), [[20, 10], [6, 5], [22, 11], [8, 7]])
    kept = read_wpafb_csv(p, keep_frame_numbers=True)
    np.testing.assert_array_equal(kept.frame, [100, 101, 101, 102])


def test_bad_csv(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("Frame,obj_1_px\n1,2\n")
    with pytest.raises(TorchtrackError, match=":1:"):
        read_wpafb_csv(p)
    p = write_csv(tmp_path / "short.csv", [(1, (1, 1), (2, 2))])
    p.write_text(p.read_text().replace("1,1,1,0,0,0,0,2,2", "1,1,1,0,0,0,0,x,2"))
    with pytest.raises(TorchtrackError, match=":2: not a number"):
        read_wpafb_csv(p)


def test_moving_mask_by_hand(tmp_path):
    # object 7 moves 1 px per frame along the row; object 3 is parked
    rows = [(k, (10 + k, 10), (50, 50)) for k in range(1, 31)]
    d = read_wpafb_csv(write_csv(tmp_path / "m.csv", rows))
    m = moving_mask(d, min_displacement=5.0, window=15)
    moving_frames = d.frame[m & (d.id == 7)]
    # displacement over the window is min(k - 1, 15) px: > 5 from frame 7 on
    np.testing.assert_array_equal(moving_frames, np.arange(7, 31))
    assert not m[d.id == 3].any()
    # gaps in an object's life: the earliest frame of the window is used
    sub = d.select(~((d.id == 7) & (d.frame >= 3) & (d.frame <= 20)))
    ms = moving_mask(sub)
    # at frame 21, the window [6, 21] holds only frame 21 itself
    assert not ms[(sub.id == 7) & (sub.frame == 21)].any()
    assert ms[(sub.id == 7) & (sub.frame == 27)].all()  # window [12, 27] starts at 21: 6 px


def test_convert_real_csv(tmp_path, wpafb_data):
    out, js = tmp_path / "gt.txt", tmp_path / "c.json"
    csv = wpafb_data / "transformed_object_states.csv"
    assert main(["convert-wpafb", str(csv), "--out", str(out), "--json", str(js)]) == 0
    d = read_mot(out)
    frames = d.frames()
    assert frames.size == 512 and frames[0] == 1 and frames[-1] == 512
    assert np.unique(d.id).size == 550
    per_frame = np.bincount(d.frame)[1:]
    assert 80 < per_frame.mean() < 90 and per_frame.max() == 113
    c = d.centers()  # inside the 585 x 496 (columns x rows) frames
    assert c[:, 0].max() < 585 and c[:, 1].max() < 496 and c.min() >= 0
    summary = json.loads(js.read_text())
    assert summary["ids"] == 550 and summary["frames"] == 512
    moving_per_frame = summary["moving_objects"] / 512
    assert 30 < moving_per_frame < 60
