"""Fitting filter parameters by gradient; the public entry points are in :mod:`torchtrack.tuning.tune`."""
