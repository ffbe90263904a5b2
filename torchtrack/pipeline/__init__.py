"""The video pipeline and the tracker stream every command runs: registration, detection, the moving-object gate,
the tracker, fixed-lag output, scoring; ``torchtrack.track`` lives in :mod:`torchtrack.pipeline.api`."""
