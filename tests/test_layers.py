"""The import layers of the design (pyproject.toml's [tool.importlinter] contracts) hold: ``lint-imports``.

Also checked by hand-rolled means that do not need import-linter: no module outside the command layer imports
it, and no library module mentions argparse's Namespace.
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
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
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


def test_no_library_module_takes_an_argparse_namespace():
    exempt = ("scenarios", "bench")  # the papers' experiments and the benchmarks are still command modules
    offenders = [str(p.relative_to(ROOT)) for p in _library_modules()
                 if p.relative_to(PACKAGE).parts[0] not in exempt and "Namespace" in p.read_text()]
    assert offenders == []
