"""MOTChallenge text I/O: round trips, the velocity columns, bad input."""

from pathlib import Path

import numpy as np
import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.io import mot
from torchtrack.io.mot import POINT_BOX_SIZE, MOTWriter, read_mot, write_mot

MOTMETRICS_DATA = None
try:
    import motmetrics

    MOTMETRICS_DATA = Path(motmetrics.__file__).parent / "data"
except ImportError:  # test-only dependency
    pass


def test_round_trip_points(tmp_path):
    rng = np.random.default_rng(0)
    frames = rng.integers(1, 20, size=200)
    ids = np.arange(200)
    cx, cy = rng.uniform(0, 500, 200), rng.uniform(0, 400, 200)
    conf = rng.uniform(0, 1, 200)
    write_mot(tmp_path / "a.txt", frames, ids, cx, cy, conf=conf)
    d = read_mot(tmp_path / "a.txt")
    order = np.lexsort((ids, frames))
    np.testing.assert_array_equal(d.frame, frames[order])
    np.testing.assert_array_equal(d.id, ids[order])
    np.testing.assert_allclose(d.centers(), np.stack([cx, cy], 1)[order], atol=1e-3)
    np.testing.assert_allclose(d.w, POINT_BOX_SIZE)
    np.testing.assert_allclose(d.conf, conf[order], rtol=1e-3)
    assert d.vx is None and d.vy is None
    line = (tmp_path / "a.txt").read_text().splitlines()[0].split(",")
    assert len(line) == 10 and line[7:] == ["-1", "-1", "-1"]


def test_velocity_columns_round_trip(tmp_path):
    vx, vy = np.array([0.5, -1.0, 3.25]), np.array([-1.0, -1.0, 0.0])
    write_mot(tmp_path / "d.txt", [1, 1, 2], [-1, -1, -1], [1, 2, 3], [4, 5, 6], vx=vx, vy=vy)
    d = read_mot(tmp_path / "d.txt")
    np.testing.assert_allclose(d.velocity(), np.stack([vx, vy], 1))
    np.testing.assert_array_equal(d.id, -1)


def test_short_lines_get_defaults(tmp_path):
    p = tmp_path / "s.txt"
    p.write_text("1,1,1,2,3,4,0.5\n2,2,1,2,3,4\n\n# comment\n3 3 1 2 3 4 0.2 -1 -1 -1\n")
    d = read_mot(p)
    np.testing.assert_allclose(d.conf, [0.5, 1.0, 0.2])
    assert d.vx is None
    np.testing.assert_allclose(d.centers(), [[2.5, 4.0]] * 3)


def test_writer_flushes_each_frame_and_accepts_tensors(tmp_path):
    p = tmp_path / "w.txt"
    w = MOTWriter(p)
    w.write_frame(1, torch.tensor([3, 4]), torch.tensor([1.0, 2.0]), torch.tensor([5.0, 6.0]))
    w.write_frame(2, [], [], [])
    # not closed yet: nothing under the final name, the completed frames readable under the partial one
    assert not p.exists()
    d = read_mot(tmp_path / "w.partial.txt")
    np.testing.assert_array_equal(d.id, [3, 4])
    w.write_frame(3, [7], [1.0], [1.0])
    w.close()
    assert read_mot(p).size == 3 and not (tmp_path / "w.partial.txt").exists()


def test_writer_left_by_an_exception_keeps_only_the_partial_file(tmp_path):
    with pytest.raises(KeyboardInterrupt), MOTWriter(tmp_path / "w.txt") as w:
        w.write_frame(1, [3], [1.0], [5.0])
        raise KeyboardInterrupt
    assert not (tmp_path / "w.txt").exists()
    np.testing.assert_array_equal(read_mot(tmp_path / "w.partial.txt").id, [3])


def test_tens_of_thousands_in_one_frame(tmp_path):
    n = 40000
    xy = np.random.default_rng(1).uniform(0, 5000, (n, 2))
    with MOTWriter(tmp_path / "big.txt") as w:
        w.write_frame(1, np.full(n, -1), xy[:, 0], xy[:, 1])
        w.write_frame(2, [5], [1.0], [2.0])
    d = read_mot(tmp_path / "big.txt")
    assert d.size == n + 1 and d.split()[0].size == n
    np.testing.assert_allclose(d.centers()[:n], xy, atol=1e-3)


def test_empty_file(tmp_path):
    p = tmp_path / "e.txt"
    p.write_text("")
    d = read_mot(p)
    assert d.size == 0 and d.frames().size == 0


@pytest.mark.parametrize(
    "line, what",
    [
        ("1,2,3", "fields"),
        ("1,2,3,4,5,x", "not a number"),
        ("-1,2,3,4,5,6", "frame"),
        ("1.5,2,3,4,5,6", "frame"),
        ("1,2.5,3,4,5,6", "id"),
        ("1,-3,3,4,5,6", "id"),
        ("1,2,nan,4,5,6", "NaN"),
        ("1,2,3,4,-5,6", "box size"),
        ("1,2,3,4,5,6,1,-1,-1,-1,7", "fields"),
    ],
)
def test_malformed_line_names_file_and_line(tmp_path, line, what):
    p = tmp_path / "bad.txt"
    p.write_text("1,1,1,1,1,1,1,-1,-1,-1\n\n" + line + "\n")
    with pytest.raises(TorchtrackError, match=what) as exc:
        read_mot(p)
    assert f"{p}:3:" in str(exc.value)


def test_duplicate_frame_id_is_an_error(tmp_path):
    p = tmp_path / "dup.txt"
    p.write_text("1,1,1,1,1,1\n1,2,1,1,1,1\n1,1,5,5,1,1\n")
    with pytest.raises(TorchtrackError, match=r":3: frame 1 id 1 already given on line 1"):
        read_mot(p)


def test_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(TorchtrackError, match="cannot read"):
        read_mot(tmp_path / "nope.txt")


@pytest.mark.skipif(MOTMETRICS_DATA is None, reason="motmetrics not installed")
def test_reads_motmetrics_sample_like_motmetrics():
    import motmetrics as mm

    for name in ("TUD-Campus/gt.txt", "TUD-Stadtmitte/test.txt"):
        ours = read_mot(MOTMETRICS_DATA / name)
        ref = mm.io.loadtxt(str(MOTMETRICS_DATA / name), fmt="mot15-2D")
        assert ours.size == len(ref)
        np.testing.assert_array_equal(ours.frame, ref.index.get_level_values(0))
        np.testing.assert_array_equal(ours.id, ref.index.get_level_values(1))
        np.testing.assert_allclose(ours.x - 1, ref["X"])  # motmetrics shifts to 0-based; we keep the file's
        np.testing.assert_allclose(ours.y - 1, ref["Y"])
        np.testing.assert_allclose(ours.h, ref["Height"])


@pytest.mark.parametrize("fields", [6, 7, 9, 10])
def test_plain_files_parsed_in_c_equal_the_line_reader(tmp_path, fields, monkeypatch):
    monkeypatch.setattr(mot, "_CHUNK_LINES", 64)  # several chunks, the last one short
    rng = np.random.default_rng(fields)
    rows = np.column_stack([rng.integers(0, 50, 200), np.arange(200) - 1, rng.uniform(-5, 500, (200, 2)),
                            rng.uniform(0, 9, (200, 2)), rng.uniform(0, 1, 200), rng.normal(0, 2, (200, 3))])
    path = tmp_path / "plain.txt"
    path.write_text("\n".join(",".join(f"{v:.6g}" for v in row[:fields]) for row in rows))  # no final newline
    fast, slow = mot._read_uniform(path), mot._read_lines(path)
    assert fast is not None and fast[-1] is None and np.array_equal(slow[-1], np.arange(1, 201))
    for a, b in zip(fast[:-1], slow[:-1]):
        assert a.dtype == b.dtype and np.array_equal(a, b)
    path.write_text(path.read_text() + "\n1,2,3,4,5,6,7,8")  # one line of another width, in the last chunk
    assert mot._read_uniform(path) is None


@pytest.mark.parametrize(("text", "ids"), [
    ("# a comment\n1,1,0,0,1,1\n", [1]), ("1,1,0,0,1,1\n\n2,1,0,0,1,1\n", [1, 1]), ("1 1 0 0 1 1\n", [1]),
    ("1,9007199254740993,0,0,1,1\n", [9007199254740993]), ("", []), ("1,1,0,0,1,1\n2,1,0,0,1\n", None)])
def test_other_files_are_read_line_by_line(tmp_path, text, ids):
    """Comments, blank lines, spaces, ids beyond 2**53 (exact only line by line), empty files and bad lines."""
    path = tmp_path / "other.txt"
    path.write_text(text)
    assert mot._read_uniform(path) is None
    if ids is None:
        with pytest.raises(TorchtrackError, match=r"other.txt:2: expected 6 to 10 fields"):
            read_mot(path)
    else:
        assert read_mot(path).id.tolist() == ids
