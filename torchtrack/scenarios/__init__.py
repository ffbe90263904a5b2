"""The papers' experiments, one module each, run by ``torchtrack scenario NAME``.

A module defines ``NAME``, ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int``.
"""
