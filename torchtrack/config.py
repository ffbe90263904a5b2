"""Where configuration files come from: a path, or the name of a preset shipped as package data.

The presets under ``torchtrack/configs/`` (the repository's ``configs/`` folder points there) install with
the package and are read through :mod:`importlib.resources`, so ``--config gmphd-paper`` or
``--benchmark wpafb-benchmark`` work from any folder after a non-editable install.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from torchtrack.errors import TorchtrackError


def preset_names() -> list[str]:
    """The names of the shipped presets (file names without ``.yaml``), sorted."""
    folder = resources.files("torchtrack") / "configs"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml"))


def preset_path(name_or_path: str | Path) -> Path:
    """The file a ``--config`` value names: an existing path as given, otherwise a shipped preset by name
    (``gmphd-paper``, ``gmphd-paper.yaml`` or ``configs/gmphd-paper.yaml``); an error naming the known
    presets where it is neither."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    stem = path.name[:-5] if path.name.endswith(".yaml") else path.name
    candidate = resources.files("torchtrack") / "configs" / f"{stem}.yaml"
    if (path.parent == Path(".") or path.parent.name == "configs") and candidate.is_file():
        return Path(str(candidate))
    raise TorchtrackError(f"{name_or_path}: no such file or preset (presets: {', '.join(preset_names())})")


def load_sections(path: str | Path, expected: set[str]) -> dict:
    """Read a YAML config that must consist of exactly the ``expected`` top-level sections."""
    import yaml

    if not Path(path).is_file():
        raise TorchtrackError(f"--config: no such file {path}")
    cfg = yaml.safe_load(Path(path).read_text())
    if not isinstance(cfg, dict) or set(cfg) != expected:
        raise TorchtrackError(f"{path}: expected exactly the sections {sorted(expected)}")
    return cfg
