"""``torchtrack track --benchmark wpafb``: the WPAFB benchmark's preset (or a config path) read, the truth
located, :func:`torchtrack.pipeline.wpafb_benchmark.run_benchmark` run and one Table 1 printed per subset."""

from __future__ import annotations

import argparse
from pathlib import Path

from torchtrack.config import preset_path, read_mapping
from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.options import read_tracker_sections
from torchtrack.io.datasets import WPAFB, wpafb_truth_csv
from torchtrack.io.outputs import write_json
from torchtrack.metrics.table import format_table1

PRESETS = {"wpafb": "wpafb-benchmark"}
"""Short names of ``--benchmark`` (the preset files are named after what they configure)."""
BENCHMARK_PRESETS = ("wpafb-benchmark", "wpafb-positions")
"""The presets that configure a benchmark."""


def benchmark_config(value: str) -> str:
    """argparse ``type`` of ``--benchmark``: ``value`` unchanged where it names a benchmark preset (or its short
    name) or a file; otherwise a usage error listing the names ``--benchmark`` takes."""
    try:
        preset_path(PRESETS.get(value, value), BENCHMARK_PRESETS)
    except TorchtrackError:
        raise argparse.ArgumentTypeError(f"{value}: no such file or benchmark preset (presets: "
                                         f"{', '.join(benchmark_config.presets)})") from None
    return value


benchmark_config.presets = (*PRESETS, *BENCHMARK_PRESETS)


def truth_csv(config: dict) -> Path:
    """The truth CSV that the config's ``truth`` names: ``wpafb`` (the default) for the data set wherever
    :func:`torchtrack.io.datasets.locate` finds it, or a path to the CSV or its folder."""
    return wpafb_truth_csv(config.get("truth", WPAFB.name))


def run_benchmark(name_or_path: str | Path, out: Path, seed: int, trackers: list[str] | None = None,
                  tracker_config: str | Path | None = None) -> dict:
    """Run the benchmark ``name_or_path`` names (``wpafb``, a preset name or a YAML path); prints one table
    per subset, writes ``out/<subset>/...`` and ``out/benchmark.json``; returns what that file holds.
    ``tracker_config`` (``--config``) replaces the benchmark's own tracker options."""
    from torchtrack.io.wpafb import read_wpafb_csv
    from torchtrack.pipeline.wpafb_benchmark import BenchmarkConfig, benchmark_payload
    from torchtrack.pipeline.wpafb_benchmark import run_benchmark as run

    path = preset_path(PRESETS.get(str(name_or_path), name_or_path), BENCHMARK_PRESETS)
    raw = read_mapping(path, "benchmark config")
    config = BenchmarkConfig.from_mapping(raw, f"benchmark config {name_or_path}")
    tracker_options = read_tracker_sections(tracker_config or config.tracker_config)
    found = run(config, read_wpafb_csv(truth_csv(raw)), out, seed, tracker_options, trackers)
    for subset, result in found.items():
        print(f"\n{format_table1(result.results, result.title(subset, config))}")
    payload = {"config": str(name_or_path), **benchmark_payload(config, seed, found)}
    write_json(Path(out) / "benchmark.json", payload)
    return payload
