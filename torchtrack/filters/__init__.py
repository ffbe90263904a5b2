"""The filters, one subpackage per family, and the multi-target trackers built on them.

- :mod:`~torchtrack.filters.kalman` — Kalman, extended and unscented filters; maneuver detection.
- :mod:`~torchtrack.filters.imm` — the interacting multiple model filter and its class-conditioned bank.
- :mod:`~torchtrack.filters.particle` — the bootstrap particle filter, resampling, joint tracking and
  classification.
- :mod:`~torchtrack.filters.gmphd` — the labelled Gaussian-mixture PHD filter and its tracker.
- :mod:`~torchtrack.filters.glmb` — the δ-GLMB filter and its tracker.
- :mod:`~torchtrack.filters.pmb` — the Poisson multi-Bernoulli (TOMB/P) filter and its tracker.
- :mod:`~torchtrack.filters.trackers` — what the multi-target trackers share: the :class:`Tracker` protocol, the
  registry (:func:`make_tracker`), the typed options, and the SORT and greedy baselines.
"""
