#!/usr/bin/env bash
# Build the documentation site into docs/_build/html/ (after scripts/setup.sh): the user guide, the API reference
# generated from the docstrings, and the gallery, whose examples are run. Any warning fails the build.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
"$PY" -m pip install --quiet -e ".[docs]"
rm -rf docs/api docs/auto_examples docs/_build
MPLBACKEND=Agg OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} "$PY" -m sphinx -W --keep-going -b html -q docs docs/_build/html
# every public module of the library has its page in the API reference (the command line, torchtrack.cli, has none)
"$PY" - <<'PYEOF'
import ast
import pkgutil
import sys
from pathlib import Path

import torchtrack

modules = ["torchtrack"] + [m.name for m in pkgutil.walk_packages(torchtrack.__path__, "torchtrack.")
                            if not any(part.startswith("_") for part in m.name.split("."))
                            and not m.name.startswith("torchtrack.cli")]
missing = [m for m in modules if not Path(f"docs/api/{m}.rst").is_file()]
if missing:
    sys.exit(f"build-docs: no API reference page for {', '.join(missing)}")
cli_pages = sorted(p.name for p in Path("docs/api").glob("torchtrack.cli*.rst"))
if cli_pages:
    sys.exit(f"build-docs: the API reference documents the library only; remove {', '.join(cli_pages)}")
undescribed = [m.name for m in pkgutil.walk_packages(torchtrack.__path__, "torchtrack.") if m.name in modules
               and not ast.get_docstring(ast.parse(Path(m.module_finder.find_spec(m.name).origin).read_text()))]
if undescribed:
    sys.exit(f"build-docs: no module docstring (the API reference's one-line description) in {', '.join(undescribed)}")
print(f"API reference: {len(modules)} public modules, each with its page", file=sys.stderr)
PYEOF
echo "documentation built: docs/_build/html/index.html" >&2
