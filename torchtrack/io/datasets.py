"""The data sets the project reads from outside the repository, and the one place that finds them.

A :class:`Dataset` says what its folder holds (:class:`DataFile`: path, size, SHA-256), where it is
published (a GitHub repository at a fixed commit, fetched by ``torchtrack data fetch``,
:mod:`torchtrack.io.fetch`) and under which licence. :func:`locate` finds its folder, trying in order

1. ``data/<folder>`` under the current folder, then under the source checkout this package runs from
   (a folder holding ``pyproject.toml`` and this package; an installed wheel has none): where
   ``torchtrack data fetch`` puts it;
2. the folder named by the data set's environment variable (``$TORCHTRACK_WPAFB``); set but without
   the data set, it is an error rather than skipped;
3. ``../shared/data/<folder>`` under the current folder, then under the checkout: the copy on the
   project's own machines.

A folder counts as holding the data set when its ``marker`` file (the WPAFB truth CSV) is there. Where
none does, the error says in one line how to get it.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from torchtrack.errors import TorchtrackError


@dataclass(frozen=True)
class DataFile:
    """One file of a data set: ``path`` inside the data set's folder, ``source`` inside the publishing
    repository, its ``size`` in bytes and its ``sha256`` (hex)."""

    path: str
    source: str
    size: int
    sha256: str


@dataclass(frozen=True)
class Dataset:
    """A data set: its ``name`` (``torchtrack data fetch NAME``), its ``folder`` name under ``data/``,
    the environment variable ``env`` that may point at it, the ``marker`` file that makes a folder count,
    its ``files``, the GitHub ``repository`` and ``commit`` that publish them, their ``licence`` (as the
    repository names it), the repository's ``licence_file`` and a ``licence_note``."""

    name: str
    title: str
    folder: str
    env: str
    marker: str
    files: tuple[DataFile, ...]
    repository: str
    commit: str
    licence: str
    licence_file: str
    licence_note: str

    @property
    def base_url(self) -> str:
        """Raw-file URL of the repository at :attr:`commit`; a file is at ``base_url/source``."""
        return f"https://raw.githubusercontent.com/{self.repository}/{self.commit}"

    @property
    def url_env(self) -> str:
        """Environment variable that replaces :attr:`base_url` (a mirror, or a test server)."""
        return f"{self.env}_URL"


_AOI02 = "dataset/WPAFB_2009/AOI_02"
_FRAME_SUMS = {
    100: (156163, "704df4ae25e538a6edd77e04b69be65abbd4cc4a5b60b26dab26e7eecf2b8247"),
    101: (156163, "704df4ae25e538a6edd77e04b69be65abbd4cc4a5b60b26dab26e7eecf2b8247"),  # = frame 100
    102: (154728, "c9264bd93be5361bdc465e590e962069f325dbf808cdf683e7e077d2dd20b825"),
    103: (154410, "7629e53a4532735466b84a7b7fb9bcd2edb010d90db60996bb2945377fa3054b"),
    104: (155837, "b2912064b5872c9ce71f438adb476e65eeb896dc557f81c0bada698b43fa204a"),
    105: (155556, "27e907a05ef34be756107d9f25569798c297b5e77f3b40bfddc3079fcead83ed"),
}

WPAFB = Dataset(
    name="wpafb",
    title="WPAFB 2009, area of interest 02: real vehicle truth (512 frames) and six real frames",
    folder="wpafb-aoi02",
    env="TORCHTRACK_WPAFB",
    marker="transformed_object_states.csv",
    files=(DataFile("transformed_object_states.csv", f"{_AOI02}/GT/transformed_object_states.csv", 3600442,
                    "97711b1bcc792cc77981c006b9576ce26703826b35533dce59047cd0d89d504b"),
           *(DataFile(f"frames/frame_{k:06d}.png", f"{_AOI02}/INPUT_DATA/stabilized_data/frame_{k:06d}.png",
                      size, digest) for k, (size, digest) in _FRAME_SUMS.items())),
    repository="Ayana-Inria/GLMB-adaptive-birth-satellite-videos",
    commit="cb8c7821be7eac9b847f7a282f8dde91b55583ea",
    licence="GPL-3.0-only",
    licence_file="LICENSE-GPL-3.0-only",
    licence_note="The repository names its licence GPL-3.0-only (file name, and the commit of 2024-03-01 that "
                 "gave it that name); the file's text is the GNU Affero General Public License v3, and the "
                 "README says 'GNUv3 License'. No separate licence covers the data folder. The imagery comes "
                 "from the WPAFB 2009 data set (AFRL, public release).",
)

_CLIF = "Data/CLIF_2007"


def _clif_frames() -> tuple[DataFile, ...]:
    from torchtrack.io.clif2007_sums import FRAMES

    rows = (line.split() for line in FRAMES.splitlines())
    return tuple(DataFile(f"frames/000000-{n}.jpg", f"{_CLIF}/jpg/000000-{n}.jpg", int(size), digest)
                 for n, size, digest in rows)


CLIF2007 = Dataset(
    name="clif2007",
    title="CLIF 2007, camera 0: 250 consecutive real frames of 668 x 1004 px (grey JPEG, 4x downsampled; no truth)",
    folder="clif2007",
    env="TORCHTRACK_CLIF2007",
    marker="README.md",
    files=(DataFile("README.md", f"{_CLIF}/README.md", 650,
                    "23843c3a85e2b4ec5cb090349f2eb371a6cc200ab994c64c305d244e52230e38"), *_clif_frames()),
    repository="mleotta/cvpr2015-opensfm",
    commit="0dd6693462ebfb9c847c08413f06326dac1a8d51",
    licence="none stated",
    licence_file="",
    licence_note="The repository states no licence. Its README.md (copied here) says the frames are a sample of "
                 "the CLIF 2007 data set, provided by the U.S. Air Force and publicly available from AFRL's SDMS "
                 "(public release), downsampled by 4 and encoded as JPEG.",
)

DATASETS: dict[str, Dataset] = {WPAFB.name: WPAFB, CLIF2007.name: CLIF2007}


def checkout_root() -> Path | None:
    """The source checkout this package runs from (the folder holding ``pyproject.toml`` beside the
    ``torchtrack`` package), or None for an installed package."""
    root = Path(__file__).resolve().parents[2]
    return root if (root / "pyproject.toml").is_file() and (root / "torchtrack").is_dir() else None


def default_roots() -> list[Path]:
    """The folders ``data/`` and ``../shared/data`` are looked for under: the current folder, then the
    source checkout (where there is one)."""
    return [Path.cwd(), *filter(None, [checkout_root()])]


def search_path(dataset: Dataset, roots: Sequence[Path], environ: Mapping[str, str]) -> list[tuple[str, Path]]:
    """``(where, folder)`` candidates in the order :func:`locate` tries them (module docstring), ``where``
    being ``"data"``, ``"env"`` or ``"shared"``; a folder reached twice (cwd = checkout) is kept once."""
    found = [("data", r / "data" / dataset.folder) for r in roots]
    if environ.get(dataset.env):
        found.append(("env", Path(environ[dataset.env])))
    found += [("shared", r.parent / "shared" / "data" / dataset.folder) for r in roots]
    unique: dict[str, tuple[str, Path]] = {}
    for where, folder in found:
        unique.setdefault(os.path.abspath(folder), (where, folder))
    return list(unique.values())


def locate(dataset: Dataset, roots: Sequence[Path] | None = None, environ: Mapping[str, str] | None = None) -> Path:
    """The folder holding ``dataset`` (search order in the module docstring; ``roots`` default
    :func:`default_roots`, ``environ`` the process's). Raises :class:`TorchtrackError` in one line where
    it is absent, or where the environment variable names a folder without it."""
    environ = os.environ if environ is None else environ
    for where, folder in search_path(dataset, default_roots() if roots is None else roots, environ):
        if (folder / dataset.marker).is_file():
            return folder
        if where == "env":
            raise TorchtrackError(f"{dataset.env}={environ[dataset.env]}: no {dataset.marker} there "
                                  f"(point it at the {dataset.folder} folder, or unset it)")
    raise TorchtrackError(f"{dataset.folder} data not found; run `torchtrack data fetch {dataset.name}` "
                          f"(into ./data/{dataset.folder}) or set {dataset.env} to its folder")


def wpafb_folder() -> Path:
    """The WPAFB AOI 02 folder (truth CSV, ``frames/``): :func:`locate` of :data:`WPAFB`."""
    return locate(WPAFB)


def wpafb_truth_csv(name_or_path: str | os.PathLike = WPAFB.name) -> Path:
    """The WPAFB truth CSV that a config value names: the data set's name (``wpafb``) for the located
    copy, or a path to the CSV or to a folder holding it (as given, relative to the current folder)."""
    if str(name_or_path) == WPAFB.name:
        return wpafb_folder() / WPAFB.marker
    path = Path(name_or_path)
    csv = path / WPAFB.marker if path.is_dir() else path
    if not csv.is_file():
        raise TorchtrackError(f"{path}: no {WPAFB.marker} there (or name the data set: {WPAFB.name})")
    return csv
