"""``torchtrack track --benchmark wpafb``: the WPAFB benchmark's preset (or a config path) read, the truth
located, :func:`torchtrack.pipeline.wpafb_benchmark.run_benchmark` run and one Table 1 printed per subset."""

from __future__ import annotations

import os
from pathlib import Path

import yaml

from torchtrack.cli._common import load_tracker_config
from torchtrack.config import preset_path
from torchtrack.errors import TorchtrackError
from torchtrack.io.outputs import write_json
from torchtrack.metrics.table import format_table1

REPO = Path(__file__).resolve().parents[2]

PRESETS = {"wpafb": "wpafb-benchmark"}
"""Short names of ``--benchmark`` (the preset files are named after what they configure)."""


def truth_csv(config: dict) -> Path:
    """The truth CSV: ``$TORCHTRACK_WPAFB/<file>`` where the variable is set, else ``truth`` of the config
    relative to the repository root."""
    name = config.get("truth", "../shared/data/wpafb-aoi02/transformed_object_states.csv")
    env = os.environ.get("TORCHTRACK_WPAFB")
    path = Path(env) / Path(name).name if env else (REPO / name)
    if not path.exists():
        raise TorchtrackError(f"WPAFB truth not found at {path} (set TORCHTRACK_WPAFB to its folder)")
    return path


def run_benchmark(name_or_path: str | Path, out: Path, seed: int, trackers: list[str] | None = None,
                  tracker_config: str | Path | None = None) -> dict:
    """Run the benchmark ``name_or_path`` names (``wpafb``, a preset name or a YAML path); prints one table
    per subset, writes ``out/<subset>/...`` and ``out/benchmark.json``; returns what that file holds.
    ``tracker_config`` (``--config``) replaces the benchmark's own tracker options."""
    from torchtrack.io.wpafb import read_wpafb_csv
    from torchtrack.pipeline.wpafb_benchmark import BenchmarkConfig, benchmark_payload
    from torchtrack.pipeline.wpafb_benchmark import run_benchmark as run

    path = preset_path(PRESETS.get(str(name_or_path), name_or_path))
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise TorchtrackError(f"cannot read benchmark config {path}: {exc}") from None
    config = BenchmarkConfig.from_mapping(raw, f"benchmark config {name_or_path}")
    tracker_options = load_tracker_config(tracker_config or config.tracker_config)
    found = run(config, read_wpafb_csv(truth_csv(raw)), out, seed, tracker_options, trackers)
    for subset, result in found.items():
        print(f"\n{result.title(subset, config)}")
        print(format_table1(result.results))
    payload = {"config": str(name_or_path), **benchmark_payload(config, seed, found)}
    write_json(Path(out) / "benchmark.json", payload)
    return payload
