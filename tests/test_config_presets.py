"""Configs ship as package data and are found by name from any folder (torchtrack.config.preset_path)."""

import subprocess
import sys
from pathlib import Path

import pytest

from torchtrack.config import preset_names, preset_path
from torchtrack.errors import TorchtrackError

REPO_CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def test_every_repository_config_is_a_preset_with_the_same_text():
    names = sorted(p.stem for p in REPO_CONFIGS.glob("*.yaml"))
    assert names == preset_names()
    for name in names:
        assert preset_path(name).read_text() == (REPO_CONFIGS / f"{name}.yaml").read_text()


@pytest.mark.parametrize("spelling", ["gmphd-paper", "gmphd-paper.yaml", "configs/gmphd-paper.yaml"])
def test_a_preset_by_name_from_another_folder(spelling, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert preset_path(spelling).read_text() == (REPO_CONFIGS / "gmphd-paper.yaml").read_text()


def test_an_existing_path_wins_over_a_preset_of_the_same_name(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "maneuver.yaml").write_text("mine: 1\n")
    assert preset_path("maneuver.yaml") == Path("maneuver.yaml")


def test_unknown_names_and_missing_files_are_refused_naming_the_presets(tmp_path):
    with pytest.raises(TorchtrackError, match="no-such-preset: no such file or preset .*gmphd-paper"):
        preset_path("no-such-preset")
    with pytest.raises(TorchtrackError, match="no such file or preset"):
        preset_path(tmp_path / "elsewhere" / "gmphd.yaml")


def test_the_command_line_takes_a_preset_name_from_an_empty_folder(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "torchtrack", "scenario", "maneuver", "--config", "maneuver",
                           "--runs", "2"], cwd=tmp_path, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "RMSE reduction" in proc.stdout
    bad = subprocess.run([sys.executable, "-m", "torchtrack", "scenario", "maneuver", "--config", "nope"],
                         cwd=tmp_path, capture_output=True, text=True)
    assert bad.returncode == 2
    assert "argument --config: nope: no such file or preset" in bad.stderr.strip().splitlines()[-1]
