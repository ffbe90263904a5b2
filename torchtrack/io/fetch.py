"""A data set's files from their publisher (or a local copy) into a folder, each verified against the
size and SHA-256 the project ships (:mod:`torchtrack.io.datasets`): ``torchtrack data fetch``.

All or nothing: the missing files go into a hidden staging folder inside the target (``.fetch-*``), each
checked as it arrives; only when every one is verified are they renamed to their final names (renames
within one file system), and the staging folder is removed whatever happens (an error, Ctrl-C). So a
failed or interrupted fetch leaves no file under a final name. Files already present and verified are
kept; a present file whose sum differs is fetched anew and replaced. Beside the data, ``SOURCE.md``
records the repository, commit, licence, origin and date of the fetch, and ``SHA256SUMS`` the sums
(``sha256sum -c SHA256SUMS`` checks them).

A failed download says the next step (:func:`offline_hint`): copy a local copy with ``--from DIR``, or point
the data set's environment variable (``TORCHTRACK_WPAFB``) at one.
"""

from __future__ import annotations

import hashlib
import http.client
import os
import shutil
import sys
import tempfile
import urllib.error
import urllib.request
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import BinaryIO

from torchtrack.errors import TorchtrackError
from torchtrack.io.datasets import DataFile, Dataset
from torchtrack.io.outputs import write_text

CHUNK = 1 << 16
NOTES = ("SOURCE.md", "SHA256SUMS")


@dataclass(frozen=True)
class FetchResult:
    """What :func:`fetch_dataset` did in ``folder``: the files it ``fetched`` (new), ``replaced`` (present
    with another sum) and ``kept`` (present and verified), from ``origin`` (a base URL or a folder)."""

    folder: Path
    origin: str
    fetched: tuple[str, ...]
    replaced: tuple[str, ...]
    kept: tuple[str, ...]

    @property
    def changed(self) -> bool:
        return bool(self.fetched or self.replaced)


def sha256_of(path: Path) -> str:
    """Hex SHA-256 of the file ``path``."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(CHUNK), b""):
            digest.update(block)
    return digest.hexdigest()


def is_verified(folder: Path, f: DataFile) -> bool:
    """``folder/f.path`` exists with the expected size and SHA-256."""
    path = folder / f.path
    return path.is_file() and path.stat().st_size == f.size and sha256_of(path) == f.sha256


class _DownloadFailed(TorchtrackError):
    """The network failed (no answer, an HTTP error, a broken transfer): :func:`fetch_dataset` adds the next step."""


def offline_hint(dataset: Dataset) -> str:
    """What to do when ``dataset`` cannot be downloaded."""
    return (f"without network access, copy a local copy with `torchtrack data fetch {dataset.name} --from DIR`, "
            f"or set {dataset.env}=DIR to use it where it is")


def _one_line(reason: object) -> str:
    return " ".join(str(reason).split())


def _open(f: DataFile, base_url: str | None, source: Path | None, timeout: float) -> tuple[BinaryIO, str]:
    """The stream of ``f`` and the name it came from (URL or local path)."""
    if source is not None:
        path = source / f.path
        try:
            return open(path, "rb"), str(path)
        except OSError as exc:
            raise TorchtrackError(f"--from {source}: cannot read {f.path} ({_one_line(exc.strerror or exc)})") from None
    url = f"{base_url.rstrip('/')}/{f.source}"
    request = urllib.request.Request(url, headers={"User-Agent": "torchtrack-data-fetch"})
    try:
        return urllib.request.urlopen(request, timeout=timeout), url
    except urllib.error.HTTPError as exc:
        raise _DownloadFailed(f"cannot download {url}: HTTP {exc.code} {_one_line(exc.reason)}") from None
    except (OSError, http.client.HTTPException) as exc:
        raise _DownloadFailed(f"cannot download {url}: {_one_line(getattr(exc, 'reason', exc))}") from None


def _receive(stream: BinaryIO, name: str, dest: Path, f: DataFile, bar) -> None:
    """Copy ``stream`` to ``dest`` checking the size (no more than expected is read) and the SHA-256."""
    digest, size = hashlib.sha256(), 0
    try:
        with stream, open(dest, "wb") as out:
            while block := stream.read(CHUNK):
                size += len(block)
                if size > f.size:
                    raise TorchtrackError(f"{name}: more than the expected {f.size} bytes (changed or wrong "
                                          "file; nothing was kept)")
                digest.update(block)
                out.write(block)
                bar.update(len(block))
    except (OSError, http.client.HTTPException) as exc:
        raise _DownloadFailed(f"cannot download {name}: {_one_line(exc)} (nothing was kept)") from None
    if size != f.size or digest.hexdigest() != f.sha256:
        raise TorchtrackError(f"{name}: SHA-256 {digest.hexdigest()} ({size} bytes) is not the expected "
                              f"{f.sha256} ({f.size} bytes); corrupt or changed file, nothing was kept")


def source_note(dataset: Dataset, origin: str, when: datetime) -> str:
    """The ``SOURCE.md`` written beside the data: where it is published, its licence, the fetch."""
    repo = f"https://github.com/{dataset.repository}"
    files = "\n".join(f"- `{f.path}` ← `{f.source}` ({f.size} bytes)" for f in dataset.files)
    return (f"# {dataset.title}\n\n"
            f"Fetched {when:%Y-%m-%dT%H:%MZ} by `torchtrack data fetch {dataset.name}` from {origin}.\n\n"
            f"- Published in: {repo} (commit {dataset.commit})\n"
            f"- Licence: {dataset.licence}"
            f"{f' ({repo}/blob/{dataset.commit}/{dataset.licence_file})' if dataset.licence_file else ''}. "
            f"{dataset.licence_note}\n"
            f"- SHA-256 of every file: `SHA256SUMS` (check with `sha256sum -c SHA256SUMS`).\n\n"
            f"## Files (here ← in the repository)\n{files}\n")


def sums_file(files: Iterable[DataFile]) -> str:
    """``SHA256SUMS`` in the format of ``sha256sum``."""
    return "".join(f"{f.sha256}  {f.path}\n" for f in files)


def fetch_dataset(dataset: Dataset, out: str | os.PathLike, base_url: str | None = None,
                  source: str | os.PathLike | None = None, progress: bool = True,
                  timeout: float = 60.0) -> FetchResult:
    """Bring ``dataset``'s files into ``out`` from ``base_url`` (default :attr:`Dataset.base_url`; a file
    is at ``base_url/<its source path>``) or, with ``source``, from a local folder in the data set's own
    layout (module docstring for the guarantees). Raises :class:`TorchtrackError` in one line on a
    network error (with :func:`offline_hint`), a ``source`` folder that does not exist, a missing local file
    or a wrong checksum."""
    out = Path(out)
    source = None if source is None else Path(source)
    if source is not None and not source.is_dir():
        raise TorchtrackError(f"--from {source}: " + ("not a folder" if source.exists() else
                                                      "the folder does not exist"))
    origin = str(source) if source is not None else (base_url or dataset.base_url)
    if out.exists() and not out.is_dir():
        raise TorchtrackError(f"--out {out}: exists and is not a folder")
    present = {f.path for f in dataset.files if (out / f.path).exists()}
    todo = [f for f in dataset.files if not is_verified(out, f)]
    kept = tuple(f.path for f in dataset.files if f not in todo)
    if not todo:
        if not all((out / n).is_file() for n in NOTES):
            _write_notes(dataset, out, origin)
        return FetchResult(out, origin, (), (), kept)
    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=".fetch-", dir=out))
    except OSError as exc:
        raise TorchtrackError(f"--out {out}: cannot write there ({_one_line(exc.strerror or exc)})") from None
    try:
        from tqdm import tqdm

        with tqdm(total=sum(f.size for f in todo), unit="B", unit_scale=True, desc=f"fetch {dataset.name}",
                  file=sys.stderr, disable=not progress, leave=False) as bar:
            for i, f in enumerate(todo):
                try:
                    stream, name = _open(f, base_url or dataset.base_url, source, timeout)
                    _receive(stream, name, staging / str(i), f, bar)
                except _DownloadFailed as exc:
                    raise TorchtrackError(f"{exc}; {offline_hint(dataset)}") from None
        for i, f in enumerate(todo):
            final = out / f.path
            final.parent.mkdir(parents=True, exist_ok=True)
            os.replace(staging / str(i), final)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        if created and not any(out.iterdir()):
            out.rmdir()
    _write_notes(dataset, out, origin)
    return FetchResult(out, origin, tuple(f.path for f in todo if f.path not in present),
                       tuple(f.path for f in todo if f.path in present), kept)


def _write_notes(dataset: Dataset, out: Path, origin: str) -> None:
    write_text(out / "SOURCE.md", source_note(dataset, origin, datetime.now(timezone.utc)))
    write_text(out / "SHA256SUMS", sums_file(dataset.files))
