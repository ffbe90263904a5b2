"""Outputs that appear whole or not at all.

Two levels, used by every command that writes files:

* **One file** — :func:`atomic_file` yields a temporary name in the same folder (``NAME.partial.SUFFIX``,
  see :func:`partial_name`: the suffix is kept so that OpenCV and matplotlib still know the format) and
  renames it to the final name when the block completes; :func:`write_text`, :func:`write_json` and
  :func:`write_yaml` use it. A reader never sees a half-written file under a final name.
* **One set** — :class:`OutputFolder` stages a whole run in ``OUT.partial`` beside the output folder
  ``OUT`` and, only when the run completed, replaces ``OUT`` by it (see the class for the guarantee, what
  SIGKILL leaves and the limits). A folder holds torchtrack's output when it has the marker file
  :data:`MARKER` naming the command; anything else is replaced only with ``force`` (``--force``).

:func:`check_output_file` checks a single output file's path (``--out FILE``, ``--json PATH``) before any
work, so that a path that cannot be written is a one-line error rather than a traceback at the end.
"""

from __future__ import annotations

import fcntl
import json
import math
import os
import shutil
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from types import TracebackType
from typing import Any

import yaml

from torchtrack.errors import TorchtrackError

MARKER = ".torchtrack-output.json"
"""The marker file of an output folder: ``{"command": "torchtrack CMD", "complete": bool}``."""

STAGING_SUFFIX = ".partial"
"""``OUT.partial``: where a run of ``OUT`` is written until it completes."""

REPLACED_SUFFIX = ".replaced"
"""``OUT.replaced``: the previous ``OUT`` during the moment of a commit, removed right after."""


def partial_name(path: str | os.PathLike) -> Path:
    """The temporary name of ``path`` while it is written: ``tracks.txt`` → ``tracks.partial.txt``."""
    path = Path(path)
    return path.with_name(f"{path.stem}{STAGING_SUFFIX}{path.suffix}")


@contextmanager
def atomic_file(path: str | os.PathLike) -> Iterator[Path]:
    """Yield the temporary name to write ``path`` under (parent folders created); rename it to ``path``
    when the block completes, remove it when the block raises."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = partial_name(path)
    try:
        yield tmp
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, path)


def save_figure(fig: Any, path: str | os.PathLike, dpi: float | None = None) -> Path:
    """Lay out the matplotlib figure ``fig``, write it to ``path`` whole (:func:`atomic_file`; the format from
    the suffix, PNG without one) and close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    with atomic_file(path) as tmp:
        fig.savefig(tmp, format=Path(path).suffix.lstrip(".") or "png", dpi=dpi)
    plt.close(fig)
    return Path(path)


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` through a temporary file and a rename; returns ``path``."""
    with atomic_file(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def _jsonable(obj):
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if hasattr(obj, "tolist") and not isinstance(obj, (str, bytes)):  # tensors, arrays and their scalars
        return _jsonable(obj.tolist())
    return obj


def write_json(path: str | os.PathLike | None, payload: Mapping, indent: int = 2) -> None:
    """Write ``payload`` as indented JSON to ``path`` (nothing when ``path`` is None): tensors and arrays
    become lists, NaN and infinities ``null``; parent folders are created; the file appears whole."""
    if path is not None:
        write_text(path, json.dumps(_jsonable(payload), indent=indent) + "\n")


def write_yaml(path: str | os.PathLike, payload: Mapping, header: str = "") -> Path:
    """Write ``payload`` as block YAML (keys in order) after the comment lines ``header``; appears whole."""
    return write_text(path, header + yaml.safe_dump(dict(payload), sort_keys=False))


def _writable_folder(folder: Path, flag: str, given: Path) -> None:
    """Error naming ``flag`` and the path ``given`` unless files can be created in ``folder`` (created later
    if missing: then its nearest existing ancestor must be a writable folder)."""
    probe = folder
    while not probe.exists():
        if probe.is_symlink():
            raise TorchtrackError(f"{flag} {given}: cannot be written, {probe} is a broken symbolic link")
        probe = probe.parent
    if not probe.is_dir():
        raise TorchtrackError(f"{flag} {given}: cannot be written, {probe} is a file, not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise TorchtrackError(f"{flag} {given}: cannot be written, {probe} is not writable")


def check_output_folder(path: str | os.PathLike, flag: str = "--out") -> None:
    """Error naming ``flag`` unless the folder ``path`` is, or can be created as, a writable folder (no file in
    its way): checked before a long run, not when its first file is written."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise TorchtrackError(f"{flag} {path}: is a file, not a folder")
    _writable_folder(path, flag, path)


def check_output_file(path: str | os.PathLike | None, flag: str = "--out") -> None:
    """Error (naming ``flag``) unless ``path`` can be written as a file: not an existing folder, in a
    folder that exists or can be created and is writable. Nothing for None."""
    if path is None:
        return
    path = Path(path)
    if path.is_dir():
        raise TorchtrackError(f"{flag} {path}: is a folder; give a file name")
    _writable_folder(path.parent, flag, path)


def _read_marker(folder: Path) -> dict[str, Any] | None:
    """The marker of ``folder`` (None when there is none or it is not ours)."""
    try:
        data = json.loads((folder / MARKER).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and isinstance(data.get("command"), str) else None


class OutputFolder:
    """Context manager: a run's files written as one set into the output folder ``target``.

    ``with OutputFolder(out, "torchtrack track") as staging:`` yields the staging folder ``OUT.partial``
    (beside ``out``, so on the same file system), empty but for the marker :data:`MARKER`; the command
    writes everything there. Leaving the block normally **commits**: the marker is marked complete, the
    previous ``out`` is renamed to ``OUT.replaced``, the staging folder is renamed to ``out`` and
    ``OUT.replaced`` is removed. Leaving it by an exception (an error, ``KeyboardInterrupt`` from SIGINT)
    removes the staging folder and leaves ``out`` as it was.

    Before the run (on entering), an existing ``out`` is checked: it must be a folder that is empty or
    holds the marker of the same ``command``; otherwise the run is refused naming ``--force`` (``force``
    replaces it anyway, except the current folder, an ancestor of it or the home folder), and so is an
    ``out`` holding one of the run's ``inputs`` (the commit would delete it). A path that cannot be written
    (under a file, a read-only folder) is refused too, before any work.

    **Guarantee.** ``out`` only ever holds a complete set: the previous run's, or this run's after the
    commit. After SIGKILL at any moment the parent folder holds one of: the previous set and possibly
    ``OUT.partial`` (killed before the commit); no ``out`` but ``OUT.replaced`` (previous set) and a
    complete ``OUT.partial`` (killed between the two renames of the commit); the new set and possibly
    ``OUT.replaced``. The next run on ``out`` repairs each case on
    entering — it finishes an interrupted commit, removes ``OUT.replaced`` and a stale ``OUT.partial`` —
    before it starts; a reader can do the same by hand.

    **One run at a time.** A run holds an exclusive lock (``flock``) on ``.OUT.lock`` beside ``out`` from entering
    to the end of its commit; a second run on the same ``out`` is refused with an error naming the holder's
    process id. The operating system releases the lock when its holder dies (``kill -9`` included), so a stale
    lock is never in the way.

    **Limits.** The commit is two renames, not one: for that instant ``out`` does not exist (above).
    The names ``OUT.partial`` and ``OUT.replaced`` belong to the run on ``out``: a non-empty
    ``OUT.partial`` without a marker is refused, but an ``OUT.replaced`` is always removed.
    Nothing is fsync'ed, so after a power cut the operating system decides what reached the disk.
    ``out`` is renamed as a whole: a mount point cannot be an output folder.

    ``commit=False`` is for the processes of a distributed run other than the one that commits: they get
    the staging folder's path and touch nothing else (the committing process prepares the folder before
    they write and commits after they are done; :func:`torchtrack.pipeline.sequences.shared_output`).
    """

    def __init__(self, target: str | os.PathLike, command: str, force: bool = False, commit: bool = True,
                 flag: str = "--out", inputs: Iterable[str | os.PathLike | None] = ()) -> None:
        self.target = Path(target)
        self.inputs = [Path(p) for p in inputs if p is not None]
        self.command = command
        self.force = force
        self.commit = commit
        self.flag = flag
        self._real = real = Path(os.path.realpath(self.target))
        self.staging = real.with_name(real.name + STAGING_SUFFIX)
        self.replaced = real.with_name(real.name + REPLACED_SUFFIX)

    def final(self, path: str | os.PathLike) -> Path:
        """Where ``path`` (a file of the staging folder) is once the run is committed."""
        return self.target / Path(path).relative_to(self.staging)

    def __enter__(self) -> Path:
        if self.commit:
            self._check()
            self._real.parent.mkdir(parents=True, exist_ok=True)   # the lock lives beside the folder
            self._lock = OutputLock(self._real.with_name(f".{self._real.name}.lock"), self.flag, self.target)
            self._lock.acquire()
            try:
                self._enter()
            except BaseException:
                self._lock.release()
                raise
        return self.staging

    def _enter(self) -> None:
        self._recover()
        self._check_owner()
        self.staging.mkdir(parents=True)
        self._mark(complete=False)

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if not self.commit:
            return
        try:
            if exc_type is not None:
                shutil.rmtree(self.staging, ignore_errors=True)
                return
            self._mark(complete=True)
            if self._real.exists():
                os.replace(self._real, self.replaced)
            os.replace(self.staging, self._real)
            shutil.rmtree(self.replaced, ignore_errors=True)
        finally:
            self._lock.release()

    def _mark(self, complete: bool) -> None:
        write_json(self.staging / MARKER, {"command": self.command, "complete": complete})

    def _check(self) -> None:
        if self._real.exists() and not self._real.is_dir():
            raise TorchtrackError(f"{self.flag} {self.target}: is a file, not a folder")
        if self._real.parent == self._real:
            raise TorchtrackError(f"{self.flag} {self.target}: cannot be an output folder")
        _writable_folder(self._real.parent, self.flag, self.target)
        for given in self.inputs:
            real = Path(os.path.realpath(given))
            if real == self._real or self._real in real.parents:
                raise TorchtrackError(f"{self.flag} {self.target}: holds the input {given}, which replacing the "
                                      f"folder would delete; give another {self.flag}")

    def _recover(self) -> None:
        """Finish or undo a commit that was killed half-way, remove a killed run's staging folder."""
        if self.replaced.exists():
            if not self._real.exists():
                staged = _read_marker(self.staging) if self.staging.is_dir() else None
                source = self.staging if staged and staged.get("complete") else self.replaced
                os.replace(source, self._real)
            shutil.rmtree(self.replaced, ignore_errors=True)
        if self.staging.exists():
            if not self.staging.is_dir() or (any(self.staging.iterdir()) and _read_marker(self.staging) is None):
                raise TorchtrackError(f"{self.flag} {self.target}: {self.staging} is in the way and is not a "
                                      "torchtrack staging folder; move it away")
            shutil.rmtree(self.staging)

    def _check_owner(self) -> None:
        if not self._real.is_dir() or not any(self._real.iterdir()):
            return
        marker = _read_marker(self._real)
        if marker is not None and marker["command"] == self.command:
            return
        if self.force:
            cwd, home = Path.cwd().resolve(), Path.home().resolve()
            if self._real == home or self._real == cwd or self._real in cwd.parents:
                raise TorchtrackError(f"{self.flag} {self.target}: will not replace the current folder, one "
                                      "above it or the home folder, even with --force")
            return
        what = f"the output of {marker['command']}" if marker else "not a torchtrack output folder"
        raise TorchtrackError(f"{self.flag} {self.target}: exists and is {what}; give another {self.flag} "
                              f"or --force to replace it")


class OutputLock:
    """An exclusive, non-blocking ``flock`` on ``path`` (created if needed, removed on release), holding the
    owner's process id; :meth:`acquire` raises :class:`TorchtrackError` naming the holder while another process
    has it. The lock dies with its process, so a run killed by ``kill -9`` leaves no lock behind that counts."""

    def __init__(self, path: Path, flag: str, target: Path) -> None:
        self.path, self.flag, self.target = path, flag, target
        self.fd: int | None = None

    def acquire(self) -> None:
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.read(fd, 32).decode(errors="replace").strip() or "another process"
                os.close(fd)
                raise TorchtrackError(f"{self.flag} {self.target}: another run is writing there (process "
                                      f"{holder}); wait for it to end or give another {self.flag}") from None
            try:   # the file may have been removed by its previous holder between open and flock: take the new one
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        os.ftruncate(fd, 0)
        os.write(fd, str(os.getpid()).encode())
        self.fd = fd

    def release(self) -> None:
        if self.fd is None:
            return
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass
        os.close(self.fd)
        self.fd = None
