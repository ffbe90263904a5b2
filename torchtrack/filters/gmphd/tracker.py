"""The enhanced labelled GM-PHD tracker of Aguilar, Ortner & Zerubia (2023): GM-PHD (section 2.2),
label fix (2.3), adaptive birth with velocity map and detector-velocity initialisation (2.4).

One frame ``k`` (:meth:`GMPHDTracker.advance`)::

    predict (eq. 3)  →  birth measurements Z_k^b (eq. 4, against the predicted components)
    →  update with Z_k (and the detector's velocities, with ``velocity_sigma``)
    →  prune, merge (established labels win), cap (sized from the measurements and live labels)  →  extract (w > ½)
    →  label fix (2.3)  →  coasting  →  label hand-over  →  velocity map ← settled estimates
    →  births from Z_k^b (eq. 5–6) join the mixture for k+1

With the detections' grey levels and ``tone_sigma``, the update weighs each (component, detection) pair by
how well the detection's tone matches the component's label's, and the hand-over by the same
(:mod:`torchtrack.filters.gmphd.tone`).

Coasting, the hand-over, the merge priority, the velocity and the tone in the update are this project's extensions
(see ``docs/gmphd.md``); each can be switched off. With ``label_fix=False``, ``handover_frames=0``,
``coast_threshold=None``, ``use_velocity_map=False``, ``use_detector_velocity=False`` and no
``velocity_sigma`` (position-only update) this is the plain
labelled GM-PHD of Panta, Clark & Vo (2009) with measurement-driven birth (the paper's baseline), which
reports one estimate per label (the highest weight).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import NamedTuple

import torch
from torch import Tensor, nn

from torchtrack.errors import TorchtrackError
from torchtrack.filters.gmphd.birth import AdaptiveBirth, BirthConstants, VelocityMap
from torchtrack.filters.gmphd.existence import LabelExistence, bernoulli_log_likelihood, label_groups, no_existence
from torchtrack.filters.gmphd.filter import (
    GMPHD,
    SCENE_COMPONENTS,
    Matrices,
    MixtureState,
    as_rows,
    concat,
    empty_mixture,
    labels_in,
)
from torchtrack.filters.gmphd.labels import (
    LostLabels,
    TentativeLabels,
    best_per_label,
    confirm_labels,
    label_fix,
    label_handover,
    no_lost_labels,
    no_tentative_labels,
    relabel,
    update_lost,
)
from torchtrack.filters.gmphd.tone import (
    TONE_MATCH_DISTANCE,
    LabelTones,
    add_births,
    lookup,
    no_label_tones,
    tone_log_ratio,
    update_tones,
)
from torchtrack.filters.trackers.options import GMPHDConfig, tracker_config
from torchtrack.filters.trackers.protocol import frame_step


class TrackerMemory(NamedTuple):
    """Everything carried from frame to frame besides the mixture (no gradient)."""

    next_label: int
    prev_label: Tensor    # (E,) labels reported at the previous frame
    prev_pos: Tensor      # (E, 2) their positions
    prev_vel: Tensor      # (E, 2) their velocities
    lost: LostLabels      # labels reported recently but not at the previous frame
    tentative: TentativeLabels        # new labels extracted but not yet reported
    tones: LabelTones                 # grey level of each label's vehicle (``tone_sigma``)
    existence: LabelExistence         # Bernoulli existence per label (the ``bernoulli`` likelihood)


class StepResult(NamedTuple):
    state: MixtureState   # mixture carried to the next frame (posterior + births)
    memory: TrackerMemory
    ids: Tensor           # (E,) labels of the reported targets
    positions: Tensor     # (E, 2)
    velocities: Tensor    # (E, 2)
    log_likelihood: Tensor | None  # () PHD predictive log-likelihood of the frame's measurements (None: not asked)
    pending: Tensor       # (T, 2) positions of new labels extracted now but not yet reported (confirm_new)


class GMPHDTracker(nn.Module):
    """Streaming labelled GM-PHD tracker; ``step`` implements the common tracker interface of
    :mod:`torchtrack.filters.trackers.protocol` and ``log_likelihood`` the differentiable training loss.

    Args:
        phd: the :class:`GMPHD` recursion (its parameters: ``p_S, p_D, κ, Q, R``; default: ``options.filter``'s).
        birth: the :class:`AdaptiveBirth` (parameters: birth weight and covariance; default: ``options.birth``'s).
        options: :class:`~torchtrack.filters.trackers.options.GMPHDConfig` (meaning and defaults there): the label
            fix, coasting, hand-over, confirmation and tone options, and ``dtype``, the floating dtype of the
            streaming state (float32 is fast, float64 accurate).
    """

    def __init__(self, phd: GMPHD | None = None, birth: AdaptiveBirth | None = None,
                 options: GMPHDConfig | None = None):
        super().__init__()
        o = self.options = options if options is not None else GMPHDConfig()
        self.phd = phd if phd is not None else GMPHD(options=o.filter)
        self.birth = birth if birth is not None else AdaptiveBirth(o.birth)
        frames = 2 if o.confirm_new is True else 1 if o.confirm_new is False else o.confirm_new
        if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
            raise TorchtrackError("confirm_new must be true, false or a whole number of frames >= 1; "
                                  f"got {o.confirm_new!r}")
        if isinstance(o.confirm_misses, bool) or not isinstance(o.confirm_misses, int):
            raise TorchtrackError(f"confirm_misses must be a whole number of frames >= 0; got {o.confirm_misses!r}")
        self.confirm_frames = frames
        self.dtype = getattr(torch, o.dtype)
        self.to(self.dtype)
        self.reset()

    @classmethod
    def from_config(cls, config: GMPHDConfig | Mapping | None = None) -> GMPHDTracker:
        """Build from a :class:`~torchtrack.filters.trackers.options.GMPHDConfig` (or a mapping of the keys to
        change from its defaults, the ``gmphd`` section of ``configs/gmphd.yaml``; None: the defaults). The
        options for detections with velocities are used; :func:`~torchtrack.filters.gmphd.presets.enhanced_gmphd`
        also follows a positions-only input."""
        return cls(options=tracker_config("gmphd", config))

    @property
    def device(self) -> torch.device:
        """Where the parameters and the streaming state live: moved by ``.to(device)``, and a stream starts on
        the device of its first frame's detections."""
        return next(self.parameters()).device

    @property
    def tone_sigma(self) -> float | None:
        """``σ_t`` of the detections' grey levels (None: tones unused)."""
        return self.options.tone_sigma

    # ------------------------------------------------------------------ functional core
    def initial(self) -> tuple[MixtureState, TrackerMemory]:
        """An empty mixture and empty memory."""
        kw = {"dtype": self.dtype, "device": self.device}
        empty = torch.empty(0, dtype=torch.long, device=kw["device"])
        e2 = torch.empty(0, 2, **kw)
        return (empty_mixture(self.phd.state_dim, **kw),
                TrackerMemory(1, empty, e2, e2, no_lost_labels(**kw), no_tentative_labels(kw["device"]),
                              no_label_tones(**kw), no_existence(**kw)))

    def advance(self, state: MixtureState, memory: TrackerMemory, z: Tensor, velocity: Tensor | None,
                mats: Matrices, vmap: VelocityMap | None = None, dt: float = 1.0,
                birth_consts: BirthConstants | None = None, likelihood: bool = True,
                tone: Tensor | None = None, bernoulli: bool = False) -> StepResult:
        """One frame of the tracker (see the module docstring); ``z (M, 2)``, ``velocity (M, 2)`` or None,
        ``tone (M,)`` the detections' grey levels or None (used with ``tone_sigma``). With ``bernoulli``
        the frame's log-likelihood is the Bernoulli-per-label one (:mod:`torchtrack.filters.gmphd.existence`)
        instead of the PHD's.

        The label fix compares each hypothesis with its label's previous estimate moved on by its own
        velocity, ``p̂_{k−1} + v̂_{k−1} dt`` (the position the label is expected at now). With
        ``likelihood=False`` the result's ``log_likelihood`` is None (not computed).
        """
        phd, birth, o = self.phd, self.birth, self.options
        pred = phd.predict(state, mats)
        use_tone = tone is not None and o.tone_sigma is not None
        is_birth = birth.birth_measurements(pred.mean[:, :2], pred.log_weight, z)
        pair = None
        if use_tone:
            component_tone, detection_tone = lookup(memory.tones, pred.label), tone.to(z.dtype)

            def pair(jj: Tensor, kk: Tensor) -> Tensor:
                return tone_log_ratio(component_tone.index_select(0, jj), detection_tone.index_select(0, kk),
                                      o.tone_sigma, o.tone_outlier)
        groups = label_groups(pred) if likelihood and bernoulli else None
        post, info = phd.update(pred, z, mats, velocity=velocity, likelihood=likelihood, pair_loglik=pair,
                                label_index=None if groups is None else (groups.inverse, groups.labels.shape[0]))
        log_lik, existence = info.log_likelihood, memory.existence
        if groups is not None:
            with_velocity = velocity is not None and mats.R_velocity is not None
            log_lik, existence = bernoulli_log_likelihood(existence, groups, info.label_support, mats, z.shape[0],
                                                          with_velocity, phd.area)
        labels = pred.size     # live labels at most; counted (a unique) only where the cap could leave its floor
        if SCENE_COMPONENTS * (z.shape[0] + labels) > phd.options.capacity:
            labels = int(torch.unique(pred.label).numel())
        capacity = phd.capacity_for(z.shape[0], labels)
        post = phd.reduce(post, memory.prev_label if o.label_fix and o.merge_priority else None, capacity)
        est = phd.extract(post)
        next_label = memory.next_label
        if o.label_fix:
            expected = memory.prev_pos + memory.prev_vel * dt
            post, next_label = label_fix(post, est, memory.prev_label, expected, next_label,
                                         min_separation=o.fix_separation)
        sel = best_per_label(post, est)
        if o.label_fix and o.coast_threshold is not None:
            coast = (~est & (post.log_weight > math.log(o.coast_threshold))
                     & labels_in(post.label, memory.prev_label)
                     & ~labels_in(post.label, post.label.index_select(0, sel)))
            sel = torch.cat([sel, best_per_label(post, coast)])
        ids = post.label.index_select(0, sel)
        mean = post.mean.index_select(0, sel)
        pos, vel = mean[:, :2], mean[:, 2:4]
        lost = memory.lost
        if o.handover_frames > 0:
            tone_of = (lambda lab: lookup(memory.tones, lab)) if use_tone else None
            handed = label_handover(ids, pos.detach(), memory.prev_label, memory.prev_pos, memory.prev_vel, lost,
                                    o.handover_distance, dt, tone_of,
                                    o.tone_handover_gap * o.tone_sigma if use_tone else float("inf"))
            post = relabel(post, ids, handed)
            ids = handed
            lost_before = lost
            lost = update_lost(lost, memory.prev_label, memory.prev_pos, memory.prev_vel, ids, o.handover_frames)
        tones = memory.tones
        if use_tone:
            tones = update_tones(tones, ids, pos.detach(), z, tone, o.tone_rate, TONE_MATCH_DISTANCE,
                                 torch.cat([post.label, lost.label]))
        tentative = memory.tentative
        pending = pos[:0].detach()
        if self.confirm_frames > 1:
            known = labels_in(ids, memory.prev_label)
            if o.handover_frames > 0:
                known = known | labels_in(ids, lost_before.label)
            report, tentative = confirm_labels(ids, known, tentative, post.label, self.confirm_frames,
                                               o.confirm_misses)
            pending = pos.index_select(0, as_rows(~report)).detach()
            report = as_rows(report)
            sel, ids, pos, vel = (x.index_select(0, report) for x in (sel, ids, pos, vel))
        pos_d, vel_d = pos.detach(), vel.detach()
        if vmap is not None:
            cov = post.cov.detach().index_select(0, sel)
            settled = as_rows((cov[:, 2, 2] + cov[:, 3, 3]) < o.settled_velocity_var)
            vmap.update(pos_d.index_select(0, settled), vel_d.index_select(0, settled))
        is_birth = as_rows(is_birth)
        zb = z.index_select(0, is_birth)
        vb = velocity.index_select(0, is_birth) if velocity is not None else None
        b_mean, b_std, b_logw = birth.forward(zb, vb, vmap, birth_consts)
        B = int(zb.shape[0])
        b_label = torch.arange(next_label, next_label + B, dtype=torch.long, device=z.device)
        births = MixtureState(b_logw, b_mean, torch.diag_embed(b_std.pow(2)), b_label,       # N(mean, diag(std²))
                              torch.ones(B, dtype=torch.bool, device=z.device))
        if use_tone and B:
            tones = add_births(tones, b_label, tone.index_select(0, is_birth))
        new_state = phd.cap(concat(post, births), capacity)
        # labels carry no gradient
        new_memory = TrackerMemory(next_label + B, ids, pos_d, vel_d, lost, tentative, tones, existence)
        return StepResult(new_state, new_memory, ids, pos, vel, log_lik, pending)

    def log_likelihood(self, measurements: list[Tensor], velocities: list[Tensor | None] | None = None,
                       dt: float = 1.0) -> Tensor:
        """Per-frame PHD predictive log-likelihoods ``(T,)`` of a sequence of measurement sets ``(M_t, 2)``;
        differentiable with respect to every parameter of ``phd`` and ``birth`` (the training loss of
        ``torchtrack tune``)."""
        state, memory = self.initial()
        vmap = self.birth.new_velocity_map(self.dtype, self.device)
        if self.phd.state_dim != 4:
            raise TorchtrackError("GMPHDTracker needs a 2-D constant-velocity state [x, y, vx, vy]")
        mats = self.phd.matrices(dt)
        consts = self.birth.constants()
        out = []
        for t, z in enumerate(measurements):
            v = velocities[t] if velocities is not None else None
            v = None if v is None else v.to(self.dtype)
            res = self.advance(state, memory, z.to(self.dtype), v, mats, vmap, dt, consts)
            state, memory = res.state, res.memory
            out.append(res.log_likelihood)
        return torch.stack(out) if out else torch.zeros(0, dtype=self.dtype, device=self.device)

    # ------------------------------------------------------------------ streaming interface
    def reset(self) -> None:
        """Forget all tracks (labels restart at 1)."""
        state, memory = self.initial()
        self._stream = _Stream(state, memory, self.birth.new_velocity_map(self.dtype, self.device),
                               pending=torch.empty(0, 2, dtype=self.dtype, device=self.device))

    def take_stream(self, other: GMPHDTracker) -> None:
        """Continue ``other``'s stream with this tracker's options: its mixture, labels and their memory, last
        frame and pending labels, and its velocity map where both trackers keep one (the per-frame switch of
        :class:`~torchtrack.filters.gmphd.input_aware.InputAwareGMPHD`; both must have the same ``dtype``). This
        tracker moves to ``other``'s device."""
        self.to(other.device)
        mine, theirs = self._stream, other._stream
        mine.state, mine.memory, mine.last_frame, mine.pending = (theirs.state, theirs.memory, theirs.last_frame,
                                                                  theirs.pending)
        if mine.vmap is not None and theirs.vmap is not None:
            mine.vmap = theirs.vmap

    @property
    def state(self) -> MixtureState:
        """The current mixture (posterior of the last frame plus the births for the next)."""
        return self._stream.state

    @property
    def pending_positions(self) -> Tensor:
        """``(T, 2)`` positions of the new labels extracted at the last frame but not yet reported (waiting for
        their confirmation, ``confirm_new``)."""
        return self._stream.pending

    @property
    def cap_hits(self) -> int:
        """How many times the component cap was hit (each also logged as a warning)."""
        return self.phd.cap_hits

    def step(self, frame: int, positions: Tensor, velocities: Tensor | None = None,
             tones: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Process frame ``frame`` with detections ``positions (K, 2)`` (and the detector's ``velocities
        (K, 2)`` in px/frame, or None; their grey levels ``tones (K,)``, or None). Returns the reported
        ``ids (E,)`` and ``positions (E, 2)`` on the tracker's device (that of the stream's first detections)."""
        positions = torch.as_tensor(positions)
        if self._stream.last_frame is None and positions.device != self.device:
            self.to(positions.device)
            self.reset()
        s = self._stream
        kw = {"dtype": self.dtype, "device": s.pending.device}   # the stream's device (no walk of the parameters)
        z = torch.as_tensor(positions, **kw).reshape(-1, 2)
        v = None if velocities is None else torch.as_tensor(velocities, **kw).reshape(-1, 2)
        t = None if tones is None else torch.as_tensor(tones, **kw).reshape(-1)
        dt = frame_step(s.last_frame, frame)
        with torch.inference_mode():
            mats = s.mats.get(dt)
            if mats is None:
                mats = s.mats[dt] = self.phd.matrices(dt)
            if s.birth_consts is None:
                s.birth_consts = self.birth.constants()
            res = self.advance(s.state, s.memory, z, v, mats, s.vmap, dt, s.birth_consts, likelihood=False, tone=t)
        s.state, s.memory, s.last_frame, s.pending = res.state, res.memory, frame, res.pending
        return res.ids, res.positions


@dataclass
class _Stream:
    """What :meth:`GMPHDTracker.step` carries between frames (a plain object: an ``nn.Module`` attribute
    costs microseconds per assignment, a noticeable part of a small frame)."""

    state: MixtureState
    memory: TrackerMemory
    vmap: VelocityMap | None
    last_frame: int | None = None
    mats: dict[float, Matrices] = field(default_factory=dict)   # parameters are frozen while streaming
    birth_consts: BirthConstants | None = None
    pending: Tensor = field(default_factory=lambda: torch.empty(0, 2))   # reset() puts it on the device
