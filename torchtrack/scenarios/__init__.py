"""The papers' experiments, one module each, run by ``torchtrack scenario NAME`` (``torchtrack.cli.scenarios``).

A module defines ``DEFAULT_CONFIG`` (its preset), ``load_config(path)``, one function that runs the experiment
from a config path and typed options (``runs``, ``seed``, ...) and returns a typed report, and
``format_report``/``report_json``: the text the command prints and the numbers of its ``--json``.
"""
