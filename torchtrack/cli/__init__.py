"""The ``torchtrack`` command.

Each sub-command lives in its own module of this package and defines ``NAME``, ``HELP``,
optional ``DESCRIPTION``, ``add_arguments(parser)`` and ``run(args) -> int``; modules are discovered
automatically, so a new command is a new file. A command group (``scenario``, ``bench``) is a sub-package
whose ``__init__`` is the command and whose modules are its members. ``NAME`` and ``HELP`` are read from the source
without importing it, and only the module of the command being run is imported: a command pays
only for its own dependencies.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import importlib.util
import os
import pkgutil
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

from torchtrack.errors import TorchtrackError
from torchtrack.io.outputs import check_output_file


def _literal(tree: ast.Module, name: str) -> str | None:
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == name for t in node.targets):
            if isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
                return node.value.value
    return None


def discover(package: str) -> list[tuple[str, str, str]]:
    """``(NAME, HELP, module name)`` of every command module of ``package``, sorted by name."""
    spec = importlib.util.find_spec(package)
    found = []
    for info in pkgutil.iter_modules(spec.submodule_search_locations):
        if info.name.startswith("_"):
            continue
        path = Path(info.module_finder.path) / (f"{info.name}/__init__.py" if info.ispkg else f"{info.name}.py")
        if not path.is_file():
            continue
        tree = ast.parse(path.read_text())
        name, help_ = _literal(tree, "NAME"), _literal(tree, "HELP")
        if name is not None:
            found.append((name, help_ or "", f"{package}.{info.name}"))
    return sorted(found)


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions as written; every option's help ends with its default where it has one and does not
    already say it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        unset = any(default is v for v in (None, False, True, argparse.SUPPRESS)) or default in ([], ())
        if action.option_strings and not unset and "default" not in text.lower():
            shown = " ".join(map(str, default)) if isinstance(default, (list, tuple)) else str(default)
            text += f" (default: {shown.replace('%', '%%')})"
        return text


class CommandParser(argparse.ArgumentParser):
    """The parser of ``torchtrack`` and of each of its commands (sub-commands get the same class): an unknown
    argument is reported by the command that was given it, with that command's usage
    (``torchtrack track: error: unrecognized arguments: --bogus``), not by ``torchtrack`` itself."""

    def __init__(self, *args, formatter_class=HelpFormatter, **kwargs) -> None:
        super().__init__(*args, formatter_class=formatter_class, **kwargs)

    def parse_args(self, args=None, namespace=None) -> argparse.Namespace:
        namespace, extra = self.parse_known_args(args, namespace)
        if extra:
            getattr(namespace, "_parser", self).error(f"unrecognized arguments: {' '.join(extra)}")
        return namespace


def add_subcommands(parser: argparse.ArgumentParser, package: str, dest: str, argv: list[str],
                    options: Callable[[argparse.ArgumentParser, ModuleType], None] | None = None) -> None:
    """Attach the command modules of ``package`` to ``parser``; import only the one ``argv`` selects. Its
    parser gets the module's ``add_arguments`` (where it has one), then ``options(parser, module)`` (the
    options that every module of ``package`` takes)."""
    sub = parser.add_subparsers(dest=dest, metavar="NAME", required=True)
    chosen = next((a for a in argv if not a.startswith("-")), None)
    for name, help_, modname in discover(package):
        if name != chosen:
            sub.add_parser(name, help=help_, description=help_)
            continue
        module = importlib.import_module(modname)
        p = sub.add_parser(name, help=help_, description=getattr(module, "DESCRIPTION", help_))
        p.set_defaults(_run=module.run, _argv_rest=argv[argv.index(chosen) + 1:], _parser=p)
        if hasattr(module, "add_arguments"):
            module.add_arguments(p)
        if options is not None:
            options(p, module)


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The ``torchtrack`` parser, with the arguments of the command that ``argv`` selects."""
    argv = sys.argv[1:] if argv is None else argv
    parser = CommandParser(
        prog="torchtrack",
        description="Batched, differentiable target tracking on PyTorch. Track the moving objects of a video or a\n"
        "folder of frames (torchtrack track --video FILE or --frames DIR), or of a detection file, with one of six\n"
        "trackers; score, draw and tune them; run the papers' experiments and the benchmarks.\n"
        "torchtrack CMD --help says what a command does and takes.",
    )
    from torchtrack import __version__

    parser.add_argument("--version", action="version", version=f"torchtrack {__version__}")
    add_subcommands(parser, "torchtrack.cli", "command", argv)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command of ``argv``. Every failure ends as one line ``torchtrack COMMAND: error: ...`` on stderr:
    exit 2 for bad input (a :class:`~torchtrack.errors.TorchtrackError`, a file that cannot be read or written),
    1 for an internal failure (any other exception; ``TORCHTRACK_DEBUG=1`` lets its traceback through), 130 when
    interrupted."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser(argv).parse_args(argv)
    try:
        check_output_file(getattr(args, "json", None), "--json")
        return int(args._run(args) or 0)
    except TorchtrackError as exc:
        return _error(args.command, str(exc), 2)
    except KeyboardInterrupt:
        print("torchtrack: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:  # a file or folder the command could not use: the input's fault, named
        where = f"{os.fsdecode(exc.filename)}: " if exc.filename is not None else ""
        return _error(args.command, f"{where}{exc.strerror or exc}", 2)
    except Exception as exc:
        if os.environ.get("TORCHTRACK_DEBUG"):
            raise
        return _error(args.command, f"internal failure ({type(exc).__name__}: {exc}); please report it with the "
                      "command line that caused it (TORCHTRACK_DEBUG=1 shows the traceback)", 1)


def _error(command: str, message: str, code: int) -> int:
    """``torchtrack COMMAND: error: MESSAGE`` on one line of stderr; returns the exit status ``code``."""
    print(f"torchtrack {command}: error: {' '.join(message.split())}", file=sys.stderr)
    return code


if __name__ == "__main__":
    sys.exit(main())
