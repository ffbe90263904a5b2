"""Every command explains itself with --help; the entry point is discovered from the modules."""

import subprocess
import sys

import pytest

from torchtrack.cli import build_parser, discover


def _commands():
    names = []
    for name, _, _ in discover("torchtrack.cli"):
        names.append([name])
    for package, group in (("torchtrack.cli.scenarios", "scenario"), ("torchtrack.cli.bench", "bench")):
        for name, _, _ in discover(package):
            names.append([group, name])
    names.append(["data", "fetch"])
    return names


@pytest.mark.parametrize("argv", _commands(), ids=lambda a: " ".join(a))
def test_help(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        build_parser([*argv, "--help"]).parse_args([*argv, "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "usage: torchtrack" in out
    if argv[0] not in ("scenario", "bench", "data") or len(argv) > 1:  # the groups only list their members
        assert "--json" in out  # --seed only where the command is random: tests/test_help.py


def test_core_commands_exist():
    names = {" ".join(a) for a in _commands()}
    assert {"scenario maneuver", "bench kf"} <= names


def test_console_entry_point_runs():
    proc = subprocess.run([sys.executable, "-m", "torchtrack", "--version"], capture_output=True, text=True)
    assert proc.returncode == 0 and "torchtrack" in proc.stdout
