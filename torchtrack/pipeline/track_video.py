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
4. **write** — each frame whose tracks became final (``output_lag`` frames later), mapped back into its
   frame by ``H_k⁻¹``, is appended to ``tracks.txt`` and flushed (an interrupted run leaves a file
   complete up to the last final frame), and the detections to ``detections.txt`` (frame coordinates,
   with velocities; the strong ones: the detector's output at its threshold);
5. **render** — the final frame goes to ``annotated.mp4`` (renamed from ``.partial.mp4`` at the end);
   the last ``output_lag`` images wait for it.

At the end, the tracks are scored against the truth (CLEAR-MOT, ``torchtrack.metrics.clear_mot``)
where given, and ``metrics.json`` gets the scores, the per-stage timings (registration, detection,
tracking, I/O, render) and the frames per second. ``metrics.json`` is written last, so a folder
holding it holds a complete run.
"""

from __future__ import annotations

import inspect
import json
import os
import time
import warnings
from collections import defaultdict
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import torch
from tqdm import tqdm

from torchtrack.detector import load_detector
from torchtrack.errors import TorchtrackError
from torchtrack.filters.multitarget import make_tracker
from torchtrack.io.frames import FrameSource, prefetch
from torchtrack.io.mot import MOTData, MOTWriter, from_points, read_mot
from torchtrack.io.video_writer import AnnotatedVideoWriter, apply_homography, save_png
from torchtrack.metrics import clear_mot
from torchtrack.pipeline.config import PipelineConfig
from torchtrack.pipeline.fixed_lag import LaggedFrame
from torchtrack.pipeline.registration import Registration, transfer_error, warp_previous
from torchtrack.pipeline.tracker_stream import TrackerStream, as_numpy


class StageTimer:
    """Accumulated wall-clock seconds per named stage."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[stage] += time.perf_counter() - t0


@contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Use ``n`` torch intra-op threads inside the block, then restore the previous number."""
    before = torch.get_num_threads()
    torch.set_num_threads(max(1, int(n)))
    try:
        yield
    finally:
        torch.set_num_threads(before)


def homography_jacobian(h: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Jacobians ``∂π(H p)/∂p (K, 2, 2)`` of the map ``p ↦ π(H [p; 1])`` at ``points (K, 2)``.

    With ``q = H [p; 1]`` and ``π(q) = q[:2] / q[2]``: ``J = (H[:2, :2] − π(q) H[2, :2]) / q[2]``.
    """
    p = np.asarray(points, np.float64).reshape(-1, 2)
    q2 = p @ h[2, :2] + h[2, 2]
    proj = apply_homography(p, h)
    return (h[None, :2, :2] - proj[:, :, None] * h[None, 2:3, :2]) / q2[:, None, None]


class FrameDetections(NamedTuple):
    """Detections of one frame: ``positions``/``velocities (K, 2)`` in reference coordinates, ``scores (K,)``,
    ``homography (3, 3)`` frame → reference; ``image_positions``/``image_velocities`` in frame coordinates
    (the detector's output); ``motion (K,)`` the motion evidence at each detection (:func:`motion_evidence`);
    ``strong (K,)`` whether it scored at least the detection threshold (the others are weak detections,
    decoded further down for :class:`~torchtrack.pipeline.tracker_stream.TrackerStream` to continue tracks);
    ``tones (K,)`` the grey level at each detection (:func:`grey_level`; None where not measured).
    On the first frame there is no previous frame: ``velocities`` are NaN (unknown) and ``motion`` is ``inf``,
    so that the moving-object gate passes everything and the trackers start without a velocity."""

    index: int
    homography: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray
    scores: np.ndarray
    image_positions: np.ndarray
    image_velocities: np.ndarray
    motion: np.ndarray
    strong: np.ndarray
    tones: np.ndarray | None = None

    def select(self, keep: np.ndarray) -> FrameDetections:
        """The detections where ``keep (K,)`` (a mask or indices)."""
        fields = ("positions", "velocities", "scores", "image_positions", "image_velocities", "motion", "strong")
        if self.tones is not None:
            fields += ("tones",)
        return self._replace(**{k: getattr(self, k)[keep] for k in fields})

    def moving(self, min_speed: float = 0.0, min_motion: float = 0.0) -> FrameDetections:
        """The detections with predicted speed ``>= min_speed`` px/frame (or unknown) and motion evidence
        ``>= min_motion``."""
        return self.select(~(np.hypot(self.velocities[:, 0], self.velocities[:, 1]) < min_speed)
                           & (self.motion >= min_motion))


MOTION_WINDOW = 5
"""Side (px) of the window over which :func:`motion_evidence` averages the frame difference."""


def motion_evidence(image: np.ndarray, previous: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Mean absolute grey-level difference between ``image`` and the ``previous`` frame registered onto it,
    over a ``MOTION_WINDOW``-px square at each of ``points (K, 2)`` (x, y): a classical change-detection cue
    (moving vehicles leave a difference of tens of grey levels, static structure only sensor noise and
    parallax). ``(K,)``."""
    diff = cv2.blur(cv2.absdiff(image, previous), (MOTION_WINDOW, MOTION_WINDOW))
    h, w = diff.shape
    x = np.clip(np.rint(points[:, 0]).astype(np.int64), 0, w - 1)
    y = np.clip(np.rint(points[:, 1]).astype(np.int64), 0, h - 1)
    return diff[y, x].astype(np.float64)


TONE_WINDOW = 3
"""Side (px) of the window over which :func:`grey_level` averages the frame."""


def grey_level(image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Mean grey level of ``image`` over a ``TONE_WINDOW``-px square at each of ``points (K, 2)`` (x, y): the
    tone of the vehicle detected there, the attribute the GM-PHD's ``tone_sigma`` compares between frames.
    ``(K,)``."""
    mean = cv2.blur(image, (TONE_WINDOW, TONE_WINDOW))
    h, w = mean.shape
    x = np.clip(np.rint(points[:, 0]).astype(np.int64), 0, w - 1)
    y = np.clip(np.rint(points[:, 1]).astype(np.int64), 0, h - 1)
    return mean[y, x].astype(np.float64)


class Detection:
    """Registration + detection of a frame stream (steps 1–2 of the module docstring).

    ``detector`` has ``detect(frame, prev_frame, prev_points)`` returning an object with ``xy (K, 2)``,
    ``score (K,)`` and ``velocity (K, 2)`` (:class:`torchtrack.detector.Detections`: frame pixel coordinates,
    velocities ``x_k − x_{k-1}`` in px/frame). A detector whose ``detect`` takes ``prev_velocity`` gets the
    previous detections' velocities too (its motion-continuity check). With ``threshold`` (our
    :class:`torchtrack.detector.Detector` only) it decodes down to that score, and with ``weak_threshold`` further
    down still: the detections between the two are marked weak (``FrameDetections.strong`` false). The prior
    heatmap of the next frame takes only the detections at or above the detector's own threshold, so that
    weak peaks do not feed themselves.
    """

    def __init__(self, detector, registration: Registration, timer: StageTimer,
                 threshold: float | None = None, weak_threshold: float | None = None) -> None:
        self.detector = detector
        self.registration = registration
        self.timer = timer
        if "threshold" not in inspect.signature(detector.detect).parameters:
            if threshold is not None:
                raise TorchtrackError("detection_threshold needs a detector whose detect() takes a threshold")
            weak_threshold = None  # a stand-in detector decodes at its own threshold only
        given = [t for t in (threshold, weak_threshold) if t is not None]
        self.decode_threshold = min(given) if given else None
        self.prior_threshold = detector.config.decode.threshold if given else -np.inf
        self.strong_threshold = self.prior_threshold if threshold is None else threshold
        self.prev_image: np.ndarray | None = None
        self.prev_h = np.eye(3)
        self.prior_ref = np.zeros((0, 2))  # prior points (reference coordinates) for the next frame
        self.prior_velocity: np.ndarray | None = None  # their velocities (px/frame), where they are detections
        self.takes_velocity = "prev_velocity" in inspect.signature(detector.detect).parameters

    def __call__(self, index: int, image: np.ndarray) -> FrameDetections:
        with self.timer("registration"):
            h = self.registration(image).homography
            h_inv = np.linalg.inv(h)
            if self.prev_image is None:
                prev = image
            else:
                # Previous frame resampled into the current frame: x_{k-1} = H_{k-1}^{-1} H_k x_k.
                prev = warp_previous(self.prev_image, np.linalg.inv(self.prev_h) @ h, image.shape, fill=image)
            prior = apply_homography(self.prior_ref, h_inv)
        with self.timer("detection"):
            extra = {} if self.decode_threshold is None else {"threshold": self.decode_threshold}
            if self.takes_velocity and self.prior_velocity is not None:
                extra["prev_velocity"] = self.prior_velocity
            found = self.detector.detect(image, prev, prior, **extra)
        pos, vel, scores = as_numpy(found.xy, (2,)), as_numpy(found.velocity, (2,)), as_numpy(found.score, ())
        with self.timer("registration"):
            pos_ref = apply_homography(pos, h)
            vel_ref = (homography_jacobian(h, pos) @ vel[:, :, None])[:, :, 0] if len(pos) else vel
            if self.prev_image is None:
                vel_ref, motion = np.full_like(vel_ref, np.nan), np.full(len(pos), np.inf)
            else:
                motion = motion_evidence(image, prev, pos)
        self.prev_image, self.prev_h = image, h
        prior = scores >= self.prior_threshold
        self.prior_ref = pos_ref[prior]
        self.prior_velocity = None if np.isnan(vel_ref).any() else vel[prior]
        return FrameDetections(index, h, pos_ref, vel_ref, scores, pos, vel, motion, scores >= self.strong_threshold,
                               grey_level(image, pos))


def replay_tracker(name: str, config: PipelineConfig, detections: list[FrameDetections]
                   ) -> Iterator[tuple[int, np.ndarray, np.ndarray, float]]:
    """Run tracker ``name`` (with ``config.options_for(name)``, ``config``'s moving-object gate, weak
    detections and output lag: :class:`TrackerStream`) on the kept detections of a pipeline run (no
    registration or detection again); yields per final frame its index, the ids, the positions in frame
    coordinates ``(N, 2)`` and the seconds spent in the tracker since the previous frame yielded."""
    stream = TrackerStream(make_tracker(name, config.options_for(name)), config)
    homography = {det.index: det.homography for det in detections}
    seconds = 0.0
    for det in [*detections, None]:
        t0 = time.perf_counter()
        final = stream.step(det)[2] if det is not None else stream.finish()
        seconds += time.perf_counter() - t0
        for frame in final:
            h_inv = np.linalg.inv(homography[frame.index])
            yield frame.index, frame.ids, apply_homography(frame.positions, h_inv), seconds
            seconds = 0.0


def rerun_tracker(name: str, config: PipelineConfig, detections: list[FrameDetections], out: Path
                  ) -> tuple[Path, float]:
    """:func:`replay_tracker` writing the tracks to ``out`` (MOTChallenge, frame coordinates); returns the
    file and the seconds spent in the tracker."""
    total = 0.0
    with MOTWriter(out) as writer:
        for index, ids, img, seconds in replay_tracker(name, config, detections):
            total += seconds
            writer.write_frame(index, ids, img[:, 0], img[:, 1])
    return out, total


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


def score(gt: MOTData, tracks: MOTData, threshold: float, ignore: np.ndarray | None = None) -> dict:
    """CLEAR-MOT of ``tracks`` against ``gt`` (centre distance ``threshold`` px; ``ignore (K,)`` marks
    don't-care truth lines, e.g. parked vehicles under the paper's moving-objects protocol)."""
    return {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in
            clear_mot(gt, tracks, threshold=threshold, ignore=ignore).items()}


def write_json_atomic(path: Path, payload: dict) -> None:
    """Write JSON to ``path`` through a temporary file and a rename (never a half-written file)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(payload, indent=2, default=float) + "\n")
    os.replace(tmp, path)


@dataclass
class PipelineResult:
    """What :func:`track_video` produced: the metrics dict (as in ``metrics.json``) and the files."""

    metrics: dict
    files: dict[str, Path] = field(default_factory=dict)
    detections: list[FrameDetections] = field(default_factory=list)


def track_video(source: FrameSource, out: str | Path, config: PipelineConfig | None = None, detector=None,
                gt: MOTData | None = None, gt_path: str = "gt.txt", ignore: np.ndarray | None = None,
                camera: np.ndarray | None = None,
                keep_detections: bool = False, progress: bool = True) -> PipelineResult:
    """Run the pipeline on ``source`` and write ``tracks.txt``, ``detections.txt``, ``annotated.mp4`` and
    ``metrics.json`` under ``out``.

    Args:
        source: frames (grey).
        config: :class:`PipelineConfig` (defaults: enhanced GM-PHD, LK registration).
        detector: object with ``detect`` (default: the shipped weights, ``detector.load_detector``).
        gt: truth (frame coordinates) to score against and draw; ``gt_path`` names it in errors;
            ``ignore (K,)`` bool over its lines marks don't-care objects (not drawn, not scored).
        camera: true homographies ``(T, 3, 3)`` reference → frame ``k`` of a synthetic sequence; when
            given, the registration error against them is measured and reported.
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
        detector = load_detector(cfg.detector_weights)
    timer = StageTimer()
    detection = Detection(detector, Registration(cfg.registration), timer, cfg.detection_threshold,
                          cfg.weak_threshold)
    stream = TrackerStream(make_tracker(cfg.tracker, cfg.options_for(cfg.tracker)), cfg)
    truth = _truth_by_frame(gt if ignore is None or gt is None else gt.select(~ignore))
    files = {"tracks": out / "tracks.txt", "detections": out / "detections.txt"}
    video = AnnotatedVideoWriter(out / "annotated.mp4", fps=cfg.video_fps, trail=cfg.trail, box=cfg.box,
                                 scale=cfg.scale) if cfg.video else None
    kept: list[FrameDetections] = []
    reg_errors: list[float] = []
    waiting: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # frames whose tracks are not final: image, H_k
    frames = 0
    t_start = time.perf_counter()
    scope = ExitStack()
    scope.enter_context(torch_threads(cfg.threads))
    bar = tqdm(total=n_frames or None, desc=f"track {cfg.tracker}", unit="frame", disable=not progress,
               leave=False)

    def emit(final: list[LaggedFrame], tracks_out: MOTWriter) -> None:
        """Write and draw the frames whose tracks became final (``output_lag`` frames back)."""
        for index, ids, pos_ref in final:
            image, h = waiting.pop(index)
            h_inv = np.linalg.inv(h)
            with timer("io"):
                pos_img = apply_homography(pos_ref, h_inv)
                tracks_out.write_frame(index, ids, pos_img[:, 0], pos_img[:, 1])
            if video is not None:
                with timer("render"):
                    t = truth.get(index)
                    drawn = video.write(image, ids, pos_ref, homography=h_inv,
                                        truth=None if t is None or not cfg.draw_truth else apply_homography(t, h),
                                        label=f"{cfg.tracker}  frame {index}")
                    if index in cfg.snapshots:
                        save_png(out / f"frame_{index:06d}.png", drawn)

    try:
        with MOTWriter(files["tracks"]) as tracks_out, MOTWriter(files["detections"]) as det_out:
            it = prefetch(source)
            while True:
                with timer("io"):
                    frame = next(it, None)
                if frame is None:
                    break
                det = detection(frame.index, frame.image)
                if camera is not None and frame.index <= len(camera):
                    # True frame k → frame 1 map: H_1 H_k^{-1} (the generator's H maps reference → frame).
                    true_h = camera[0] @ np.linalg.inv(camera[frame.index - 1])
                    reg_errors.append(float(np.median(transfer_error(det.homography, true_h, frame.image.shape))))
                waiting[frame.index] = (frame.image, det.homography)
                with timer("tracking"):
                    _, pos_ref, final = stream.step(det)
                if cfg.prior == "tracks":
                    detection.prior_ref, detection.prior_velocity = pos_ref, None
                with timer("io"):
                    found = det.select(det.strong)
                    det_out.write_frame(frame.index, np.full(len(found.scores), -1), found.image_positions[:, 0],
                                        found.image_positions[:, 1], conf=found.scores,
                                        vx=found.image_velocities[:, 0], vy=found.image_velocities[:, 1])
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
    finally:
        bar.close()
        scope.close()
    wall = time.perf_counter() - t_start
    if frames == 0:
        raise TorchtrackError(f"{source.path}: no frames")
    metrics: dict = {"source": str(source.path), "tracker": cfg.tracker, "frames": frames,
                     "frame_size": list(source.shape)}
    if gt is not None:
        check_truth_frames(gt, gt_path, frames)
        metrics["clear_mot"] = score(gt, read_mot(files["tracks"]), cfg.threshold, ignore)
        det_scores = score(gt, _detections_as_tracks(files["detections"]), cfg.threshold, ignore)
        metrics["detector"] = {k: det_scores[k] for k in ("TP", "FP", "FN", "precision", "recall", "MOTP")}
    duplicates = stream.duplicates
    if duplicates:
        warnings.warn(f"tracker {cfg.tracker} reported {duplicates} estimate(s) under an identity already "
                      "reported in the same frame; they were left out of tracks.txt", stacklevel=2)
        metrics["duplicate_identities_dropped"] = duplicates
    seconds = dict(timer.seconds)
    metrics["timings_s"] = {**seconds, "total": wall}
    metrics["fps"] = {"end_to_end": frames / wall,
                      **{f"{k}_only": frames / v for k, v in seconds.items() if v > 0}}
    if reg_errors:
        metrics["registration_error_px"] = {"median": float(np.median(reg_errors)),
                                            "p90": float(np.percentile(reg_errors, 90)),
                                            "max": float(np.max(reg_errors))}
    files["metrics"] = out / "metrics.json"
    write_json_atomic(files["metrics"], metrics)
    return PipelineResult(metrics, files, kept)


def _detections_as_tracks(path: Path) -> MOTData:
    """Detections scored as if each were its own one-frame track (a detector-only CLEAR-MOT: its MOTA
    is meaningless for identities, but FP, FN, precision and recall describe the detector)."""
    d = read_mot(path)
    return from_points(d.frame, np.arange(d.size), *d.centers().T)

