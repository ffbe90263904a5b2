"""The papers' experiments, one module each, run by ``torchtrack scenario NAME``.

A module defines ``NAME``, ``HELP``, ``DEFAULT_CONFIG`` (its preset), ``RUNS`` (default Monte Carlo runs),
optionally ``PARAMS`` (what a ``torchtrack tune`` fitted-parameter file sets) and ``add_arguments(parser)``
(its own options), and ``run(args) -> int``; ``torchtrack scenario`` adds the options every scenario takes.
"""
