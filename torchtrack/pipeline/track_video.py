"""The end-to-end video pipeline (Fig. 1 of Aguilar et al., ICASSP 2023), streaming frame by frame.

For each frame ``k`` (only the previous frame is kept, so memory does not grow with the sequence):

1. **register** — ``H_k``: frame ``k`` → reference (the first frame), see
   :mod:`torchtrack.pipeline.registration`;
2. **detect** — ``H, V = CT(I_k, I_{k-1}, G_{k-1})`` (paper eq. 1): the detector sees the current
   frame, the previous frame warped into the current one by ``H_k⁻¹ H_{k-1}`` (so that only the
   objects move), and the prior heatmap ``G_{k-1}`` built from the previous frame's detections (or
   tracks) mapped into the current frame;
3. **track** — positions and detector velocities go to reference coordinates (velocities through the
   Jacobian of ``H_k`` at each point) and through :class:`~torchtrack.pipeline.tracker_stream.TrackerStream`
   (moving-object gate, weak detections that continue a track, the tracker's ``step``, fixed-lag output);
   tracks live in reference coordinates (an estimate repeating an identity already reported in the frame
   is dropped, counted and warned about: identities must be unique per frame);
4. **record** — each frame whose tracks became final (``output_lag`` frames later), mapped back into its
   frame by ``H_k⁻¹``, goes to a :class:`~torchtrack.pipeline.recorder.TrackRecorder`, which keeps it in
   memory and appends it to ``tracks.txt`` (flushed: an interrupted run leaves a file complete up to the
   last final frame); the detections likewise to ``detections.txt`` (frame coordinates, with velocities;
   the strong ones: the detector's output at its threshold);
5. **render** — the final frame goes to ``annotated.mp4`` (renamed from ``.partial.mp4`` at the end);
   the last ``output_lag`` images wait for it.

At the end, the recorded tracks (in memory) are scored against the truth (CLEAR-MOT,
:func:`torchtrack.metrics.table.score`) where given, and ``metrics.json`` gets the scores, the per-stage
timings (registration, detection, tracking, I/O, render), the frames per second and the registration's
summary (frame-to-frame residual, segments, searches, the fraction of pixels the moving-object gate passes;
per frame in ``registration.csv``). ``metrics.json`` is written last, so a folder holding it holds a
complete run.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from torchtrack.detector import load_detector
from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.protocol import make_tracker
from torchtrack.geometry import apply_homography, transfer_error
from torchtrack.io.frames import FrameSource, prefetch
from torchtrack.io.mot import MOTData, from_points
from torchtrack.io.outputs import write_json
from torchtrack.io.video_writer import AnnotatedVideoWriter, save_png
from torchtrack.metrics.table import score, scoring
from torchtrack.pipeline.config import PipelineConfig
from torchtrack.pipeline.detection import Detection
from torchtrack.pipeline.fixed_lag import LaggedFrame
from torchtrack.pipeline.frame_detections import FrameDetections
from torchtrack.pipeline.recorder import TrackRecorder
from torchtrack.pipeline.registration import Registration
from torchtrack.pipeline.registration_log import RegistrationLog
from torchtrack.pipeline.timer import StageTimer
from torchtrack.pipeline.tracker_stream import TrackerStream
from torchtrack.threads import torch_threads


def _truth_by_frame(gt: MOTData | None) -> dict[int, np.ndarray]:
    if gt is None:
        return {}
    centers = gt.centers()
    return {int(f): centers[idx] for f, idx in zip(gt.frames(), gt.split())}


def check_truth_frames(gt: MOTData, gt_path: str, frames: int) -> None:
    """Error naming ``gt_path`` when the truth refers to frames beyond the ``frames`` of the video."""
    if gt.size and int(gt.frame.max()) > frames:
        raise TorchtrackError(f"{gt_path}: truth refers to frames up to {int(gt.frame.max())}, but the "
                              f"video has only {frames} frames")


@dataclass
class PipelineResult:
    """What :func:`track_video` produced: the metrics dict (as in ``metrics.json``), the files, the recorded
    ``tracks`` (frame coordinates) and, with ``keep_detections``, every frame's detections."""

    metrics: dict
    tracks: MOTData
    files: dict[str, Path] = field(default_factory=dict)
    detections: list[FrameDetections] = field(default_factory=list)


def track_video(source: FrameSource, out: str | Path, config: PipelineConfig | None = None, detector=None,
                gt: MOTData | None = None, gt_path: str = "gt.txt", ignore: np.ndarray | None = None,
                camera: np.ndarray | None = None, tracker=None,
                keep_detections: bool = False, progress: bool = True) -> PipelineResult:
    """Run the pipeline on ``source`` and write ``tracks.txt``, ``detections.txt``, ``annotated.mp4`` and
    ``metrics.json`` under ``out``.

    Args:
        source: frames (grey).
        config: :class:`PipelineConfig` (defaults: enhanced GM-PHD, LK registration).
        detector: object with ``detect`` (default: the shipped weights, ``detector.load_detector``).
        gt: truth (frame coordinates) to score against and draw; ``gt_path`` names it in errors;
            ``ignore (K,)`` bool over its lines marks don't-care objects (not drawn, not scored: the vehicles
            that are not moving; ``metrics["clear_mot"]`` holds the keys of ``eval --json``, ``moving_only``
            whether ``ignore`` was given).
        camera: true homographies ``(T, 3, 3)`` reference → frame ``k`` of a synthetic sequence; when
            given, the registration error against them is measured and reported.
        tracker: the tracker to run, already built (default: ``make_tracker(config.tracker, ...)``; e.g. a
            :class:`~torchtrack.pipeline.strip_tracking.StripTracker`).
        keep_detections: also return every frame's :class:`FrameDetections` (to run other trackers on
            the same detections, as ``torchtrack demo`` does; a few kB per frame).
    """
    cfg = config or PipelineConfig()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for stale in ("metrics.json", "annotated.mp4"):  # never leave a previous run's results beside ours
        (out / stale).unlink(missing_ok=True)
    n_frames = len(source)
    if gt is not None and n_frames:
        check_truth_frames(gt, gt_path, n_frames)
    if detector is None:
        detector = load_detector(cfg.detector_weights, cfg.detector_tile, cfg.detector_backend)
    timer = StageTimer()
    detection = Detection(detector, Registration(cfg.registration), timer, cfg.detection_threshold,
                          cfg.weak_threshold,
                          gate=(cfg.min_motion, cfg.gate_registration, cfg.min_speed, cfg.gate_budget,
                                cfg.motion_noise_factor),
                          scale=cfg.detector_scale)
    if tracker is None:
        tracker = make_tracker(cfg.tracker, cfg.options_for(cfg.tracker))
    stream = TrackerStream(tracker, cfg)
    truth = _truth_by_frame(gt if ignore is None or gt is None else gt.select(~ignore))
    files = {"tracks": out / "tracks.txt", "detections": out / "detections.txt"}
    marks = ["tracks", *(["trails"] if cfg.trail else []), *(["truth"] if gt is not None and cfg.draw_truth else [])]
    video = AnnotatedVideoWriter(out / "annotated.mp4", fps=cfg.video_fps, trail=cfg.trail, box=cfg.box,
                                 scale=cfg.scale, legend=marks) if cfg.video else None
    kept: list[FrameDetections] = []
    reg_errors: list[float] = []
    per_frame = RegistrationLog(out / "registration.csv")
    files["registration"] = per_frame.path
    waiting: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # frames whose tracks are not final: image, H_k
    frames = 0
    t_start = time.perf_counter()

    def emit(final: list[LaggedFrame], tracks_out: TrackRecorder) -> None:
        """Write and draw the frames whose tracks became final (``output_lag`` frames back)."""
        for index, ids, pos_ref in final:
            image, h = waiting.pop(index)
            h_inv = np.linalg.inv(h)
            with timer("io"):
                tracks_out.record(index, ids, apply_homography(pos_ref, h_inv))
            if video is not None:
                with timer("render"):
                    t = truth.get(index)
                    drawn = video.write(image, ids, pos_ref, homography=h_inv,
                                        truth=None if t is None or not cfg.draw_truth else apply_homography(t, h),
                                        label=f"{cfg.tracker}  frame {index}")
                    if index in cfg.snapshots:
                        save_png(out / f"frame_{index:06d}.png", drawn)

    try:
        with (torch_threads(cfg.threads),
              tqdm(total=n_frames or None, desc=f"track {cfg.tracker}", unit="frame", disable=not progress,
                   leave=False) as bar,
              TrackRecorder(files["tracks"]) as tracks_out, TrackRecorder(files["detections"]) as det_out,
              per_frame):
            frames_in = prefetch(source)
            while True:
                with timer("io"):
                    frame = next(frames_in, None)
                if frame is None:
                    break
                det = detection(frame.index, frame.image)
                per_frame.add(frame.index, detection.last, detection.gate_pass)
                if camera is not None and frame.index <= len(camera):
                    # True frame k → frame 1 map: H_1 H_k^{-1} (the generator's H maps reference → frame).
                    true_h = camera[0] @ np.linalg.inv(camera[frame.index - 1])
                    reg_errors.append(float(np.median(transfer_error(det.homography, true_h, frame.image.shape))))
                waiting[frame.index] = (frame.image, det.homography)
                with timer("tracking"):
                    _, pos_ref, final = stream.step(det)
                if cfg.prior == "tracks":
                    detection.set_prior(pos_ref)
                with timer("io"):
                    found = det.select(det.strong)
                    det_out.record(frame.index, np.full(len(found.scores), -1), found.image_positions, found.scores,
                                   found.image_velocities)
                emit(final, tracks_out)
                if keep_detections:
                    kept.append(det)
                frames += 1
                bar.update()
            with timer("tracking"):
                final = stream.finish()
            emit(final, tracks_out)
        if video is not None:
            with timer("render"):
                files["video"] = video.close()
    except BaseException:
        if video is not None:
            video.abort()
        raise
    wall = time.perf_counter() - t_start
    if frames == 0:
        raise TorchtrackError(f"{source.path}: no frames")
    metrics: dict = {"source": str(source.path), "tracker": cfg.tracker, "frames": frames,
                     "frame_size": list(source.shape)}
    if gt is not None:
        check_truth_frames(gt, gt_path, frames)
        metrics["clear_mot"] = {**score(gt, tracks_out.tracks(), cfg.threshold, ignore),
                                **scoring(ignore is not None, cfg.threshold)}
        det_scores = score(gt, _detections_as_tracks(det_out.tracks()), cfg.threshold, ignore)
        metrics["detector"] = {k: det_scores[k] for k in ("TP", "FP", "FN", "precision", "recall", "MOTP")}
    if stream.duplicates:
        warnings.warn(f"tracker {cfg.tracker} reported {stream.duplicates} estimate(s) under an identity already "
                      "reported in the same frame; they were left out of tracks.txt", stacklevel=2)
        metrics["duplicate_identities_dropped"] = stream.duplicates
    seconds = dict(timer.seconds)
    metrics["timings_s"] = {**seconds, "total": wall}
    metrics["fps"] = {"end_to_end": frames / wall,
                      **{f"{k}_only": frames / v for k, v in seconds.items() if v > 0}}
    metrics["registration"] = per_frame.summary()
    if reg_errors:
        metrics["registration_error_px"] = {"median": float(np.median(reg_errors)),
                                            "p90": float(np.percentile(reg_errors, 90)),
                                            "max": float(np.max(reg_errors))}
    files["metrics"] = out / "metrics.json"
    write_json(files["metrics"], metrics)
    return PipelineResult(metrics, tracks_out.tracks(), files, kept)


def _detections_as_tracks(detections: MOTData) -> MOTData:
    """Detections scored as if each were its own one-frame track (a detector-only CLEAR-MOT: its MOTA
    is meaningless for identities, but FP, FN, precision and recall describe the detector)."""
    return from_points(detections.frame, np.arange(detections.size), *detections.centers().T)
