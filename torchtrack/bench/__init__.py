"""Throughput benchmarks, one module each, run by ``torchtrack bench NAME`` (``torchtrack.cli.bench``).

A module defines ``measure(...)``, typed options in, a :class:`torchtrack.bench._timing.BenchResult` out
(``workload, ours_per_s, reference, reference_per_s, ratio`` and its own numbers; ``payload()`` is the JSON),
and, where it prints more than :func:`torchtrack.bench._timing.format_result`, a ``format_*`` function.
"""
