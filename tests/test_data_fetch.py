"""``torchtrack data fetch``: downloads from a loopback HTTP server (127.0.0.1, stopped by the test) in the
publishing repository's layout, checksums, all-or-nothing on errors and interrupts, re-runs that do
nothing, ``--from`` copies; and the shipped WPAFB sums against the copy on this machine."""

from __future__ import annotations

import functools
import hashlib
import http.server
import re
import shutil
import threading
from pathlib import Path

import pytest

from torchtrack.cli import main
from torchtrack.errors import TorchtrackError
from torchtrack.io import fetch as fetch_module
from torchtrack.io.datasets import WPAFB, DataFile, Dataset
from torchtrack.io.fetch import fetch_dataset

TRUTH, FRAME = b"Frame Number,obj_1_px\n100,5\n", bytes(range(256)) * 300   # the frame spans several chunks


def toy_dataset(files: dict[str, tuple[str, bytes]]) -> Dataset:
    """A data set of ``{path: (source path, content)}`` whose sums are those of the contents."""
    listed = tuple(DataFile(p, src, len(b), hashlib.sha256(b).hexdigest()) for p, (src, b) in files.items())
    return Dataset(name="toy", title="Toy data: two files", folder="toy", env="TORCHTRACK_TOY", marker="truth.csv",
                   files=listed,
                   repository="example/toy", commit="0" * 40, licence="CC0-1.0", licence_file="LICENSE",
                   licence_note="A test licence.")


TOY = toy_dataset({"truth.csv": ("pub/GT/truth.csv", TRUTH), "frames/f1.png": ("pub/img/f1.png", FRAME)})


def publish(root: Path, dataset: Dataset, contents: dict[str, bytes]) -> Path:
    """Write ``contents`` (by data-set path) under ``root`` at each file's source path."""
    for f in dataset.files:
        if f.path in contents:
            (root / f.source).parent.mkdir(parents=True, exist_ok=True)
            (root / f.source).write_bytes(contents[f.path])
    return root


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:
        pass


@pytest.fixture
def server(tmp_path):
    """``(url, root)``: a loopback HTTP server serving the folder ``root``; shut down after the test."""
    root = tmp_path / "served"
    root.mkdir()
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_Quiet, directory=str(root)))
    thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}", root
    finally:
        httpd.shutdown()
        httpd.server_close()
        thread.join(timeout=5)


def files_under(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*")) if folder.exists() else []


def test_fetch_downloads_verifies_and_records_the_source(server, tmp_path):
    url, root = server
    publish(root, TOY, {"truth.csv": TRUTH, "frames/f1.png": FRAME})
    out = tmp_path / "data" / "toy"
    result = fetch_dataset(TOY, out, base_url=url, progress=False)
    assert result.fetched == ("truth.csv", "frames/f1.png") and not result.replaced and not result.kept
    assert (out / "truth.csv").read_bytes() == TRUTH and (out / "frames" / "f1.png").read_bytes() == FRAME
    assert files_under(out) == ["SHA256SUMS", "SOURCE.md", "frames", "frames/f1.png", "truth.csv"]
    sums = dict(line.split("  ")[::-1] for line in (out / "SHA256SUMS").read_text().splitlines())
    assert sums == {"truth.csv": hashlib.sha256(TRUTH).hexdigest(), "frames/f1.png": hashlib.sha256(FRAME).hexdigest()}
    note = (out / "SOURCE.md").read_text()
    assert "https://github.com/example/toy" in note and "CC0-1.0" in note and url in note
    assert re.search(r"Fetched \d{4}-\d\d-\d\dT\d\d:\d\dZ by", note)           # the fetch time, in UTC


def test_a_second_fetch_does_nothing(server, tmp_path, capsys):
    url, root = server
    publish(root, TOY, {"truth.csv": TRUTH, "frames/f1.png": FRAME})
    out = tmp_path / "toy"
    fetch_dataset(TOY, out, base_url=url, progress=False)
    stamps = {p: (out / p).stat().st_mtime_ns for p in files_under(out)}
    shutil.rmtree(root / "pub")                                    # nothing to download from any more
    again = fetch_dataset(TOY, out, base_url=url, progress=False)
    assert not again.changed and again.kept == ("truth.csv", "frames/f1.png")
    assert {p: (out / p).stat().st_mtime_ns for p in files_under(out)} == stamps


def test_a_corrupted_download_is_refused_and_nothing_is_left(server, tmp_path):
    url, root = server
    bad = bytearray(FRAME)
    bad[1000] ^= 1
    publish(root, TOY, {"truth.csv": TRUTH, "frames/f1.png": bytes(bad)})
    out = tmp_path / "data" / "toy"
    with pytest.raises(TorchtrackError, match=r"f1.png: SHA-256 [0-9a-f]{64} .* is not the expected") as exc:
        fetch_dataset(TOY, out, base_url=url, progress=False)
    assert "\n" not in str(exc.value)
    assert not out.exists()                   # the verified truth.csv was not kept either: all or nothing


def test_a_longer_file_is_refused(server, tmp_path):
    url, root = server
    publish(root, TOY, {"truth.csv": TRUTH + b"x" * 10**6, "frames/f1.png": FRAME})
    out = tmp_path / "toy"
    out.mkdir()
    with pytest.raises(TorchtrackError, match=f"truth.csv: more than the expected {len(TRUTH)} bytes"):
        fetch_dataset(TOY, out, base_url=url, progress=False)
    assert files_under(out) == []


def test_a_missing_file_on_the_server_is_a_one_line_error(server, tmp_path):
    url, root = server
    publish(root, TOY, {"truth.csv": TRUTH})
    out = tmp_path / "toy"
    with pytest.raises(TorchtrackError, match=rf"^cannot download {url}/pub/img/f1.png: HTTP 404"):
        fetch_dataset(TOY, out, base_url=url, progress=False)
    assert not out.exists()


def test_an_unreachable_server_is_a_one_line_error(tmp_path):
    with pytest.raises(TorchtrackError, match=r"^cannot download http://127.0.0.1:9/pub/GT/truth.csv: "):
        fetch_dataset(TOY, tmp_path / "toy", base_url="http://127.0.0.1:9", progress=False, timeout=2)
    assert not (tmp_path / "toy").exists()


NEXT_STEP = "`torchtrack data fetch toy --from DIR`, or set TORCHTRACK_TOY=DIR"


@pytest.mark.parametrize("where", ["the server", "the transfer"])
def test_a_failed_download_names_the_next_step(tmp_path, monkeypatch, where):
    if where == "the transfer":                             # the connection breaks while a file arrives
        class Broken:
            def __enter__(self):
                return self

            def __exit__(self, *exc):
                return False

            def read(self, n):
                raise ConnectionResetError("connection reset by peer")

        monkeypatch.setattr(fetch_module.urllib.request, "urlopen", lambda request, timeout: Broken())
    with pytest.raises(TorchtrackError) as caught:
        fetch_dataset(TOY, tmp_path / "toy", base_url="http://127.0.0.1:9", progress=False, timeout=2)
    message = str(caught.value)
    assert message.startswith("cannot download http://127.0.0.1:9/pub/GT/truth.csv: ")
    assert message.endswith(NEXT_STEP + " to use it where it is") and "\n" not in message
    assert not (tmp_path / "toy").exists()


def test_from_a_folder_that_does_not_exist_says_so(tmp_path):
    with pytest.raises(TorchtrackError, match=r"^--from \S*absent: the folder does not exist$"):
        fetch_dataset(TOY, tmp_path / "toy", source=tmp_path / "absent", progress=False)
    (tmp_path / "a-file").write_text("x")
    with pytest.raises(TorchtrackError, match=r"^--from \S*a-file: not a folder$"):
        fetch_dataset(TOY, tmp_path / "toy", source=tmp_path / "a-file", progress=False)
    assert not (tmp_path / "toy").exists()


def test_cli_data_messages_name_the_next_step(tmp_path, capsys):
    out = tmp_path / "wpafb"
    assert main(["data", "fetch", "wpafb", "--url", "http://127.0.0.1:9", "--timeout", "2", "--out", str(out),
                 "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("torchtrack data: error: cannot download http://127.0.0.1:9/") and "\n" not in err
    assert "torchtrack data fetch wpafb --from DIR" in err and "TORCHTRACK_WPAFB=DIR" in err
    assert main(["data", "fetch", "wpafb", "--from", str(tmp_path / "nowhere"), "--out", str(out),
                 "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"torchtrack data: error: --from {tmp_path / 'nowhere'}: the folder does not exist"
    assert not out.exists()


def test_an_interrupted_fetch_leaves_no_file_under_a_final_name(server, tmp_path, monkeypatch):
    url, root = server
    publish(root, TOY, {"truth.csv": TRUTH, "frames/f1.png": FRAME})
    out = tmp_path / "toy"
    out.mkdir()
    (out / "notes.txt").write_text("the user's own file")
    receive = fetch_module._receive

    def interrupted(stream, name, dest, f, bar):
        if f.path == "frames/f1.png":                     # Ctrl-C halfway through the second file
            dest.write_bytes(FRAME[: len(FRAME) // 2])
            raise KeyboardInterrupt
        receive(stream, name, dest, f, bar)

    monkeypatch.setattr(fetch_module, "_receive", interrupted)
    with pytest.raises(KeyboardInterrupt):
        fetch_dataset(TOY, out, base_url=url, progress=False)
    assert files_under(out) == ["notes.txt"]
    monkeypatch.setattr(fetch_module, "_receive", receive)
    assert fetch_dataset(TOY, out, base_url=url, progress=False).fetched == ("truth.csv", "frames/f1.png")


def test_a_present_file_with_another_sum_is_replaced_and_a_good_one_kept(server, tmp_path):
    url, root = server
    publish(root, TOY, {"truth.csv": TRUTH, "frames/f1.png": FRAME})
    out = tmp_path / "toy"
    (out / "frames").mkdir(parents=True)
    (out / "truth.csv").write_bytes(TRUTH)
    (out / "frames" / "f1.png").write_bytes(b"edited by hand")
    result = fetch_dataset(TOY, out, base_url=url, progress=False)
    assert result.kept == ("truth.csv",) and result.replaced == ("frames/f1.png",) and not result.fetched
    assert (out / "frames" / "f1.png").read_bytes() == FRAME


def test_from_copies_a_local_folder_and_checks_it(tmp_path):
    local = tmp_path / "copy"
    (local / "frames").mkdir(parents=True)
    (local / "truth.csv").write_bytes(TRUTH)
    out = tmp_path / "toy"
    with pytest.raises(TorchtrackError, match=r"^--from .*copy: cannot read frames/f1.png"):
        fetch_dataset(TOY, out, source=local, progress=False)
    assert not out.exists()
    (local / "frames" / "f1.png").write_bytes(FRAME)
    assert fetch_dataset(TOY, out, source=local, progress=False).fetched == ("truth.csv", "frames/f1.png")
    assert str(local) in (out / "SOURCE.md").read_text()


# -- the real data set, served from the copy on this machine ----------------------------------------------


def test_shipped_sums_are_those_of_the_copy_on_this_machine(wpafb_data):
    listed = dict(line.split()[::-1] for line in (wpafb_data / "SHA256SUMS").read_text().splitlines())
    assert {f.path: f.sha256 for f in WPAFB.files} == listed
    for f in WPAFB.files:
        assert hashlib.sha256((wpafb_data / f.path).read_bytes()).hexdigest() == f.sha256
        assert (wpafb_data / f.path).stat().st_size == f.size


def test_cli_fetches_wpafb_from_the_repository_layout(server, tmp_path, monkeypatch, capsys, wpafb_data):
    url, root = server
    publish(root, WPAFB, {f.path: (wpafb_data / f.path).read_bytes() for f in WPAFB.files})
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv(WPAFB.url_env, url)                          # the base URL from the environment
    assert main(["data", "fetch", "wpafb", "--no-progress"]) == 0
    out = tmp_path / "data" / "wpafb-aoi02"
    assert "7 fetched" in capsys.readouterr().out
    for f in WPAFB.files:
        assert (out / f.path).read_bytes() == (wpafb_data / f.path).read_bytes()
    note = (out / "SOURCE.md").read_text()
    assert WPAFB.repository in note and WPAFB.licence in note and WPAFB.licence_file in note
    assert main(["data", "fetch", "wpafb", "--no-progress"]) == 0
    assert "nothing to do" in capsys.readouterr().out


def test_cli_refuses_a_corrupted_wpafb_copy_with_exit_2(server, tmp_path, capsys, wpafb_data):
    url, root = server
    contents = {f.path: (wpafb_data / f.path).read_bytes() for f in WPAFB.files}
    contents["frames/frame_000103.png"] = contents["frames/frame_000103.png"][:-1] + b"\0"
    publish(root, WPAFB, contents)
    out = tmp_path / "wpafb"
    assert main(["data", "fetch", "wpafb", "--url", url, "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("torchtrack data: error: ")
    assert "frame_000103.png: SHA-256" in err
    assert not out.exists()


def test_clif2007_lists_its_250_consecutive_frames_and_fetches_from_a_local_copy(tmp_path):
    from torchtrack.io.datasets import CLIF2007

    frames = [f for f in CLIF2007.files if f.path.startswith("frames/")]
    assert [f.path for f in frames] == [f"frames/000000-{n}.jpg" for n in range(100006, 100256)]
    assert all(len(f.sha256) == 64 and f.size > 100_000 for f in frames)
    assert CLIF2007.marker in {f.path for f in CLIF2007.files}
    # --from with one file corrupted: refused, naming it, nothing kept under its final name.
    source = tmp_path / "copy"
    contents = {f.path: b"x" * f.size for f in CLIF2007.files[:2]}
    for path, body in contents.items():
        (source / path).parent.mkdir(parents=True, exist_ok=True)
        (source / path).write_bytes(body)
    with pytest.raises(TorchtrackError, match="README.md"):
        fetch_dataset(CLIF2007, tmp_path / "out", source=source, progress=False)
    assert not (tmp_path / "out" / "README.md").exists()
