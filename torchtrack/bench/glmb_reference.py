"""A NumPy δ-GLMB tracker written the way the published codes are (B.-N. Vo's MATLAB ``jointpredictupdate`` and
its Python ports): the reference of ``torchtrack bench glmb``.

The same model and recursion as :mod:`torchtrack.filters.glmb.filter` (equations (G1)–(G7) of its docstring) and
:mod:`torchtrack.filters.glmb.birth` ((B1), (B2)), with the same options (:class:`GLMBConfig`):

- (G1)/(G2) every track of the table and every birth is predicted and updated against every measurement one
  track at a time (a Python loop over tracks, each Kalman step in NumPy), χ² gating, the per-track weights
  ``η_i`` over ``[absent, missed, z_1 … z_M]`` (zero outside the gate);
- (G3) one hypothesis at a time: ``ceil(chains √w_h / Σ_h' √w_h')`` Gibbs chains, each started with every track
  absent and run ``sweeps`` sweeps, one draw per track and sweep (each draw: the track's row of ``η``, the
  measurements other tracks hold locked out, the cumulative sum inverted with one uniform);
- (G4)–(G7) distinct samples, their weights in the log domain, new tracks keyed by (predicted track, choice),
  hypotheses of the same track set merged, prune, cap, normalise, the MAP-cardinality estimate;
- births (B1)–(B2) from the measurements' probability of having been assigned, and for positions only the
  two-point births (B3) of the previous frame's unexplained measurements.

What differs from :class:`~torchtrack.filters.glmb.filter.GLMBFilter`: **no groups** — like the published code, one
δ-GLMB over all tracks (a frame's hypotheses are joint: ``chains`` chains per frame, ``max_hypotheses`` hypotheses
in all, the estimate is the joint MAP); the sweep visits a hypothesis's tracks in table order, then the births;
its own random stream (``numpy.random.Generator``). Where the tracks form one group (every track gates a common
measurement chain), the two filters define the same density, and with the sampler replaced by exhaustive
enumeration (``enumerate_all``) the same hypotheses and weights (``tests/test_bench_glmb.py``). No confirmation
(the tracker's reporting rule): the reference returns the estimate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import cho_solve, solve_triangular
from scipy.stats import chi2

from torchtrack.filters.trackers.options import GLMBConfig

ABSENT, MISSED = 0, 1   # columns of a track's η row; column 2 + j is measurement j


@dataclass(frozen=True)
class Track:
    """One row of the track table: ``N(x; mean, cov)`` of ``label`` (birth frame, birth index); ``meas`` the
    measurement it took in the last frame (-1: none)."""

    mean: np.ndarray   # (n,)
    cov: np.ndarray    # (n, n)
    label: tuple[int, int]
    meas: int


@dataclass
class Hypothesis:
    """A set of table rows (ascending) and its log-weight."""

    tracks: tuple[int, ...]
    log_weight: float


@dataclass
class ReferenceState:
    """The δ-GLMB: its track table and hypotheses (log-weights normalised)."""

    table: list[Track] = field(default_factory=list)
    hypotheses: list[Hypothesis] = field(default_factory=lambda: [Hypothesis((), 0.0)])


def _log(p: float) -> float:
    return math.log(p) if p > 0 else -math.inf


def _logsumexp(values: list[float]) -> float:
    top = max(values)
    return top + math.log(sum(math.exp(v - top) for v in values)) if math.isfinite(top) else top


def cv_model(q: float) -> tuple[np.ndarray, np.ndarray]:
    """2-D constant velocity over one frame, state ``[x, y, vx, vy]``: ``F (4, 4)``, ``Q (4, 4)`` (continuous
    white-noise acceleration of density ``q``)."""
    F = np.eye(4)
    F[0, 2] = F[1, 3] = 1.0
    Q = q * np.kron(np.array([[1 / 3, 1 / 2], [1 / 2, 1.0]]), np.eye(2))
    return F, Q


def enumerate_choices(eta_rows: list[np.ndarray]) -> list[tuple[int, ...]]:
    """Every joint choice over the rows (one column each, a measurement column at most once) of nonzero weight:
    exhaustive, for tiny problems (the test's replacement of the Gibbs sampler)."""
    out: list[tuple[int, ...]] = []

    def extend(prefix: tuple[int, ...], taken: set[int]) -> None:
        if len(prefix) == len(eta_rows):
            out.append(prefix)
            return
        for col in np.flatnonzero(eta_rows[len(prefix)] > 0):
            if col < 2 or col not in taken:
                extend(prefix + (int(col),), taken | ({int(col)} if col >= 2 else set()))

    extend((), set())
    return out


def gibbs_chain(eta_rows: list[np.ndarray], sweeps: int, rng: np.random.Generator) -> list[tuple[int, ...]]:
    """One Gibbs chain over the rows' joint choice, started all absent: the choice after each of ``sweeps``
    sweeps. ``eta_rows``: each track's ``η`` over ``[absent, missed, z_1 … z_M]`` (any positive scale)."""
    n = len(eta_rows)
    choice = [ABSENT] * n
    taken = np.zeros(eta_rows[0].shape[0] if n else 0, dtype=bool)   # measurement columns held by some track
    samples = []
    for _ in range(sweeps):
        for i in range(n):
            taken[choice[i]] = False
            weights = np.where(taken, 0.0, eta_rows[i])
            cum = np.cumsum(weights)
            pick = int(np.searchsorted(cum, rng.random() * cum[-1], side="right"))
            choice[i] = min(pick, len(cum) - 1)
            if choice[i] >= 2:
                taken[choice[i]] = True
        samples.append(tuple(choice))
    return samples


class ReferenceGLMB:
    """The per-hypothesis δ-GLMB tracker (module docstring) with the options of ``config``; ``seed`` its random
    stream; ``enumerate_all``: every feasible assignment instead of the Gibbs samples (tiny problems only);
    ``velocities``: the measurement is ``[z, v]`` with the detector's velocity (needs ``config.velocity_sigma``)."""

    def __init__(self, config: GLMBConfig, seed: int = 0, enumerate_all: bool = False, velocities: bool = False):
        c = self.config = config
        self.F, self.Q = cv_model(c.q)
        self.with_velocity = velocities and c.velocity_sigma is not None
        if self.with_velocity:
            self.H = np.eye(4)
            self.R = np.diag([c.sigma**2] * 2 + [c.velocity_sigma**2] * 2)
        else:
            self.H = np.hstack([np.eye(2), np.zeros((2, 2))])
            self.R = c.sigma**2 * np.eye(2)
        self.gate = chi2.ppf(c.gate, self.H.shape[0]) if self.H.shape[0] != 2 else -2.0 * math.log1p(-c.gate)
        self.rng = np.random.default_rng(seed)
        self.enumerate_all = enumerate_all
        self.state = ReferenceState()
        self.births: list[tuple[Track, float]] = []   # (density, log r_B) joining the next frame
        self.previous = (np.zeros((0, 2)), np.zeros(0))  # the last frame's z and r_U, for (B3)
        self.next_index = 0
        self.draws = 0          # single Gibbs draws made (one track, one sweep)

    # ------------------------------------------------------------------------------------------ one frame
    def step(self, frame: int, z: np.ndarray, v: np.ndarray | None = None) -> tuple[list[tuple[int, int]],
                                                                                      np.ndarray, np.ndarray]:
        """One frame: ``z (M, 2)``, ``v (M, 2)`` (used with ``velocities``) → the estimate's labels, its means
        ``(E, 4)`` and the probability that each measurement was assigned ``(M,)``."""
        c = self.config
        meas = np.concatenate([z, v], 1) if self.with_velocity else z
        log_kappa = math.log(c.clutter_density) + (math.log(c.velocity_clutter_density) if self.with_velocity
                                                    else 0.0)
        self.state, used, estimate = self._update(self.state, self.births, meas, log_kappa)
        if not self.with_velocity and c.birth_pairs > 0:
            self.births = self._pair_births(z, used, frame)
        else:
            self.births = self._births(z, v if self.with_velocity else None, used, frame)
        self.previous = (z, used)
        table = self.state.table
        return ([table[t].label for t in estimate], np.array([table[t].mean for t in estimate]).reshape(-1, 4),
                used)

    def _update(self, state: ReferenceState, births: list[tuple[Track, float]], z: np.ndarray,
                log_kappa: float) -> tuple[ReferenceState, np.ndarray, list[int]]:
        c = self.config
        M = z.shape[0]
        T = len(state.table)
        rows = [(t, _log(c.p_survival), _log(1 - c.p_survival)) for t in state.table] + \
               [(b, log_r, math.log1p(-math.exp(log_r))) for b, log_r in births]
        if not rows:
            return ReferenceState(), np.zeros(M), []
        # (G1), (G2): each track predicted and updated against every measurement
        predicted, log_eta, updates = [], [], []
        for track, log_exist, log_absent in rows:
            mean, cov = self.F @ track.mean, self.F @ track.cov @ self.F.T + self.Q
            cov = 0.5 * (cov + cov.T)
            eta = np.full(2 + M, -math.inf)
            eta[ABSENT], eta[MISSED] = log_absent, log_exist + _log(1 - c.p_detection)
            S = self.H @ cov @ self.H.T + self.R
            L = np.linalg.cholesky(0.5 * (S + S.T))
            nu = z - self.H @ mean                                          # (M, m)
            white = solve_triangular(L, nu.T, lower=True).T
            nis = (white**2).sum(1)
            loglik = -0.5 * (nis + 2 * np.log(np.diag(L)).sum() + z.shape[1] * math.log(2 * math.pi))
            gated = nis <= self.gate
            eta[2:][gated] = log_exist + _log(c.p_detection) + loglik[gated] - log_kappa
            predicted.append((mean, cov, track.label))
            log_eta.append(eta)
            updates.append((L, nu))
        eta_rows = [np.exp(e - e.max()) for e in log_eta]
        # (G3), (G4): per hypothesis, Gibbs samples (or every assignment) and their weights
        half = [0.5 * h.log_weight for h in state.hypotheses]
        norm = _logsumexp(half)
        birth_rows = list(range(T, len(rows)))
        samples: dict[tuple[int, tuple[int, ...]], float] = {}
        for h, hyp in enumerate(state.hypotheses):
            members = list(hyp.tracks) + birth_rows
            if self.enumerate_all:
                choices = enumerate_choices([eta_rows[i] for i in members])
            else:
                choices = []
                for _ in range(max(1, math.ceil(math.exp(half[h] - norm) * c.chains))):
                    choices += gibbs_chain([eta_rows[i] for i in members], c.sweeps, self.rng)
                self.draws += len(choices) * len(members)
            for choice in choices:
                key = tuple(zip(members, choice))
                if (h, key) not in samples:
                    samples[(h, key)] = hyp.log_weight + sum(log_eta[i][g] for i, g in zip(members, choice))
        # (G5) new tracks: (predicted track, choice); hypotheses of the same new track set merged
        new_index: dict[tuple[int, int], int] = {}
        merged: dict[tuple[int, ...], list[float]] = {}
        for (_, key), log_w in samples.items():
            tracks = tuple(sorted(new_index.setdefault((i, g), len(new_index)) for i, g in key if g != ABSENT))
            merged.setdefault(tracks, []).append(log_w)
        hyps = [Hypothesis(tracks, _logsumexp(ws)) for tracks, ws in merged.items()]
        # (G6) normalise, prune (the heaviest always kept), cap, normalise
        total = _logsumexp([h.log_weight for h in hyps])
        hyps = sorted((Hypothesis(h.tracks, h.log_weight - total) for h in hyps), key=lambda h: -h.log_weight)
        log_prune = _log(c.prune_threshold)
        hyps = [h for rank, h in enumerate(hyps) if rank == 0 or h.log_weight >= log_prune][:c.max_hypotheses]
        total = _logsumexp([h.log_weight for h in hyps])
        # the table: the tracks some hypothesis holds, the Kalman update of those that took a measurement
        held = {t for h in hyps for t in h.tracks}
        keys = [k for k, idx in new_index.items() if idx in held]
        remap, table = {}, []
        for i, g in keys:
            mean, cov, label = predicted[i]
            if g >= 2:
                mean, cov = self._kalman(mean, cov, *updates[i], g - 2)
            remap[new_index[(i, g)]] = len(table)
            table.append(Track(mean, cov, label, g - 2 if g >= 2 else -1))
        new = ReferenceState(table, [Hypothesis(tuple(sorted(remap[t] for t in h.tracks)), h.log_weight - total)
                                     for h in hyps])
        return new, self._used(new, M), self._estimate(new)

    def _kalman(self, mean: np.ndarray, cov: np.ndarray, L: np.ndarray, nu: np.ndarray, j: int):
        """The update of the predicted ``mean, cov`` with measurement ``j`` (``S = L Lᵀ``; Joseph form)."""
        C = cov @ self.H.T
        K = cho_solve((L, True), C.T).T
        A = np.eye(mean.shape[0]) - K @ self.H
        P = A @ cov @ A.T + K @ self.R @ K.T
        return mean + K @ nu[j], 0.5 * (P + P.T)

    @staticmethod
    def _used(state: ReferenceState, M: int) -> np.ndarray:
        """``r_U(z_j) = Σ_h w_h [z_j ∈ h]`` ``(M,)``."""
        used = np.zeros(M)
        for h in state.hypotheses:
            for t in h.tracks:
                if state.table[t].meas >= 0:
                    used[state.table[t].meas] += math.exp(h.log_weight)
        return np.clip(used, 0.0, 1.0)

    @staticmethod
    def _estimate(state: ReferenceState) -> list[int]:
        """(G7): the heaviest hypothesis of the MAP cardinality."""
        card: dict[int, float] = {}
        for h in state.hypotheses:
            card[len(h.tracks)] = card.get(len(h.tracks), 0.0) + math.exp(h.log_weight)
        n = max(sorted(card), key=lambda k: card[k])
        return list(max((h for h in state.hypotheses if len(h.tracks) == n), key=lambda h: h.log_weight).tracks)

    def _birth_existence(self, z: np.ndarray, used: np.ndarray) -> np.ndarray:
        """``r_B (M,)`` of (B1) with the rate of (B2)."""
        c = self.config
        rate = c.birth_rate
        if z.shape[0] >= 2:
            extent = z.max(0) - z.min(0)
            rate = max(c.birth_rate, c.birth_density * float(extent[0] * extent[1]) * 1e-6)
        free = np.clip(1.0 - used, 0.0, None)
        return np.minimum(rate * free / max(free.sum(), 1.0), c.birth_max)

    def _pair_births(self, z: np.ndarray, used: np.ndarray, frame: int) -> list[tuple[Track, float]]:
        """(B3), positions only: measurement by measurement, its ``birth_pairs`` nearest unexplained measurements
        of the previous frame within ``birth_max_speed`` each propose a birth at that displacement, sharing
        the measurement's ``r_B`` in proportion to their ``1 − r_U`` (normalised by ``max(1, Σ)``)."""
        c = self.config
        r = self._birth_existence(z, used)
        z_prev, used_prev = self.previous
        free_prev = np.clip(1.0 - used_prev, 0.0, None)
        cov = np.diag([c.birth_sigma_pos**2] * 2 + [c.birth_sigma_vel_pair**2] * 2)
        out = []
        for j in range(z.shape[0]):
            dist = np.linalg.norm(z_prev - z[j], axis=1)
            near = [i for i in np.argsort(dist, kind="stable")
                    if dist[i] <= c.birth_max_speed and free_prev[i] > 0][: c.birth_pairs]
            total = max(sum(free_prev[i] for i in near), 1.0)
            for i in near:
                r_pair = r[j] * free_prev[i] / total
                if r_pair >= c.birth_min:
                    out.append((Track(np.concatenate([z[j], z[j] - z_prev[i]]), cov.copy(), (frame, self.next_index),
                                      -1), math.log(r_pair)))
                    self.next_index += 1
        return out

    def _births(self, z: np.ndarray, v: np.ndarray | None, used: np.ndarray, frame: int) -> list[tuple[Track, float]]:
        """(B1), (B2): one birth per measurement whose ``r_B`` reaches ``birth_min``."""
        c = self.config
        r = self._birth_existence(z, used)
        sv = c.birth_sigma_vel_detector if v is not None else c.birth_sigma_vel
        cov = np.diag([c.birth_sigma_pos**2] * 2 + [sv**2] * 2)
        out = []
        for j in np.flatnonzero(r >= c.birth_min):
            vel = v[j] if v is not None else np.zeros(2)
            out.append((Track(np.concatenate([z[j], vel]), cov.copy(), (frame, self.next_index), -1),
                        math.log(r[j])))
            self.next_index += 1
        return out
