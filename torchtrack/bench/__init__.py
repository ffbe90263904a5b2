"""Throughput benchmarks, one module each, run by ``torchtrack bench NAME``.

A module defines ``NAME``, ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int`` (``torchtrack bench``
adds ``--seed`` and ``--json``) and reports ``workload, ours_per_s, reference, reference_per_s, ratio`` (see
:func:`torchtrack.bench._timing.report`).
"""
