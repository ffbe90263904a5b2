"""The import layers of the design (pyproject.toml's [tool.importlinter] contracts) hold: ``lint-imports``.

Also checked by hand-rolled means that do not need import-linter: no module outside the command layer imports
it, and no library module imports argparse or takes an argparse Namespace.
"""

import ast
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "torchtrack"


def _imports(path: Path) -> set[str]:
    return _imported(ast.parse(path.read_text()))


def _imported(tree: ast.Module) -> set[str]:
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
        elif isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
    return names


def _library_modules() -> list[Path]:
    return [p for p in PACKAGE.rglob("*.py") if "cli" not in p.relative_to(PACKAGE).parts[:1]
            and p.name != "__main__.py"]


def test_lint_imports_contracts_hold():
    exe = shutil.which("lint-imports") or shutil.which("lint-imports", path=str(Path(sys.executable).parent))
    if exe is None:
        pytest.skip("import-linter is not installed (pip install import-linter, the `test` extra): "
                    "the layer contracts were not checked")
    done = subprocess.run([exe, "--config", str(ROOT / "pyproject.toml")], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]


def test_no_library_module_imports_the_command_layer():
    offenders = {str(p.relative_to(ROOT)): sorted(m for m in _imports(p) if m.split(".")[:2] == ["torchtrack", "cli"])
                 for p in _library_modules()}
    assert {k: v for k, v in offenders.items() if v} == {}


def _command_line_uses(tree: ast.Module) -> list[str]:
    """What in ``tree`` does command-line work: an import of argparse, a parameter annotated with ``Namespace``
    or named ``namespace``, or a command module's functions (``add_arguments(parser)``, ``run(args)``)."""
    found = [f"imports {n}" for n in _imported(tree) if n.split(".")[0] == "argparse"]
    for node in ast.walk(tree):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        a = node.args
        params = [p for p in [*a.posonlyargs, *a.args, *a.kwonlyargs, a.vararg, a.kwarg] if p is not None]
        for arg in params:
            annotation = ast.unparse(arg.annotation) if arg.annotation is not None else ""
            if arg.arg == "namespace" or "Namespace" in annotation:
                found.append(f"{node.name}({arg.arg}{': ' + annotation if annotation else ''})")
        if node in tree.body and (node.name == "add_arguments" or (node.name == "run" and [p.arg for p in params]
                                                                     == ["args"])):
            found.append(f"command function {node.name}")
    return found


def test_no_library_module_takes_an_argparse_namespace():
    """Only the command layer reads the command line: outside ``torchtrack/cli`` (and ``__main__.py``) no module
    imports argparse or has a parameter that is an argparse Namespace (by name or annotation)."""
    offenders = {str(p.relative_to(ROOT)): found for p in _library_modules()
                 if (found := _command_line_uses(ast.parse(p.read_text())))}
    assert offenders == {}


@pytest.mark.parametrize("source", [
    "import argparse",
    "from argparse import Namespace",
    "def run(args): ...",
    "def add_arguments(parser) -> None: ...",
    "def main(ns: 'argparse.Namespace') -> int: ...",
    "from typing import Any\ndef step(options: Any, *, namespace=None): ...",
])
def test_the_command_line_check_finds(source):
    assert _command_line_uses(ast.parse(source))


def test_the_command_line_check_passes_typed_functions():
    source = "def run(config: Path, runs: int, *, seed: int = 0) -> int: ...\ndef step(*args): ..."
    assert _command_line_uses(ast.parse(source)) == []
