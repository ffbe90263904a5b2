"""Poisson multi-Bernoulli filtering: the track-oriented marginal MeMBer/Poisson (TOMB/P) filter.

Williams (2015), "Marginal multi-Bernoulli filters" (IEEE T-AES 51(3)), cited by the PMB paper as [3];
linear-Gaussian, batched over any leading dimensions (Monte Carlo runs, independent scenes) and
differentiable in the continuous parameters.

The multi-target density is Poisson multi-Bernoulli (PMB):

* **undetected targets**: a Poisson point process with Gaussian-mixture intensity
  ``D_u(x) = Σ_k w_k N(x; m_k, P_k)`` (fixed capacity ``K``; empty slots have ``log w = -inf``);
* **detected targets**: ``N`` Bernoulli tracks with existence ``r_i``, Gaussian ``N(x; m_i, P_i)`` and
  an integer label (``-1`` marks an empty slot); ``N`` follows the scene (``max(capacity, kept)``).

Prediction::

    w_k ← p_S w_k, r_i ← p_S r_i, (m, P) ← (F m, F P Fᵀ + Q);  D_u ← D_u + D_b   (birth intensity)

Update with measurements ``Z = {z_1 … z_M}``, ``z = H x + v, v ~ N(0, R)``, clutter intensity ``κ``:

* track ``i`` misses: weight ``w_i0 = 1 − r_i p_D``; posterior existence
  ``r_i (1 − p_D) / (1 − r_i p_D)``, state unchanged;
* track ``i`` takes ``z_j`` (inside the gate ``ν_ijᵀ S_i⁻¹ ν_ij < γ``): weight
  ``w_ij = r_i p_D N(z_j; H m_i, S_i)``, existence 1, Kalman-updated state;
* ``z_j`` is the first detection of a target or clutter: weight ``λ_j = e_j + κ(z_j)`` with
  ``e_j = p_D Σ_k w_k N(z_j; H m_k, S_k)``; the new Bernoulli has existence ``e_j / λ_j`` and the
  moment-matched mixture of the Kalman updates of the Poisson components;
* the Poisson intensity becomes ``(1 − p_D) D_u``.

The marginal association probabilities ``p_i(0), p_i(j), p_j(new)`` come from loopy belief
propagation (:func:`torchtrack.association.lbp.lbp_marginals`, or on the gated pairs only with ``sparse``:
:mod:`torchtrack.filters.pmb.sparse`) and the **track-oriented merge**
(TOMB) collapses each track's hypotheses to one Bernoulli by moment matching::

    r_i' = p_i(0) r_i^miss + Σ_j p_i(j)
    m_i' = (p_i(0) r_i^miss m_i + Σ_j p_i(j) m_ij) / r_i'
    P_i' = (p_i(0) r_i^miss (P_i + d_0 d_0ᵀ) + Σ_j p_i(j) (P_i⁺ + d_j d_jᵀ)) / r_i'
    r_j^new = p_j(new) e_j / λ_j

Discrete steps — gating, pruning tracks with ``r < prune_existence`` and Poisson components with
``w < prune_poisson``, ordering the kept Bernoullis by existence — are stop-gradient selections;
everything else is differentiable. Estimates are the tracks with ``r > estimate_threshold``; labels
are given once, when a measurement creates its Bernoulli, and follow that Bernoulli afterwards.
"""

from __future__ import annotations

import logging
import math
from typing import NamedTuple

import torch
from torch import Tensor, nn

from torchtrack.association.lbp import LBPResult, lbp_marginals
from torchtrack.association.lbp_sparse import SparseLBPResult, sparse_lbp_marginals
from torchtrack.errors import TorchtrackError
from torchtrack.filters.pmb.sparse import PairMoments, gated_pairs, pair_moments
from torchtrack.gaussian import (
    chi2_quantile,
    innovation_cov,
    innovations_likelihood,
    kalman_gain,
    matmul,
    moment_match,
    posterior_cov,
    small_matmul,
    symmetrize,
)
from torchtrack.models.measurement import MeasurementModel
from torchtrack.models.motion import MotionModel
from torchtrack.params import Positive, Probability

log = logging.getLogger(__name__)

NEG_INF = float("-inf")


class PMBState(NamedTuple):
    """A PMB density with ``K`` Poisson components and ``N`` Bernoulli slots, batch shape ``*``."""

    poisson_log_weight: Tensor  # (*, K)       log w_k (-inf: empty)
    poisson_mean: Tensor        # (*, K, n)
    poisson_cov: Tensor         # (*, K, n, n)
    existence: Tensor           # (*, N)       r_i (0 in empty slots)
    mean: Tensor                # (*, N, n)
    cov: Tensor                 # (*, N, n, n) (identity in empty slots)
    label: Tensor               # (*, N)       int64, -1: empty slot
    next_label: Tensor          # (*,)         int64, the next label to give

    @property
    def valid(self) -> Tensor:
        """``(*, N)`` bool: the slot holds a Bernoulli."""
        return self.label >= 0


class PMBUpdateInfo(NamedTuple):
    """What an update reveals besides the new state."""

    marginals: LBPResult | SparseLBPResult   # association marginals of the existing tracks (*, N, M) and new
    #                                          targets (*, M); on the sparse path (an unbatched update with
    #                                          2-D measurements, by default): per gated pair (E,) and (M,);
    #                                          ``marginals.assoc_matrix()`` is (*, N, M) on either path


class Estimates(NamedTuple):
    """Tracks whose existence exceeds the threshold."""

    mask: Tensor       # (*, N) bool
    mean: Tensor       # (*, N, n)
    label: Tensor      # (*, N)
    existence: Tensor  # (*, N)


class _Fixed(nn.Module):
    """A constant (not learnable) value, for probabilities of exactly 0 or 1 and a zero intensity."""

    def __init__(self, value: float):
        super().__init__()
        self.register_buffer("value", torch.tensor(float(value)))

    def forward(self) -> Tensor:
        return self.value


def _probability(value: float, name: str, learnable: bool) -> nn.Module:
    if not 0.0 <= value <= 1.0:
        raise TorchtrackError(f"{name} must lie in [0, 1]; got {value!r}")
    return Probability(value, name, requires_grad=learnable) if 0.0 < value < 1.0 else _Fixed(value)


def _log(x: Tensor) -> Tensor:
    """``log x`` with ``log 0 = -inf`` and a finite gradient at 0."""
    tiny = torch.finfo(x.dtype).tiny
    return torch.where(x > 0, torch.log(x.clamp_min(tiny)), torch.full_like(x, NEG_INF))


class _Hypotheses(NamedTuple):
    log_lik: Tensor   # (*, C, M) log N(z_j; H m_c, S_c)
    d2: Tensor        # (*, C, M) Mahalanobis distance squared
    innovation: Tensor  # (*, C, M, d) ν_cj = z_j − H m_c
    gain: Tensor      # (*, C, n, d) K_c
    cov: Tensor       # (*, C, n, n) Kalman-updated covariance (the same for every z_j)


def _small_mv(A: Tensor, x: Tensor) -> Tensor:
    """``A_c x_cm`` for ``A (*, C, p, q)`` and ``x (*, C, M, q)`` → ``(*, C, M, p)``, unrolled over ``q``."""
    out = A[..., :, 0].unsqueeze(-2) * x[..., 0:1]
    for k in range(1, A.shape[-1]):
        out = out + A[..., :, k].unsqueeze(-2) * x[..., k:k + 1]
    return out


def _kalman_all_pairs(mean: Tensor, cov: Tensor, z: Tensor, H: Tensor, R: Tensor, what: str) -> _Hypotheses:
    """Kalman updates of ``C`` Gaussians with each of ``M`` measurements at once.

    ``mean (*, C, n)``, ``cov (*, C, n, n)``, ``z (*, M, d)``, ``H (d, n)``, ``R (*, d, d)``. The shared
    update of :mod:`torchtrack.gaussian` with the measurements as an extra batch dimension: ``S_c`` is
    factorised once per component (:func:`~torchtrack.gaussian.kalman_gain`), each innovation ``ν_cm``
    is whitened by it, and ``P_c⁺ = P_c − W_c W_cᵀ`` (symmetric by construction). The updated means
    ``m_c + K_c ν_cj`` are left to the caller (the TOMB merge needs only their weighted moments).
    """
    PHt, S = innovation_cov(cov, H, R.unsqueeze(-3))                 # (*, C, n, d), (*, C, d, d)
    gain = kalman_gain(S, PHt, what)
    nu = z.unsqueeze(-3) - (mean @ H.transpose(-1, -2)).unsqueeze(-2)   # (*, C, M, d)
    d2, log_lik = innovations_likelihood(gain, nu)                   # (*, C, M)
    return _Hypotheses(log_lik, d2, nu, gain.gain, posterior_cov(cov, gain))


def _lbp_on_gated_lines(log_w: Tensor, log_miss: Tensor, log_new: Tensor, gated: Tensor, iterations: int,
                        tol: float | None) -> LBPResult:
    """:func:`lbp_marginals` of an unbatched problem on the Bernoullis and measurements with a gated pair only:
    the others take no part in any message (their weights ``a_ij`` are 0), so their marginals are ``p_i(0) = 1``
    and ``p_j(new) = 1`` and the rest is the same; the iteration runs on the smaller matrix."""
    if log_w.dim() != 2 or torch.is_grad_enabled():
        return lbp_marginals(log_w, log_miss, log_new, iterations=iterations, tol=tol, check=False)
    rows, cols = gated.any(1).nonzero().squeeze(1), gated.any(0).nonzero().squeeze(1)
    sub = lbp_marginals(log_w[rows][:, cols], log_miss[rows], log_new[cols], iterations=iterations, tol=tol,
                        check=False)
    assoc, meas_assoc = log_w.new_zeros(log_w.shape), log_w.new_zeros(log_w.shape)
    assoc[rows.unsqueeze(1), cols] = sub.assoc
    meas_assoc[rows.unsqueeze(1), cols] = sub.meas_assoc
    miss = log_miss.new_ones(log_miss.shape).index_put_((rows,), sub.miss)
    new = log_new.new_ones(log_new.shape).index_put_((cols,), sub.new)
    return LBPResult(assoc, miss, new, meas_assoc, sub.iterations, sub.converged)


class PMBFilter(nn.Module):
    """The TOMB/P filter (module docstring) for a linear motion and a linear measurement model.

    Args:
        motion: linear :class:`~torchtrack.models.motion.MotionModel` (``F``, ``Q``).
        measurement: linear measurement model with ``matrix()`` ``H`` and ``noise_cov()`` ``R``.
        p_survival, p_detection: probabilities in [0, 1] (learnable when strictly inside).
        clutter_intensity: ``κ``, expected clutter per unit measurement volume (>= 0; learnable when > 0).
        birth_weight, birth_mean, birth_cov: the birth intensity ``D_b = w_b N(m_b, P_b)`` (weight
            learnable; ``birth_weight=0`` for no birth).
        capacity: the floor of the Bernoulli slots ``N``, which follow the scene: after each update ``N`` is
            the larger of ``capacity`` and the number of Bernoullis above ``prune_existence`` (grown between
            steps; a Bernoulli above the threshold is never dropped to fit).
        capacity_limit: a hard limit on the Bernoullis kept (None: none); an update that would keep more
            raises :class:`TorchtrackError` naming it.
        poisson_capacity: Poisson components ``K`` kept (the birth component is always added).
        gate: gate probability; pairs with ``ν ᵀ S⁻¹ ν`` above its chi-square quantile are not hypotheses.
        lbp_iterations, lbp_tol: LBP cap and tolerance (``lbp_tol=None``: fixed iterations, for autograd).
        prune_existence, prune_poisson: pruning thresholds for ``r`` and ``w_k``.
        estimate_threshold: a track is reported when ``r`` exceeds it.
        sparse: the track part of the update on the gated (Bernoulli, measurement) pairs only
            (:mod:`torchtrack.filters.pmb.sparse`; unbatched states, 2-D measurements); the same result as
            the dense ``N × M`` path up to rounding. None (default): wherever it applies (an unbatched update
            with 2-D measurements), where it is as fast as the dense path on small scenes and faster from about
            a hundred tracks on (``torchtrack bench pmb``).
    """

    def __init__(self, motion: MotionModel, measurement: MeasurementModel, p_survival: float = 0.99,
                 p_detection: float = 0.9, clutter_intensity: float = 1e-4, birth_weight: float = 0.05,
                 birth_mean: Tensor | None = None, birth_cov: Tensor | None = None, capacity: int = 64,
                 poisson_capacity: int = 8, gate: float = 0.9999, lbp_iterations: int = 50,
                 lbp_tol: float | None = 1e-7, prune_existence: float = 1e-4, prune_poisson: float = 1e-6,
                 estimate_threshold: float = 0.5, learnable: bool = True, capacity_limit: int | None = None,
                 sparse: bool | None = None):
        super().__init__()
        if not motion.is_linear:
            raise TorchtrackError("PMBFilter needs a linear motion model")
        if capacity < 1 or poisson_capacity < 2:
            raise TorchtrackError(f"capacity must be >= 1 and poisson_capacity >= 2; got {capacity}, "
                                  f"{poisson_capacity}")
        if sparse and measurement.meas_dim != 2:
            raise TorchtrackError(f"PMB: sparse association needs 2-D measurements; got {measurement.meas_dim}-D")
        if not 0.0 < gate <= 1.0:
            raise TorchtrackError(f"gate must be a probability in (0, 1]; got {gate!r}")
        if clutter_intensity < 0 or birth_weight < 0:
            raise TorchtrackError("clutter_intensity and birth_weight must be >= 0")
        self.motion = motion
        self.measurement = measurement
        n = motion.state_dim
        self.p_survival = _probability(p_survival, "p_survival", learnable)
        self.p_detection = _probability(p_detection, "p_detection", learnable)
        self.clutter_intensity = (Positive(clutter_intensity, "clutter intensity", requires_grad=learnable)
                                  if clutter_intensity > 0 else _Fixed(0.0))
        self.birth_weight = (Positive(birth_weight, "birth weight", requires_grad=learnable)
                             if birth_weight > 0 else _Fixed(0.0))
        bm = torch.zeros(n) if birth_mean is None else torch.as_tensor(birth_mean, dtype=torch.get_default_dtype())
        bc = torch.eye(n) if birth_cov is None else torch.as_tensor(birth_cov, dtype=torch.get_default_dtype())
        if bm.shape != (n,) or bc.shape != (n, n):
            raise TorchtrackError(f"birth_mean must be ({n},) and birth_cov ({n}, {n})")
        self.register_buffer("birth_mean", bm)
        self.register_buffer("birth_cov", bc)
        self.capacity = capacity
        self.capacity_limit = capacity_limit
        self.sparse = sparse
        self.poisson_capacity = poisson_capacity
        self.gate_d2 = chi2_quantile(gate, measurement.meas_dim)
        self.lbp_iterations = lbp_iterations
        self.lbp_tol = lbp_tol
        self.prune_existence = prune_existence
        self.prune_poisson = prune_poisson
        self.estimate_threshold = estimate_threshold
        self._cache: dict = {}
        self._tracked: list[Tensor] | None = None

    def _apply(self, fn, *args, **kwargs):
        """``.to()``/``.double()`` replace buffers: forget the tensors the constants cache watches."""
        self._tracked = None
        self._cache = {}
        return super()._apply(fn, *args, **kwargs)

    # ------------------------------------------------------------------ state
    def init_state(self, batch_shape: tuple[int, ...] = (), undetected_weight: float = 0.0,
                   undetected_mean: Tensor | None = None, undetected_cov: Tensor | None = None,
                   dtype: torch.dtype = torch.float64, device=None) -> PMBState:
        """No tracks; the Poisson intensity ``undetected_weight · N(mean, cov)`` (default: the birth)."""
        n, N, K = self.motion.state_dim, self.capacity, self.poisson_capacity
        kw = {"dtype": dtype, "device": device}
        um = self.birth_mean if undetected_mean is None else torch.as_tensor(undetected_mean)
        uc = self.birth_cov if undetected_cov is None else torch.as_tensor(undetected_cov)
        lw = torch.full((*batch_shape, K), NEG_INF, **kw)
        if undetected_weight > 0:
            lw[..., 0] = float(torch.log(torch.tensor(undetected_weight, dtype=torch.float64)))
        eye = torch.eye(n, **kw)
        return PMBState(
            poisson_log_weight=lw,
            poisson_mean=um.to(**kw).expand(*batch_shape, K, n).clone(),
            poisson_cov=uc.to(**kw).expand(*batch_shape, K, n, n).clone(),
            existence=torch.zeros(*batch_shape, N, **kw),
            mean=torch.zeros(*batch_shape, N, n, **kw),
            cov=eye.expand(*batch_shape, N, n, n).clone(),
            label=torch.full((*batch_shape, N), -1, dtype=torch.long, device=device),
            next_label=torch.zeros(batch_shape, dtype=torch.long, device=device),
        )

    # ------------------------------------------------------------------ constants
    def _constants(self, which: str, dt, ref: Tensor) -> tuple[Tensor, ...]:
        """Model matrices and probabilities in ``ref``'s dtype/device.

        Without gradients (no parameter requires grad, or grad mode off) and for a float ``dt`` they are
        computed once and reused until a parameter or buffer changes (storage or version counter): the
        dozens of small operations that build ``F``, ``Q``, ``H``, ``R`` are then not repeated per scan.
        """
        if self._tracked is None:
            self._tracked = [*self.parameters(), *self.buffers()]
        tensors = self._tracked
        cacheable = isinstance(dt, (int, float, type(None))) and not (
            torch.is_grad_enabled() and any(t.requires_grad for t in tensors))
        key = None
        if cacheable:
            key = (which, dt, ref.dtype, ref.device, tuple((t.data_ptr(), t._version) for t in tensors))
            hit = self._cache.get(which)
            if hit is not None and hit[0] == key:
                return hit[1]
        if which == "predict":
            ps = self.p_survival().to(ref)
            out = (self.motion.transition_matrix(dt).to(ref), self.motion.process_noise(dt).to(ref), ps,
                   _log(self.birth_weight().to(ref)), self.birth_mean.to(ref), self.birth_cov.to(ref))
        else:
            pd = self.p_detection().to(ref)
            out = (self.measurement.matrix().to(ref), self.measurement.noise_cov().to(ref), pd, _log(pd),
                   _log(1.0 - pd), _log(self.clutter_intensity().to(ref)))
        if key is not None:
            self._cache[which] = (key, out)
        return out

    # ------------------------------------------------------------------ predict
    def predict(self, state: PMBState, dt=1.0) -> PMBState:
        """Prediction: survival, motion, and the birth component added to the Poisson part."""
        ref = state.mean
        F, Q, ps, log_bw, bm, bc = self._constants("predict", dt, ref)
        mean = state.mean @ F.transpose(-1, -2)
        cov = symmetrize(matmul(F, state.cov @ F.transpose(-1, -2)) + Q)
        existence = ps * state.existence
        pmean = state.poisson_mean @ F.transpose(-1, -2)
        pcov = symmetrize(matmul(F, state.poisson_cov @ F.transpose(-1, -2)) + Q)
        plw = state.poisson_log_weight + _log(ps)
        # keep the K-1 heaviest components, then append the birth (a stop-gradient selection)
        keep = torch.topk(plw.detach(), self.poisson_capacity - 1, dim=-1).indices
        plw = plw.gather(-1, keep)
        n = pmean.shape[-1]
        pmean = pmean.gather(-2, keep.unsqueeze(-1).expand(*keep.shape, n))
        pcov = pcov.gather(-3, keep[..., None, None].expand(*keep.shape, n, n))
        batch = plw.shape[:-1]
        plw = torch.cat([plw, log_bw.expand(*batch, 1)], -1)
        pmean = torch.cat([pmean, bm.expand(*batch, 1, n)], -2)
        pcov = torch.cat([pcov, bc.expand(*batch, 1, n, n)], -3)
        return state._replace(poisson_log_weight=plw, poisson_mean=pmean, poisson_cov=pcov,
                              existence=existence, mean=mean, cov=cov)

    # ------------------------------------------------------------------ update
    def update(self, state: PMBState, z: Tensor, mask: Tensor | None = None,
               extra_noise: Tensor | None = None) -> tuple[PMBState, PMBUpdateInfo]:
        """TOMB/P update with the measurement set of one scan.

        Args:
            state: predicted :class:`PMBState`, batch ``*``.
            z: ``(*, M, d)`` measurements (padding allowed, see ``mask``); ``M`` may be 0.
            mask: ``(*, M)`` bool, True for real measurements (default: all).
            extra_noise: ``(*, d, d)`` added to ``R`` (variance inflation by an uncertain sensor).

        Returns:
            the updated state (pruned; ``max(capacity, kept)`` Bernoulli slots) and :class:`PMBUpdateInfo`.
        """
        ref = state.mean
        d = self.measurement.meas_dim
        if z.shape[-1] != d or z.shape[:-2] != state.existence.shape[:-1]:
            raise TorchtrackError(f"PMB update: z must be (*, M, {d}) with batch {tuple(state.existence.shape[:-1])}; "
                                  f"got {tuple(z.shape)}")
        sparse = self.sparse if self.sparse is not None else (z.dim() == 2 and d == 2)
        if sparse and z.dim() != 2:
            raise TorchtrackError(f"PMB update: sparse association needs an unbatched state; got batch "
                                  f"{tuple(z.shape[:-2])}")
        z = z.to(ref)
        M = z.shape[-2]
        batch = z.shape[:-2]
        zmask = torch.ones(z.shape[:-1], dtype=torch.bool, device=z.device) if mask is None else mask.bool()
        if not bool(torch.isfinite(torch.where(zmask.unsqueeze(-1), z, torch.zeros_like(z))).all()):
            raise TorchtrackError("PMB update: measurements contain NaN or infinite values")
        z = torch.where(zmask.unsqueeze(-1), z, torch.zeros_like(z))              # padding never leaks
        H, R, pd, log_pd, log_1mpd, log_kappa = self._constants("update", None, ref)
        R = R.expand(*batch, d, d)
        if extra_noise is not None:
            R = R + extra_noise.to(ref)
        tiny = torch.finfo(ref.dtype).tiny

        valid = state.valid
        r = state.existence
        N = r.shape[-1]
        if sparse:
            poi = _kalman_all_pairs(state.poisson_mean, state.poisson_cov, z, H, R,
                                    "PMB: innovation covariance (Poisson component)")
        else:   # tracks and Poisson components in one batch of Kalman hypotheses
            both = _kalman_all_pairs(torch.cat([state.mean, state.poisson_mean], -2),
                                     torch.cat([state.cov, state.poisson_cov], -3), z, H, R,
                                     "PMB: innovation covariance (track or Poisson component)")
            trk = _Hypotheses(*(t[..., :N, :] if t.dim() == both.log_lik.dim() else t[..., :N, :, :] for t in both))
            poi = _Hypotheses(*(t[..., N:, :] if t.dim() == both.log_lik.dim() else t[..., N:, :, :] for t in both))
        log_r = _log(torch.where(valid, r, torch.ones_like(r)))
        log_miss = _log((1.0 - r * pd).clamp_min(0.0))

        # new-target hypotheses from the Poisson intensity and clutter
        l_kj = state.poisson_log_weight.unsqueeze(-1) + log_pd + poi.log_lik     # (*, K, M)
        log_e = torch.logsumexp(l_kj, dim=-2)                                   # (*, M)
        log_lam = torch.logaddexp(log_e, log_kappa.expand_as(log_e)).clamp_min(float(torch.log(torch.tensor(tiny))))
        log_new = torch.where(zmask, log_lam, torch.zeros_like(log_lam))
        r_new_hyp = torch.exp(torch.clamp(log_e - log_lam, max=0.0))
        any_poisson = torch.isfinite(l_kj).any(-2, keepdim=True)
        l_safe = torch.where(any_poisson, l_kj, torch.zeros_like(l_kj)).transpose(-1, -2)  # (*, M, K)
        K_ = state.poisson_log_weight.shape[-1]
        n = state.mean.shape[-1]
        poi_mean = state.poisson_mean.unsqueeze(-2) + poi.innovation @ poi.gain.transpose(-1, -2)  # (*, K, M, n)
        new_mean, new_cov = moment_match(l_safe, poi_mean.transpose(-2, -3),
                                         poi.cov.unsqueeze(-4).expand(*batch, M, K_, n, n))

        # marginal association probabilities (Williams & Lau 2014) and the innovation moments of the merge
        if sparse:
            pairs = gated_pairs(state.mean, state.cov, valid, z, zmask, H, R, self.gate_d2)
            marg = sparse_lbp_marginals(pairs.row, pairs.col, log_r[pairs.row] + log_pd + pairs.log_lik, log_miss,
                                        log_new, iterations=self.lbp_iterations, tol=self.lbp_tol, check=False)
            moments = pair_moments(pairs.row, marg.assoc, pairs.innovation, N)
            gain, cov_upd = pairs.gain, pairs.cov
        else:
            gated = (trk.d2 < self.gate_d2) & valid.unsqueeze(-1) & zmask.unsqueeze(-2)
            log_w = torch.where(gated, log_r.unsqueeze(-1) + log_pd + trk.log_lik,
                                torch.full_like(trk.log_lik, NEG_INF))
            marg = _lbp_on_gated_lines(log_w, log_miss, log_new, gated, self.lbp_iterations, self.lbp_tol)
            aj = marg.assoc                                                      # (*, N, M)
            moments = PairMoments(aj.sum(-1), (aj.unsqueeze(-2) @ trk.innovation).squeeze(-2),
                                  (aj.unsqueeze(-1) * trk.innovation).transpose(-1, -2) @ trk.innovation)
            gain, cov_upd = trk.gain, trk.cov

        # track-oriented merge
        r_miss = r * (1.0 - pd) / (1.0 - r * pd).clamp_min(tiny)
        a0 = marg.miss * r_miss                                                  # (*, N)
        a_det = moments.detected
        r_post = a0 + a_det
        denom = r_post.clamp_min(tiny)
        # with c = ν̄ / r', ν̄ = Σ_j p_i(j) ν_ij and V = Σ_j p_i(j) ν_ij ν_ijᵀ the merge is
        #   m' = m + K c,  P' = (p_i(0) r^miss P + Σ_j p_i(j) P⁺) / r' + K (V / r' − c cᵀ) Kᵀ
        c = moments.nu_bar / denom.unsqueeze(-1)
        inner = moments.V / denom[..., None, None] - c.unsqueeze(-1) * c.unsqueeze(-2)
        mean_post = state.mean + _small_mv(gain, c.unsqueeze(-2)).squeeze(-2)
        cov_post = ((a0[..., None, None] * state.cov + a_det[..., None, None] * cov_upd) / denom[..., None, None]
                    + small_matmul(small_matmul(gain, inner), gain.transpose(-1, -2)))
        r_new = torch.where(zmask, marg.new * r_new_hyp, torch.zeros_like(r_new_hyp))
        new_label = torch.where(zmask, state.next_label.unsqueeze(-1) + torch.cumsum(zmask.long(), -1) - 1,
                                torch.full_like(zmask, -1, dtype=torch.long))
        next_label = state.next_label + zmask.long().sum(-1)

        existence = torch.cat([r_post, r_new], -1)
        mean = torch.cat([mean_post, new_mean], -2)
        cov = torch.cat([symmetrize(cov_post), symmetrize(new_cov)], -3)
        label = torch.cat([torch.where(valid, state.label, torch.full_like(state.label, -1)), new_label], -1)
        existence, mean, cov, label = self._compact(existence, mean, cov, label)

        plw = state.poisson_log_weight + log_1mpd
        plw = plw.masked_fill(plw < math.log(self.prune_poisson), NEG_INF)
        new_state = PMBState(plw, state.poisson_mean, state.poisson_cov, existence, mean, cov, label, next_label)
        return new_state, PMBUpdateInfo(marg)

    def _compact(self, existence: Tensor, mean: Tensor, cov: Tensor, label: Tensor):
        """Prune ``r < prune_existence`` and keep every other Bernoulli, most likely first, in
        ``max(capacity, kept)`` slots (stop-gradient); more than ``capacity_limit`` kept is an error."""
        keep = (label >= 0) & (existence >= self.prune_existence)
        kept = int(keep.sum(-1).max()) if keep.numel() else 0
        if self.capacity_limit is not None and kept > self.capacity_limit:
            raise TorchtrackError(f"PMB: {kept} Bernoullis above prune_existence exceed capacity_limit "
                                  f"{self.capacity_limit} (raise capacity_limit, or prune_existence)")
        N = max(self.capacity, kept)
        if existence.shape[-1] < N:
            pad = N - existence.shape[-1]
            n = mean.shape[-1]
            existence = torch.cat([existence, existence.new_zeros(*existence.shape[:-1], pad)], -1)
            mean = torch.cat([mean, mean.new_zeros(*mean.shape[:-2], pad, n)], -2)
            cov = torch.cat([cov, cov.new_zeros(*cov.shape[:-3], pad, n, n)], -3)
            label = torch.cat([label, label.new_full((*label.shape[:-1], pad), -1)], -1)
            keep = torch.cat([keep, keep.new_zeros(*keep.shape[:-1], pad)], -1)
        score = torch.where(keep, existence.detach(), torch.full_like(existence, -1.0))
        idx = torch.topk(score, N, dim=-1).indices
        n = mean.shape[-1]
        keep = keep.gather(-1, idx)
        existence = torch.where(keep, existence.gather(-1, idx), torch.zeros_like(keep, dtype=existence.dtype))
        mean = torch.where(keep.unsqueeze(-1), mean.gather(-2, idx.unsqueeze(-1).expand(*idx.shape, n)),
                           torch.zeros_like(mean[..., :N, :]))
        eye = torch.eye(n, dtype=cov.dtype, device=cov.device)
        cov = torch.where(keep[..., None, None], cov.gather(-3, idx[..., None, None].expand(*idx.shape, n, n)), eye)
        label = torch.where(keep, label.gather(-1, idx), torch.full_like(idx, -1))
        return existence, mean, cov, label

    # ------------------------------------------------------------------ outputs
    def step(self, state: PMBState, z: Tensor, mask: Tensor | None = None, dt=1.0,
             extra_noise: Tensor | None = None) -> tuple[PMBState, PMBUpdateInfo]:
        """``predict`` then ``update``."""
        return self.update(self.predict(state, dt), z, mask, extra_noise)

    def estimate(self, state: PMBState, threshold: float | None = None) -> Estimates:
        """Tracks with ``r > threshold`` (default ``estimate_threshold``)."""
        thr = self.estimate_threshold if threshold is None else threshold
        mask = state.valid & (state.existence > thr)
        return Estimates(mask, state.mean, state.label, state.existence)


def expected_count(state: PMBState) -> tuple[Tensor, Tensor]:
    """Expected number of targets ``(Σ_i r_i, Σ_k w_k)``: detected (Bernoulli) and undetected (Poisson); ``(*,)``."""
    return state.existence.sum(-1), torch.exp(state.poisson_log_weight).sum(-1)
