"""Detection scores: precision, recall and F1 of detections within a radius of the truth (one-to-one
Hungarian matching per frame), and the mean velocity error of the matched detections."""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

from torchtrack.detector.decode import Detections
from torchtrack.errors import TorchtrackError
from torchtrack.geometry import apply_homography, warp_previous


def match(pred: np.ndarray, truth: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(i_pred, i_truth)`` of the one-to-one assignment minimising the summed distance among
    pairs closer than ``radius`` px. pred (N, 2), truth (M, 2)."""
    if len(pred) == 0 or len(truth) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    d = np.linalg.norm(pred[:, None, :] - truth[None, :, :], axis=2)
    cost = np.where(d <= radius, d, 1e6)
    i, j = linear_sum_assignment(cost)
    ok = d[i, j] <= radius
    return i[ok], j[ok]


@dataclass
class Scores:
    """Accumulated counts; ``care`` truth (e.g. moving vehicles) with the rest as don't-care."""

    radius: float = 10.0
    tp: int = 0
    fp: int = 0
    fn: int = 0
    frames: int = 0
    seconds: float = 0.0
    cpu_seconds: float = 0.0
    velocity_errors: list = field(default_factory=list)

    def add(self, det: Detections, truth_xy: np.ndarray, truth_velocity: np.ndarray | None = None,
            care: np.ndarray | None = None, counted: np.ndarray | None = None) -> None:
        """Score one frame. Detections matched to don't-care truth (``care`` False) count neither as
        true nor as false positives; unmatched don't-care truth is no miss; an unmatched detection is a
        false positive only where ``counted`` (per detection, default all: e.g. inside a scored region)."""
        pred = det.xy.numpy().astype(np.float64)
        care = np.ones(len(truth_xy), bool) if care is None else care
        i, j = match(pred, truth_xy, self.radius)
        unmatched = np.ones(len(pred), bool)
        unmatched[i] = False
        self.fp += int((unmatched if counted is None else unmatched & counted).sum())
        hit = care[j]
        self.tp += int(hit.sum())
        self.fn += int(care.sum() - hit.sum())
        self.frames += 1
        if truth_velocity is not None and len(i):
            tv = truth_velocity[j[hit]]
            pv = det.velocity.numpy()[i[hit]]
            known = ~np.isnan(tv).any(axis=1)
            self.velocity_errors += np.linalg.norm(pv[known] - tv[known], axis=1).tolist()

    def result(self) -> dict:
        p = self.tp / max(1, self.tp + self.fp)
        r = self.tp / max(1, self.tp + self.fn)
        f1 = 2 * p * r / max(1e-12, p + r)
        v = float(np.mean(self.velocity_errors)) if self.velocity_errors else float("nan")
        return {"precision": p, "recall": r, "f1": f1, "velocity_error_px": v, "frames": self.frames,
                "fps": self.frames / self.seconds if self.seconds > 0 else float("nan"),
                "fps_cpu_time": self.frames / self.cpu_seconds if self.cpu_seconds > 0 else float("nan"),
                "tp": self.tp, "fp": self.fp, "fn": self.fn}


PRIORS = ("stream", "truth", "empty")


def stream(detector, frames: Iterable[np.ndarray], scores_time: Scores | None = None,
           motions: Iterable[np.ndarray | None] | None = None,
           priors: Iterable[np.ndarray | None] | None = None):
    """Run ``detector.detect`` over a sequence, the prior of each frame being the previous detections
    (and their velocities, for the motion-continuity check, from the third frame on: as in the pipeline,
    the first frame's velocities, measured without a previous frame, are not passed on);
    yields :class:`Detections` per frame, adding the wall-clock and process CPU seconds of the calls to
    ``scores_time.seconds`` and ``scores_time.cpu_seconds`` (CPU time per frame, summed over threads,
    is what a dedicated core would take; wall time depends on the machine's load). With ``motions``
    (per frame the camera map from it to the previous frame, :func:`registered_motions`) the previous
    frame and detections are first mapped onto the current frame, as after the pipeline's registration
    (the warp is not timed: it belongs to registration). With ``priors`` (per frame the points ``(N, 2)``
    in the previous frame's pixels to use as its prior instead of the previous detections, e.g. the
    previous truth: what a perfect feedback would give) no velocities are passed on."""
    prev, prev_pts, prev_vel = None, None, None
    unset = itertools.repeat(None)
    for img, m, given in zip(frames, unset if motions is None else motions, unset if priors is None else priors):
        if prev is not None and given is not None:
            prev_pts = torch.as_tensor(np.asarray(given, np.float64).reshape(-1, 2)).float()
        if prev is not None and m is not None:
            prev = warp_previous(np.asarray(prev), m, img.shape, fill=np.asarray(img))
            prev_pts = torch.from_numpy(apply_homography(prev_pts.numpy(), np.linalg.inv(m))).float()
        t0, c0 = time.perf_counter(), time.process_time()
        det = detector.detect(img, prev, prev_pts, prev_velocity=prev_vel)
        if scores_time is not None:
            scores_time.seconds += time.perf_counter() - t0
            scores_time.cpu_seconds += time.process_time() - c0
        yield det
        # a first frame's velocities were measured without a previous frame: not a motion to continue
        prev, prev_pts, prev_vel = img, det.xy, det.velocity if prev is not None and priors is None else None


def moving_only(det: Detections, min_speed: float, camera: np.ndarray | None = None) -> Detections:
    """The detections whose predicted speed is at least ``min_speed`` px/frame; with ``camera`` (K, 2),
    the image motion a static point at each detection has (camera jitter), the speed over the ground
    ``|v - v_camera|``."""
    v = det.velocity if camera is None else det.velocity - torch.as_tensor(camera, dtype=det.velocity.dtype)
    fast = v.norm(dim=1) >= min_speed
    return Detections(det.xy[fast], det.score[fast], det.velocity[fast], det.mask[fast])


def registered_motions(homographies: Sequence[np.ndarray]) -> list[np.ndarray | None]:
    """Per frame ``k`` the camera map to frame ``k-1``, ``H_{k-1} H_k⁻¹``, from the true reference-to-frame
    homographies (``None`` for the first frame)."""
    return [None] + [np.asarray(a) @ np.linalg.inv(b) for a, b in zip(homographies[:-1], homographies[1:])]


def ground_velocity(xy: np.ndarray, velocity: np.ndarray, current_to_previous: np.ndarray) -> np.ndarray:
    """Velocity over the ground in the current frame's pixels, ``x_k − M⁻¹ x_{k−1}`` with
    ``x_{k−1} = x_k − velocity`` (image motion), ``M`` the camera map current -> previous: what a
    detector sees between the current frame and the previous one warped onto it."""
    return xy - apply_homography(xy - velocity, np.linalg.inv(current_to_previous))


def camera_velocity(xy: np.ndarray, current_to_previous: np.ndarray) -> np.ndarray:
    """Image motion ``x - M x`` of static ground points at ``xy`` (K, 2), ``M = H_{k-1} H_k⁻¹`` the camera map
    from the current frame to the previous one (:func:`registered_motions`)."""
    return xy - apply_homography(xy, current_to_previous)


def evaluate_frames(detector, video_frames, radius: float = 10.0, min_speed: float = 2.0,
                    prior: str = "stream") -> dict:
    """Scores on :class:`torchtrack.sim.video.VideoFrame` s of one or more sequences (a list of lists),
    with ``"moving"``: the detections predicted to move over the ground (their velocity less the camera
    jitter's image motion, known from the frames' homographies, as after the pipeline's registration) at
    ``min_speed`` px/frame or more against the moving truth, detections on parked vehicles being
    don't-care (frames after the first). A detector trained on registered pairs
    (``config.data.register``) sees the previous frame warped onto the current one by the true camera
    motion, and its velocities are scored against the velocity over the ground. ``prior``: the prior of
    each frame after the first is the previous frame's detections (``stream``, as in use), the previous
    frame's truth (``truth``: the detector given a perfect feedback, what a tracker feeding it could at
    best provide) or empty (``empty``: no feedback)."""
    if prior not in PRIORS:
        raise TorchtrackError(f"prior must be one of {', '.join(PRIORS)}; got {prior!r}")
    scores, moving = Scores(radius), Scores(radius)
    registered = _registered(detector)
    for seq in video_frames:
        motions = registered_motions([f.homography for f in seq])
        priors = None if prior == "stream" else [None] + [p.xy if prior == "truth" else np.zeros((0, 2))
                                                           for p in seq[:-1]]
        for f, m, det in zip(seq, motions, stream(detector, (f.image for f in seq), scores,
                                                  motions if registered else None, priors)):
            vel = None if m is None else ground_velocity(f.xy, f.velocity, m) if registered else f.velocity
            scores.add(det, f.xy, vel)
            if m is not None:
                cam = None if registered else camera_velocity(det.xy.numpy().astype(np.float64), m)
                moving.add(moving_only(det, min_speed, cam), f.xy, vel, care=f.moving)
    moving.seconds, moving.cpu_seconds = scores.seconds, scores.cpu_seconds
    return {**scores.result(), "moving": moving.result()}


@torch.inference_mode()
def evaluate_synthetic(detector, video_config, seeds: Iterable[int], radius: float = 10.0,
                       prior: str = "stream") -> dict:
    """Generate held-out sequences (one per seed) with ``video_config`` and score the detector
    (:func:`evaluate_frames`)."""
    from torchtrack.sim.video import generate_sequence

    seqs = [list(generate_sequence(video_config, torch.Generator().manual_seed(s))) for s in seeds]
    return evaluate_frames(detector, seqs, radius, prior=prior)


@torch.inference_mode()
def evaluate_cache(detector, cache, n_frames: int, radius: float = 10.0) -> dict:
    """Scores on the first ``n_frames`` frames of every sequence of a :class:`~detector.dataset.SequenceCache`."""
    scores = Scores(radius)
    n_frames = min(n_frames, cache.frames.shape[1])
    registered = _registered(detector)
    for s in range(cache.frames.shape[0]):
        imgs = [cache.frames[s, t].numpy() for t in range(n_frames)]
        motions = registered_motions(cache.homography[s, :n_frames].numpy())
        for t, det in enumerate(stream(detector, imgs, scores, motions if registered else None)):
            _, xy, vel = cache.truth(s, t)
            xy, vel = xy.numpy().astype(np.float64), vel.numpy().astype(np.float64)
            if t > 0 and registered:
                vel = ground_velocity(xy, vel, motions[t])
            scores.add(det, xy, vel if t > 0 else None)
    return scores.result()


def _registered(detector) -> bool:
    config = getattr(detector, "config", None)
    return bool(config is not None and config.data.register)
