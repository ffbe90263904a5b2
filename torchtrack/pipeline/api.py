"""The Python face of the main job: :func:`track` runs one tracker on frames, a video or detections, as
``torchtrack track`` does (the command calls it); ``torchtrack.evaluate``
(:func:`torchtrack.metrics.evaluation.evaluate_scores`) scores tracks as ``torchtrack eval`` does.

::

    import torchtrack

    result = torchtrack.track(frames="seq/frames", gt="seq/gt.txt")   # the video pipeline
    print(result.metrics["MOTA"])                                     # the moving vehicles (score="moving")
    result.save("out/seq")                                            # the command's files, as one set

    result = torchtrack.track(detections="det.txt", tracker="glmb", gt="gt.txt")
    scores = torchtrack.evaluate("gt.txt", result.tracks, moving=True)   # the scores of result.metrics

Inputs are paths or arrays: a detection or truth array holds MOTChallenge rows ``(K, 6..10)``
(``frame, id, x, y, w, h[, conf, vx, vy, -1]``, the columns of the files; :func:`torchtrack.io.mot.from_rows`),
frames an array ``(T, H, W)`` of grey images or a list of them.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterable, Mapping
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.options import read_tracker_sections
from torchtrack.filters.trackers.protocol import Tracker
from torchtrack.io.frames import ArraySource, FrameSource, open_frames
from torchtrack.io.mot import MOTData, as_mot, as_rows, read_mot
from torchtrack.io.moving import SCORES, dont_care, flags_beside
from torchtrack.io.outputs import OutputFolder
from torchtrack.pipeline.config import PipelineConfig, load_pipeline_config
from torchtrack.pipeline.detection_file import detection_file_config, track_detections
from torchtrack.pipeline.track_video import track_video

COMMAND = "torchtrack track"
"""The command named in the marker of the output folders that :func:`track` and :meth:`TrackResult.save` write
(:class:`torchtrack.io.outputs.OutputFolder`): ``torchtrack track --out`` may replace them."""

MOTInput = str | os.PathLike | MOTData | np.ndarray
EXTRAS = ("tracker", "frames_run", "seconds", "FPS")
"""The keys of :attr:`TrackResult.metrics` beside the scores, for every input: the tracker's name, the frames it
ran, its seconds and its frames per second (the tracker alone, as Table 1's FPS)."""


@dataclass
class TrackResult:
    """What :func:`track` produced.

    Attributes:
        tracks: ``(N, 10)`` MOTChallenge rows of the reported targets (frame coordinates), sorted by frame and id:
            the content of ``tracks.txt``.
        detections: ``(M, 10)`` rows of the detections the tracker was given (the detector's, velocities in
            columns 8 and 9, for frames and videos; the input's for detections).
        metrics: one flat dict for every input, None without truth: the keys of ``torchtrack eval --json``
            (``MOTA``, ``MOTP``, ``IDF1``, ``HOTA``, ..., ratios as fractions; ``gate`` and ``moving_only`` say how
            it was scored) and :data:`EXTRAS` beside them.
        report: everything ``metrics.json`` holds (the scores where there is truth, frames, timings, frames/s;
            for frames and videos the scores under ``clear_mot``, with the registration's summary).
        files: the files written, by kind (``tracks``, ``detections``, ``metrics``, ``video``; with
            ``calibrate``: ``config``, ``calibration``, ``loss``).
        calibration: with ``calibrate``, the content of ``calibration.json`` (its ``status`` says whether the
            fit passed its checks); else None.
    """

    tracks: np.ndarray
    detections: np.ndarray
    metrics: dict | None
    report: dict
    files: dict[str, Path] = field(default_factory=dict)
    calibration: dict | None = None
    _scratch: tempfile.TemporaryDirectory | None = field(default=None, repr=False)

    def save(self, out_dir: str | os.PathLike, force: bool = False) -> dict[str, Path]:
        """Write the run's files into ``out_dir`` as one set (an existing folder is replaced only when it holds
        the output of ``torchtrack track``, or with ``force``); returns where each file now is."""
        folder = OutputFolder(out_dir, COMMAND, force)
        with folder as staging:
            copied = {kind: Path(shutil.copy2(path, staging / path.name)) for kind, path in self.files.items()}
        self.files = {kind: folder.final(path) for kind, path in copied.items()}
        return self.files


def tracker_options(config: str | os.PathLike | Mapping | Any | None, tracker: str) -> dict[str, Any]:
    """Tracker name → options, from ``config``: a tracker YAML (path or preset name, one section per tracker),
    a mapping of sections, or typed options (the dataclass of ``tracker``, e.g. a
    :class:`~torchtrack.filters.trackers.options.GMPHDConfig`)."""
    if config is None or isinstance(config, str | os.PathLike):
        return read_tracker_sections(config)
    if isinstance(config, Mapping):
        return dict(config)
    return {tracker: config}


def _frame_source(frames: str | os.PathLike | np.ndarray | Iterable[np.ndarray] | None,
                  video: str | os.PathLike | None) -> FrameSource:
    if video is not None:
        return open_frames(video)
    if isinstance(frames, str | os.PathLike):
        return open_frames(frames)
    return ArraySource(frames)


def track(frames: str | os.PathLike | np.ndarray | Iterable[np.ndarray] | None = None,
          video: str | os.PathLike | None = None, detections: MOTInput | None = None, *,
          tracker: str | Tracker = "gmphd", tracker_name: str | None = None,
          config: str | os.PathLike | Mapping | Any | None = None, gt: MOTInput | None = None,
          gt_name: str | None = None, score: str = "moving",
          device: str = "cpu", threshold: float = 10.0,
          pipeline_config: str | os.PathLike | PipelineConfig | None = None,
          weights: str | os.PathLike | None = None, draw_video: bool | None = None, threads: int | None = None,
          camera: np.ndarray | None = None, ignore: np.ndarray | None = None,
          out: str | os.PathLike | None = None, force: bool = False, inputs: Iterable[str | os.PathLike | None] = (),
          progress: bool = False) -> TrackResult:
    """Run one tracker on ``frames`` (a folder of images or an array), a ``video`` file or ``detections``.

    Args:
        frames, video, detections: the input, exactly one. Frames and videos go through the video pipeline
            (registration, detector, moving-object gate, tracker, fixed-lag output); detections straight to the
            tracker (no gate, online output, unless ``pipeline_config`` sets them).
        tracker: a registered name (``gmphd``, ``labelled-gmphd``, ``sort``, ``greedy``, ``pmb``, ``glmb``) or a
            tracker object with ``reset()`` and ``step(frame, positions, velocities)``, recorded under
            ``tracker_name`` (default its ``name`` attribute or class name).
        config: the trackers' options (:func:`tracker_options`); default the built-in ones.
        gt: truth to score against (a path, :class:`MOTData` or rows); ``gt_name`` names it in errors (default: its
            path).
        score: which of ``gt``'s objects are targets (:func:`torchtrack.io.moving.dont_care`): ``moving`` (default)
            the moving vehicles, the others don't-care, as ``torchtrack eval --moving`` scores (the
            ``velocity.txt`` beside a ``gt`` path where its sequence has one, else the paper's displacement rule);
            ``all`` every object. ``ignore (K,)`` replaces the moving rule's don't-care lines with these
            (``score="moving"`` only).
        device: where the tracker (and the detector) run: ``cpu``, ``cuda`` or ``cuda:N``.
        threshold: the CLEAR-MOT centre distance in px (detections; frames take the pipeline config's).
        pipeline_config: the video pipeline's settings (a YAML path or preset name, or a :class:`PipelineConfig`).
        weights: detector weights (default: the shipped ones). ``draw_video``: write ``annotated.mp4`` (default:
            as the pipeline config says; the embedded one does). ``threads``: torch CPU threads of the pipeline.
        camera: the true homographies ``(T, 3, 3)`` of a synthetic sequence, to measure the registration.
        out: write the files there as one set (as ``torchtrack track --out``; ``force`` and ``inputs`` as
            its ``--force`` and the paths it reads); default a temporary folder, kept while the result lives
            (:meth:`TrackResult.save` copies them).
        progress: draw a progress bar (video pipeline).

    Returns:
        A :class:`TrackResult`: ``tracks`` and ``detections`` as MOTChallenge rows, ``metrics`` one flat dict
        whatever the input (the keys of ``torchtrack eval --json`` — ``MOTA``, ``HOTA``, ``IDF1``, ... as
        fractions, ``gate``, ``moving_only`` — and ``tracker``, ``frames_run``, ``seconds``, ``FPS``; None without
        ``gt``), ``report`` (all of ``metrics.json``) and ``files`` (the files written, by kind).

    Raises:
        TorchtrackError: not exactly one input, an unknown ``score``, or an input the reader rejects (one line
        naming it).
    """
    if sum(x is not None for x in (frames, video, detections)) != 1:
        raise TorchtrackError("give exactly one input: frames, video or detections")
    name = tracker if isinstance(tracker, str) else tracker_name or getattr(tracker, "name", type(tracker).__name__)
    built = None if isinstance(tracker, str) else tracker
    options = tracker_options(config, name)
    truth = as_mot(gt, "gt") if gt is not None else None
    ignore = _dont_care(truth, gt, score, ignore)
    scratch = tempfile.TemporaryDirectory(prefix="torchtrack-") if out is None else None
    folder = OutputFolder(out, COMMAND, force, inputs=list(inputs)) if out is not None else None
    with folder if folder is not None else nullcontext(scratch.name) as staging:
        staging = Path(staging)
        if detections is not None:
            det = as_mot(detections, "detections")
            base = _pipeline_config(pipeline_config) if pipeline_config is not None else None
            run_config = detection_file_config(options, threshold, base).replace(device=device)
            report = track_detections(det, name, run_config, staging, truth, built, ignore)
            files = {"tracks": staging / "tracks.txt", "metrics": staging / "metrics.json"}
            tracks, given = read_mot(files["tracks"]), det
        else:
            source = _frame_source(frames, video)
            changes = {"tracker": name, "device": device, "tracker_options": options.get(name),
                       "video": draw_video, "threads": threads,
                       "detector_weights": None if weights is None else str(weights)}
            run_config = _pipeline_config(pipeline_config).replace(
                **{key: value for key, value in changes.items() if value is not None})
            result = track_video(source, staging, run_config, gt=truth, gt_path=gt_name or str(gt), ignore=ignore,
                                 camera=camera, tracker=built, progress=progress)
            report, files, tracks = result.metrics, result.files, result.tracks
            given = read_mot(files["detections"])
    if folder is not None:
        files = {kind: folder.final(path) for kind, path in files.items()}
    metrics = _flat_metrics(report, detections is None) if truth is not None else None
    return TrackResult(as_rows(tracks), as_rows(given), metrics, report, files, _scratch=scratch)


def _flat_metrics(report: dict, video: bool) -> dict:
    """:attr:`TrackResult.metrics` from a scored ``metrics.json`` payload: the video pipeline's (scores under
    ``clear_mot``, the tracker's seconds under ``timings_s``) or the detection file's (flat)."""
    if not video:
        return {key: value for key, value in report.items() if key != "cap_hits"}
    seconds = report["timings_s"].get("tracking", 0.0)
    return {**report["clear_mot"], "tracker": report["tracker"], "frames_run": report["frames"], "seconds": seconds,
            "FPS": report["frames"] / seconds if seconds > 0 else float("inf")}


def _dont_care(truth: MOTData | None, gt: MOTInput | None, score: str, ignore: np.ndarray | None
               ) -> np.ndarray | None:
    """The don't-care lines of ``truth`` under ``score``: ``ignore`` where given, else those of
    :func:`~torchtrack.io.moving.dont_care` (with the ``velocity.txt`` beside ``gt`` where it is a path)."""
    if score not in SCORES:
        raise TorchtrackError(f"score must be one of {', '.join(SCORES)}; got {score!r}")
    if ignore is not None and score != "moving":
        raise TorchtrackError("ignore marks the don't-care lines of score='moving'; score='all' has none")
    if truth is None or ignore is not None:
        return ignore
    return dont_care(truth, score, flags_beside(gt) if isinstance(gt, str | os.PathLike) else None)


def _pipeline_config(value: str | os.PathLike | PipelineConfig | None) -> PipelineConfig:
    return value if isinstance(value, PipelineConfig) else load_pipeline_config(value)
