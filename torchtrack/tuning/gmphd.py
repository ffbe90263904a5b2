"""Tunable GM-PHD tracker (:class:`~torchtrack.filters.gmphd.tracker.GMPHDTracker`): ``p_D``, clutter
density ``κ``, measurement and process noise, ``p_S``, birth weight and birth spreads.

Items are windows of consecutive frames, :class:`FrameWindow` (measurement sets ``Z_k (M_k, 2)``, the
detector's velocities, and the truth for scoring). The tracker starts empty at each window; its first
``burn_in`` frames (while every target is still being born) run but do not count in the loss.

Losses:

- ``phd`` — the negative PHD predictive log-likelihood per frame (Poisson approximation; Mahler 2007,
  as returned by :meth:`GMPHD.update`)::

      log p(Z_k | Z_{1:k-1}) ≈ −λ_c − p_D Σ_j w_j⁻ + Σ_{z∈Z_k} log(κ + p_D Σ_j w_j⁻ N(z; H m_j⁻, S_j))

  with ``λ_c = κ · area`` (``model.filter.area`` must be set, otherwise ``κ`` would grow without bound).
- ``gospa`` — the soft GOSPA^p per frame (:func:`~torchtrack.tuning.losses.sinkhorn_gospa`) between
  the PHD's components (estimates of mass ``min(w_j, 1)``) and the truth positions.

Evaluation on held-out windows streams the tracker (as ``torchtrack track`` does) and scores CLEAR-MOT
(``threshold`` px) and the mean OSPA (cut-off ``ospa_c``, order 1) against the truth.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchtrack.errors import TorchtrackError
from torchtrack.filters.gmphd.tracker import GMPHDTracker
from torchtrack.tuning.kalman import psd_factor
from torchtrack.tuning.losses import sinkhorn_gospa
from torchtrack.tuning.parameters import get_values, plain
from torchtrack.tuning.registry import Tunable, TuneData, check_keys

DATA_KEYS = ("wpafb", "truth", "simulate_truth", "detections", "detections_file", "train_frames",
             "held_out_frames", "held_out_draws", "window", "burn_in", "threshold", "ospa_c", "gospa_c")
DET_KEYS = ("pd", "sigma", "clutter", "velocity_sigma", "image_size")
TRUTH_KEYS = ("targets", "frames", "q", "speed", "image_size")


def frame_span(span: Any, key: str) -> tuple[int, int]:
    """``[first, last]`` frame numbers of ``data.<key>`` as ints; a clear error otherwise."""
    if not (isinstance(span, (list, tuple)) and len(span) == 2
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in span)
            and int(span[0]) <= int(span[1])):
        raise TorchtrackError(f"data.{key} must be [first, last] frame numbers"
                              f"{' or a list of such spans' if key == 'train_frames' else ''}; got {span!r}")
    return int(span[0]), int(span[1])


def train_spans(spans: Any) -> list[tuple[int, int]]:
    """``data.train_frames``: one span or several (e.g. the frames either side of a held-out block)."""
    if not (isinstance(spans, (list, tuple)) and spans and all(isinstance(s, (list, tuple)) for s in spans)):
        spans = [spans]
    return [frame_span(s, "train_frames") for s in spans]


class FrameWindow(NamedTuple):
    """Consecutive frames: numbers ``(T,)``, measurement sets ``z[t] (M_t, 2)``, velocities (or None),
    and the truth of those frames (:class:`~torchtrack.io.mot.MOTData`, may be None)."""

    frames: list[int]
    z: list[Tensor]
    velocity: list[Tensor | None]
    truth: Any


def simulate_truth(cfg: Mapping[str, Any], generator: torch.Generator):
    """Targets following the tracker's own nearly-constant-velocity model (CWNA, spectral density ``q``)
    for the whole sequence: positions uniform over ``image_size``, velocities ``N(0, speed² I)``, frames
    ``1..frames``; returns MOTChallenge-style truth (ids from 1)."""
    from torchtrack.io.mot import from_points
    from torchtrack.models import ConstantVelocity

    check_keys(cfg, TRUTH_KEYS, "data.simulate_truth")
    N, K = int(cfg.get("targets", 20)), int(cfg.get("frames", 200))
    if N < 1 or K < 1:
        raise TorchtrackError(f"data.simulate_truth needs targets >= 1 and frames >= 1; got {N}, {K}")
    W, H = (float(v) for v in cfg.get("image_size", [500.0, 500.0]))
    f64 = torch.float64
    with torch.no_grad():
        cv = ConstantVelocity(2, float(cfg.get("q", 0.1))).double()
        F = cv.transition_matrix(1.0)
        A = psd_factor(cv.process_noise(1.0))
        x = torch.cat([torch.rand(N, 2, generator=generator, dtype=f64) * torch.tensor([W, H], dtype=f64),
                       torch.randn(N, 2, generator=generator, dtype=f64) * float(cfg.get("speed", 2.0))], 1)
        pos = []
        for _ in range(K):
            pos.append(x[:, :2].clone())
            x = x @ F.T + torch.randn(N, 4, generator=generator, dtype=f64) @ A.T
        p = torch.stack(pos).numpy()                                               # (K, N, 2)
    frames = np.repeat(np.arange(1, K + 1), N)
    ids = np.tile(np.arange(1, N + 1), K)
    return from_points(frames, ids, p[..., 0].reshape(-1), p[..., 1].reshape(-1))


@contextlib.contextmanager
def quiet_caps() -> Iterator[None]:
    """Silence the GM-PHD's per-frame "cap hit" warnings (training runs many mis-specified frames);
    the hits are still counted in ``GMPHD.cap_hits`` and reported by :meth:`GMPHDTunable.evaluate`."""
    logger = logging.getLogger("torchtrack.filters.gmphd.filter")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(level)


class GMPHDTunable(Tunable):
    """The enhanced labelled GM-PHD tracker (or ``tracker: labelled-gmphd``, the baseline)."""

    name = "gmphd"
    losses = ("phd", "bernoulli", "gospa")

    def __init__(self, options: Mapping[str, Any] | None = None):
        super().__init__(options)
        self.variant = self.options.get("tracker", "gmphd")
        if self.variant not in ("gmphd", "labelled-gmphd"):
            raise TorchtrackError(f"model.tracker must be 'gmphd' or 'labelled-gmphd'; got {self.variant!r}")
        self.burn_in = 0
        self.threshold, self.ospa_c, self.gospa_c = 10.0, 10.0, 10.0

    def tracker_config(self) -> dict:
        """The tracker's own options (``torchtrack track --config`` section), without ``tracker``."""
        return {k: v for k, v in self.options.items() if k != "tracker"}

    def build(self) -> GMPHDTracker:
        from torchtrack.filters.trackers.options import tracker_config

        return GMPHDTracker.from_config(tracker_config(self.variant, self.tracker_config()))   # with-velocity options

    # -- data -------------------------------------------------------------------------------------
    def load_data(self, config: Mapping[str, Any], generator: torch.Generator) -> TuneData:
        from torchtrack.io.mot import read_mot

        check_keys(config, DATA_KEYS, "data (gmphd)")
        self.burn_in = int(config.get("burn_in", 5))
        self.threshold = float(config.get("threshold", 10.0))
        self.ospa_c = float(config.get("ospa_c", 10.0))
        self.gospa_c = float(config.get("gospa_c", 10.0))
        if sum(k in config for k in ("wpafb", "truth", "simulate_truth")) != 1:
            raise TorchtrackError("data (gmphd) needs exactly one of 'wpafb' (the data set's name, wpafb, or the "
                                  "truth CSV or its folder), "
                                  "'truth' (a MOTChallenge file) or 'simulate_truth'")
        if "wpafb" in config:
            from torchtrack.io.datasets import wpafb_truth_csv
            from torchtrack.io.wpafb import read_wpafb_csv

            truth = read_wpafb_csv(wpafb_truth_csv(config["wpafb"]))
        elif "truth" in config:
            truth = read_mot(Path(config["truth"]))
        else:
            truth = simulate_truth(config["simulate_truth"] or {}, generator)
        if ("detections" in config) == ("detections_file" in config):
            raise TorchtrackError("data (gmphd) needs exactly one of 'detections' (simulation settings) or "
                                  "'detections_file'")
        if "detections" in config:
            det = self._simulate(truth, config["detections"] or {}, generator)
        else:
            det = read_mot(Path(config["detections_file"]))
        window = int(config.get("window", 50))
        if window <= self.burn_in:
            raise TorchtrackError(f"data.window ({window}) must be larger than data.burn_in ({self.burn_in})")
        first, last = int(truth.frame.min()), int(truth.frame.max())
        spans = train_spans(config.get("train_frames", [first, last]))
        train = [w for span in spans for w in self._windows(det, truth, span, window, "train_frames")]
        held = config.get("held_out_frames")
        # held-out frames form one window each range (scored by streaming the tracker through it)
        held_out = self._windows(det, truth, held, None, "held_out_frames") if held else []
        return TuneData(train, held_out, self._draws(config, truth))

    def _draws(self, config: Mapping[str, Any], truth) -> dict[int, list[FrameWindow]]:
        """``held_out_draws: [seed, ...]``: the held-out frames with detections simulated anew from each
        seed (the same settings, the same truth), so that a held-out score is not one draw's luck."""
        seeds = config.get("held_out_draws")
        if seeds is None:
            return {}
        if not (isinstance(seeds, list) and seeds and len(set(seeds)) == len(seeds)
                and all(isinstance(s, int) and not isinstance(s, bool) for s in seeds)):
            raise TorchtrackError(f"data.held_out_draws must be a non-empty list of distinct integer seeds; got "
                                  f"{seeds!r}")
        if "detections" not in config or not config.get("held_out_frames"):
            raise TorchtrackError("data.held_out_draws needs simulated 'detections' and 'held_out_frames'")
        return {s: self._windows(self._simulate(truth, config["detections"] or {}, torch.Generator().manual_seed(s)),
                                 truth, config["held_out_frames"], None, "held_out_frames") for s in seeds}

    def _simulate(self, truth, cfg: Mapping[str, Any], generator: torch.Generator):
        from torchtrack.sim.detections import default_image_size, simulate_detections

        check_keys(cfg, DET_KEYS, "data.detections")
        size = cfg.get("image_size") or default_image_size(truth)
        return simulate_detections(truth, float(cfg.get("pd", 0.9)), float(cfg.get("sigma", 1.0)),
                                   float(cfg.get("clutter", 0.0)), tuple(size), cfg.get("velocity_sigma"),
                                   generator).detections

    def _windows(self, det, truth, span, window: int | None, key: str) -> list[FrameWindow]:
        lo, hi = frame_span(span, key)
        frames = np.arange(lo, hi + 1)
        centres, vel = det.centers(), det.velocity()
        idx = det.split(frames)
        tidx = truth.split(frames)
        length = window or len(frames)
        out = []
        for s in range(0, len(frames), length):
            sl = slice(s, s + length)
            if len(frames[sl]) <= self.burn_in:
                continue
            rows = np.concatenate(tidx[sl]) if tidx[sl] else np.zeros(0, np.int64)
            out.append(FrameWindow([int(f) for f in frames[sl]],
                                   [torch.from_numpy(centres[i]) for i in idx[sl]],
                                   [None if vel is None else torch.from_numpy(vel[i]) for i in idx[sl]],
                                   truth.select(rows)))
        return out

    def truth(self, data_config: Mapping[str, Any]) -> dict[str, Any]:
        det = data_config.get("detections")
        if not isinstance(det, Mapping):
            return {}
        out = {"phd.p_detection": float(det.get("pd", 0.9)), "phd.measurement.sigma": float(det.get("sigma", 1.0))}
        sim = data_config.get("simulate_truth")
        if isinstance(sim, Mapping):
            out["phd.motion.q"] = float(sim.get("q", 0.1))
        area = (self.options.get("filter") or {}).get("area")
        if area and "clutter" in det:
            out["phd.clutter_density"] = float(det["clutter"]) / float(area)
            out["clutter_rate"] = float(det["clutter"])
        return out

    def derived(self, module: GMPHDTracker) -> dict[str, Any]:
        """``clutter_rate = κ · area`` (false detections per frame)."""
        if module.phd.area is None:
            return {}
        with torch.no_grad():
            return {"clutter_rate": float(module.phd.clutter_density() * module.phd.area)}

    def export(self, module: GMPHDTracker) -> tuple[str, dict]:
        """``track.yaml``: the tracker options with the fitted values, for ``torchtrack track --config``."""
        opts = {k: dict(v) if isinstance(v, Mapping) else v for k, v in self.tracker_config().items()}
        filt, birth = dict(opts.get("filter") or {}), dict(opts.get("birth") or {})
        for name, v in plain(get_values(module)).items():
            section, _, key = name.partition(".")
            if section == "phd":
                filt[{"motion.q": "q", "measurement.sigma": "sigma"}.get(key, key)] = v
            elif section == "birth":
                birth[key] = v
        opts["filter"], opts["birth"] = filt, birth
        return "track.yaml", {self.variant: opts}

    # -- losses -----------------------------------------------------------------------------------
    def _run(self, module: GMPHDTracker, item: FrameWindow, loss: str) -> tuple[Tensor, int]:
        """Summed ``loss`` over the counted frames of one window, and their number."""
        want_gospa = loss == "gospa"
        state, memory = module.initial()
        vmap = module.birth.new_velocity_map(module.dtype)
        mats = module.phd.matrices(1.0)
        total = torch.zeros((), dtype=module.dtype)
        counted = 0
        truth_split = item.truth.split(item.frames) if want_gospa else None
        prev = None
        for t, (frame, z, v) in enumerate(zip(item.frames, item.z, item.velocity)):
            dt = 1.0 if prev is None else float(frame - prev)
            prev = frame
            if dt != 1.0:
                mats = module.phd.matrices(dt)
            res = module.advance(state, memory, z.to(module.dtype), None if v is None else v.to(module.dtype),
                                 mats, vmap, dt, bernoulli=loss == "bernoulli")
            state, memory = res.state, res.memory
            if t < self.burn_in:
                continue
            counted += 1
            if want_gospa:
                y = torch.as_tensor(item.truth.centers()[truth_split[t]], dtype=module.dtype)
                w = torch.where(state.mask, state.log_weight.exp().clamp(max=1.0), torch.zeros_like(state.log_weight))
                total = total + sinkhorn_gospa(state.mean[:, :2], y, est_weight=w, c=self.gospa_c)
            else:
                total = total - res.log_likelihood
        return total, counted

    def loss(self, module: GMPHDTracker, items: Sequence[FrameWindow], loss: str) -> Tensor:
        if loss in ("phd", "bernoulli") and module.phd.area is None:
            raise TorchtrackError("the PHD likelihood needs model.filter.area (the surveillance area in px²) so "
                                  "that the clutter rate is identifiable")
        total, count = torch.zeros((), dtype=module.dtype), 0
        with quiet_caps():
            for item in items:
                s, c = self._run(module, item, loss)
                total, count = total + s, count + c
        return total / max(count, 1)

    def item_frames(self, item: FrameWindow) -> int:
        return len(item.frames)

    def score(self, module: GMPHDTracker, items: Sequence[FrameWindow], metric: str) -> dict[str, float]:
        """:meth:`evaluate`, without the OSPA (a tenth of the time) unless ``metric`` is ``OSPA``."""
        return self.evaluate(module, items, ospa=metric == "OSPA")

    def evaluate(self, module: GMPHDTracker, items: Sequence[FrameWindow], ospa: bool = True) -> dict[str, float]:
        """CLEAR-MOT (MOTA, IDS, FP, FN) and (``ospa``) mean OSPA of the streaming tracker over the windows.

        Windows that continue one another (the training windows of one ``train_frames`` span) are
        streamed as one sequence through the stream of ``torchtrack track --detections``
        (:func:`torchtrack.pipeline.replay.run_tracker`); the tracker restarts only where the frames jump,
        and each restart gets its own identities, the truth's too (no identity switch is counted across a
        jump; frames are not offset, so windows over the same frames share them)."""
        from torchtrack.io.mot import concat_mot
        from torchtrack.metrics.clear_mot import clear_mot
        from torchtrack.metrics.ospa import mot_ospa_gospa
        from torchtrack.pipeline.detection_file import detection_file_config
        from torchtrack.pipeline.frame_detections import FrameDetections
        from torchtrack.pipeline.replay import run_tracker
        from torchtrack.pipeline.sequences import concatenate

        stream = detection_file_config(threshold=self.threshold).replace(dtype=str(module.dtype).split(".")[-1])
        runs: list[list[FrameWindow]] = []
        for item in items:
            if not runs or item.frames[0] != runs[-1][-1].frames[-1] + 1:
                runs.append([])
            runs[-1].append(item)
        caps = module.phd.cap_hits
        parts = []
        for run in runs:
            module.reset()
            frames = (FrameDetections.registered(f, z.detach().double().numpy(),
                                                 None if v is None else v.detach().double().numpy())
                      for item in run for f, z, v in zip(item.frames, item.z, item.velocity))
            with quiet_caps():
                tracks = run_tracker(module, stream, frames).tracks
            parts.append((concat_mot([w.truth for w in run]), tracks))
        module.reset()
        gt, pred = concatenate(parts, offset_frames=False)
        m = clear_mot(gt, pred, self.threshold)  # not metrics.table.score: a search needs no HOTA
        out = {k: float(m[k]) for k in ("MOTA", "MOTP", "IDF1", "FP", "FN", "IDS")}
        if ospa:
            _, o, _ = mot_ospa_gospa(gt, pred, c=self.ospa_c, p_ospa=1.0)
            out["OSPA"] = float(o[0].mean())
        out["cap_hits"] = float(module.phd.cap_hits - caps)
        return out
