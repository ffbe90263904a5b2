"""The ``torchtrack`` command.

Each sub-command lives in its own module of this package and defines ``NAME``, ``HELP``,
``add_arguments(parser)`` and ``run(args) -> int``; modules are discovered automatically, so a
new command is a new file.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from torchtrack.errors import TorchtrackError


def _command_modules(package: str) -> list:
    pkg = importlib.import_module(package)
    modules = []
    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{package}.{info.name}")
        if hasattr(module, "NAME") and hasattr(module, "run"):
            modules.append(module)
    return modules


def add_subcommands(parser: argparse.ArgumentParser, package: str, dest: str) -> None:
    """Attach every command module found in ``package`` as a sub-parser of ``parser``."""
    sub = parser.add_subparsers(dest=dest, metavar="NAME", required=True)
    for module in _command_modules(package):
        p = sub.add_parser(
            module.NAME,
            help=module.HELP,
            description=getattr(module, "DESCRIPTION", module.HELP),
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        module.add_arguments(p)
        p.set_defaults(_run=module.run)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="torchtrack",
        description="Batched, differentiable target tracking: filters, scenarios from the papers, "
        "a detector and a satellite-video pipeline.",
    )
    from torchtrack import __version__

    parser.add_argument("--version", action="version", version=f"torchtrack {__version__}")
    add_subcommands(parser, "torchtrack.cli", "command")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except TorchtrackError as exc:
        print(f"torchtrack {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("torchtrack: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
