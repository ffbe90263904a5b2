"""Every ``--help`` of ``torchtrack`` tells the truth in the same way: no Sphinx markup, no internal class names,
no issue or session numbers; every option has a help line that shows its default; ``--seed`` only where the
command draws random numbers, ``--no-progress`` where it draws a progress bar; an unknown argument and a wrong
preset name are usage errors of the command given them.

The parsers are built in this process, command by command, exactly as ``torchtrack CMD ... --help`` builds
them (only the chosen command's module is imported, :func:`torchtrack.cli.build_parser`)."""

from __future__ import annotations

import argparse
import ast
import inspect
import re
from pathlib import Path

import pytest

import torchtrack
from torchtrack.cli import build_parser, main

TRACKERS = ("gmphd", "labelled-gmphd", "sort", "greedy", "pmb", "glmb")

# Commands that draw no random number (no --seed) and those that draw a progress bar (--no-progress).
DETERMINISTIC = {("convert-wpafb",), ("data", "fetch"), ("draw",), ("eval",), ("select-trackers",)}
PROGRESS_BARS = {("demo",), ("draw",), ("track",), ("tune",), ("train-detector",), ("select-trackers",),
                 ("simulate-video",), ("data", "fetch"), ("scenario", "formation"), ("scenario", "jtc"),
                 ("scenario", "pedestrian")}


def _subparsers(parser: argparse.ArgumentParser) -> argparse._SubParsersAction | None:
    return next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)


def _walk() -> dict[tuple[str, ...], argparse.ArgumentParser]:
    """Every command path (``()`` for ``torchtrack`` itself) and its parser, built as its ``--help`` builds it."""
    found = {}

    def visit(path: tuple[str, ...]) -> None:
        parser = build_parser(list(path))
        for name in path:
            parser = _subparsers(parser).choices[name]
        found[path] = parser
        sub = _subparsers(parser)
        for name in sub.choices if sub is not None else ():
            visit((*path, name))

    visit(())
    return found


COMMANDS = _walk()


def _internal_class_names() -> set[str]:
    """The CamelCase names of the classes that torchtrack defines (e.g. ``OutputFolder``)."""
    names = set()
    for path in Path(torchtrack.__file__).parent.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and re.fullmatch(r"_?[A-Z][a-z0-9]+(?:[A-Z][A-Za-z0-9]*)+", node.name):
                names.add(node.name.lstrip("_"))
    return names


def _options(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {s: a for a in parser._actions for s in a.option_strings}


def _label(path: tuple[str, ...]) -> str:
    return " ".join(("torchtrack", *path))


def test_every_command_is_walked():
    assert {("track",), ("draw",), ("scenario", "jtc"), ("bench", "kf"), ("data", "fetch")} <= set(COMMANDS)
    assert sum(len(p) == 2 and p[0] == "bench" for p in COMMANDS) >= 10


def test_no_markup_internal_names_or_history_in_any_help():
    classes = _internal_class_names()
    assert "OutputFolder" in classes
    problems = []
    for path, parser in COMMANDS.items():
        text = parser.format_help()
        for pattern, what in ((r"`|:[a-z]+:`|\*\*|^\s*\* ", "Sphinx markup"),
                              (r"\bissues?\b|\bsessions?\b|#\d+|\bUTC\b|load average", "history")):
            for m in re.finditer(pattern, text, re.IGNORECASE | re.MULTILINE):
                context = text[max(0, m.start() - 40):m.end() + 20]
                problems.append(f"{_label(path)}: {what} {m.group()!r} in ...{context!r}")
        problems += [f"{_label(path)}: internal class name {name}" for name in classes
                     if re.search(rf"\b{name}\b", text)]
    assert not problems, "\n".join(problems)


def test_every_option_has_help_that_shows_its_default():
    problems = []
    for path, parser in COMMANDS.items():
        formatter = parser._get_formatter()
        for action in parser._actions:
            if isinstance(action, (argparse._HelpAction, argparse._VersionAction, argparse._SubParsersAction)):
                continue
            if action.help is argparse.SUPPRESS:
                continue
            name = "/".join(action.option_strings) or action.dest
            text = formatter._expand_help(action) if action.help else ""
            if not text.strip():
                problems.append(f"{_label(path)} {name}: no help text")
            has_default = not (any(action.default is v for v in (None, False, True, argparse.SUPPRESS))
                               or action.default in ([], ()))
            if action.option_strings and has_default and "default" not in text.lower():
                problems.append(f"{_label(path)} {name}: default {action.default!r} not shown in {text!r}")
    assert not problems, "\n".join(problems)


def test_seed_only_where_the_command_is_random():
    problems = []
    for path, parser in COMMANDS.items():
        run = parser.get_default("_run")
        if run is None or _subparsers(parser) is not None:
            continue
        has_seed = "--seed" in _options(parser)
        source = inspect.getsource(inspect.getmodule(run))
        if path in DETERMINISTIC:
            if has_seed:
                problems.append(f"{_label(path)}: --seed on a command that draws no random number")
        elif not has_seed or "seed" not in source:
            problems.append(f"{_label(path)}: random, but --seed is {'not read' if has_seed else 'missing'}")
    assert not problems, "\n".join(problems)


def test_no_progress_on_every_command_with_a_progress_bar():
    missing = [_label(p) for p in PROGRESS_BARS if "--no-progress" not in _options(COMMANDS[p])]
    assert not missing
    # and nowhere a progress bar is not drawn
    extra = [_label(p) for p, parser in COMMANDS.items() if "--no-progress" in _options(parser)
             and p not in PROGRESS_BARS]
    assert not extra


def test_top_level_help_lists_the_trackers_and_the_video_inputs():
    text = COMMANDS[()].format_help()
    one_line = " ".join(text.split())
    for tracker in TRACKERS:
        assert re.search(rf"(?<![\w-]){re.escape(tracker)}(?![\w-])", one_line), tracker
    for word in ("video", "frames", "detections"):
        assert word in one_line, word


def test_track_help_starts_with_frames_and_video():
    parser = COMMANDS[("track",)]
    description = parser.description
    first_paragraph = description.split("\n\n")[0]
    assert "video" in first_paragraph and "frames" in first_paragraph
    examples = description[description.index("Examples:"):].splitlines()[1:3]
    assert any("--video" in line for line in examples) and any("--frames" in line for line in examples)


def test_track_without_input_names_every_input(tmp_path, capsys):
    assert main(["track", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("torchtrack track: error:")
    for flag in ("--video", "--frames", "--sequences", "--detections", "--benchmark"):
        assert flag in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("path", [("track",), ("eval",), ("scenario", "maneuver"), ("bench", "kf"), ("data", "fetch")])
def test_unknown_argument_is_the_commands_usage_error(path, capsys):
    with pytest.raises(SystemExit) as stop:
        main([*path, *(["wpafb"] if path == ("data", "fetch") else []), "--no-such-option"])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    prog = _label(path)
    assert err.startswith(f"usage: {prog} ")
    assert f"{prog}: error: unrecognized arguments: --no-such-option" in err


def test_every_command_reports_an_unknown_argument_with_its_own_usage(capsys):
    for path, parser in COMMANDS.items():
        if _subparsers(parser) is not None:
            continue
        argv = [*path, "--no-such-option"]
        with pytest.raises(SystemExit) as stop:
            build_parser(argv).parse_args(argv)
        err = capsys.readouterr().err
        prog = _label(path)
        assert stop.value.code == 2 and err.startswith(f"usage: {prog} ") and f"\n{prog}: error: " in err, err


def test_wrong_preset_name_lists_only_the_commands_presets(capsys):
    checked = 0
    for path, parser in COMMANDS.items():
        for option, action in _options(parser).items():
            presets = getattr(action.type, "presets", None)
            if not presets or not option.startswith("--"):
                continue
            args = [*path, *(["wpafb"] if path == ("data", "fetch") else []), option, "no-such-preset"]
            with pytest.raises(SystemExit):
                build_parser(args).parse_args(args)
            err = capsys.readouterr().err
            listed = re.search(r"presets: ([^)]*)\)", err).group(1).split(", ")
            assert listed == list(presets), (path, option, err)
            assert err.startswith(f"usage: {_label(path)} ") and f"{_label(path)}: error: argument {option}" in err
            checked += 1
    assert checked >= 8
