"""Gaussian-mixture PHD filter (Vo & Ma 2006) with labelled components (Panta, Clark & Vo 2009).

The PHD ``D_k(x)`` is a Gaussian mixture (eq. 2 of Aguilar, Ortner & Zerubia 2023)::

    D_k(x) = Σ_j w_j N(x; m_j, P_j)

held in a :class:`MixtureState` whose leading axis (``J`` components) is bounded by a cap that follows the
scene (:meth:`GMPHD.capacity_for`: ``max(capacity, k (measurements + live labels))``, the configured
``capacity`` its floor): every step ends with pruning, merging and capping, so memory stays bounded over
arbitrarily long sequences, and a cap that is hit is logged (``logging`` warning) and counted.

Prediction (eq. 3; Vo & Ma 2006 eq. 21–24)::

    w⁻ = p_S w,   m⁻ = F m,   P⁻ = F P Fᵀ + Q          (birth components are added by the caller)

Update of every component against every measurement in its gate (eq. 25–29)::

    ẑ_j = H m_j,  S_j = H P_j Hᵀ + R,  K_j = P_j Hᵀ S_j⁻¹,  P_j⁺ = P_j − K_j S_j K_jᵀ
    missed:    w = (1 − p_D) w_j,                         m = m_j,                P = P_j
    detected:  w = p_D w_j g_jk / (κ(z_k) + Σ_i p_D w_i g_ik),  m = m_j + K_j (z_k − ẑ_j),  P = P_j⁺
    g_jk = N(z_k; ẑ_j, S_j), kept only inside the gate  (z_k − ẑ_j)ᵀ S_j⁻¹ (z_k − ẑ_j) ≤ γ

With the detector's velocity ``v_k`` (``velocity_sigma`` set; this project's extension, not the paper's) each
detection is ``[z_k, v_k]``, measured through ``H = I_4`` with ``R_4 = blockdiag(R, σ_v² I)``, gated with the
4-dof χ² quantile, and the clutter intensity is ``κ(z_k) κ_v``. A detector's velocities are often right to
a fraction of a pixel but now and then grossly wrong (a vehicle matched to its neighbour in a platoon);
with ``velocity_outlier`` ``ε > 0`` the velocity of a target's detection is an outlier with probability
``ε``, drawn from the clutter's velocity density ``κ_v``, so each pair's likelihood is the mixture::

    g_jk = (1 − ε) N([z_k, v_k]; [ẑ_j, v̂_j], S_j) + ε κ_v N(z_k; ẑ_j, S_j^pos)

gated on the position alone; the pair's posterior takes the update of the larger of the two terms
(with or without the velocity), its weight the whole mixture.

``S`` is factored once per component (it does not depend on the measurement); pairs outside the gate
get weight zero. A small frame (at most :data:`~torchtrack.association.grid.DENSE_PAIRS` pairs) tests every
pair at once; a larger one never forms the pairs outside the gate: they come from a grid index of the
measurements searched with a radius per component that no in-gate pair exceeds (:func:`gated_pairs`), and
the denominator of each measurement is a segment sum over its pairs (:func:`log_normaliser`), so the
update's time and memory follow the gated pairs — about the number of targets at a constant density — not
``J × M``. Both give the same result.

The PHD predictive log-likelihood of a measurement set (Mahler 2007, the Poisson form used for
parameter learning) is returned by :meth:`GMPHD.update`::

    log p(Z_k | Z_{1:k-1}) ≈ −λ_c − p_D Σ_j w_j⁻ + Σ_k log(κ(z_k) + p_D Σ_j w_j⁻ g_jk)

with ``λ_c = κ · area`` (the term is dropped when ``area`` is None).

Labels propagate: every updated hypothesis inherits its component's label, a merged component takes
the label of its highest-weight member. Pruning, merging, capping and extraction are explicit
stop-gradient *selections*; weights, means and covariances stay differentiable with respect to
``p_S, p_D, κ, Q, R`` and the birth parameters.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor, nn

from torchtrack.association.grid import DENSE_PAIRS, disc_candidates
from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.options import GMPHDFilterOptions
from torchtrack.gaussian import (
    KalmanGain,
    chi2_quantile,
    gaussian_log_likelihood,
    innovation_pairs,
    innovations_likelihood,
    kalman_gain,
    leading_gain,
    log_det_from_cholesky,
    posterior_cov,
    scalar,
    squared_norm,
    whitened_sq_norms,
)
from torchtrack.models import ConstantVelocity, LinearPosition, MeasurementModel, MotionModel
from torchtrack.params import Positive, Probability

log = logging.getLogger(__name__)

NEG_INF = float("-inf")


class MixtureState(NamedTuple):
    """A labelled Gaussian mixture; ``J`` components, state size ``n``.

    ``log_weight (J,)`` (``-inf`` for an empty slot), ``mean (J, n)``, ``cov (J, n, n)``,
    ``label (J,)`` int64 track labels, ``mask (J,)`` bool live slots.
    """

    log_weight: Tensor
    mean: Tensor
    cov: Tensor
    label: Tensor
    mask: Tensor

    @property
    def size(self) -> int:
        return int(self.log_weight.shape[0])

    def select(self, index: Tensor) -> MixtureState:
        """Components at ``index`` (a long index or bool mask; a stop-gradient selection). A mask is turned into
        indices once (on a GPU each boolean indexing waits for the device to count its ``True`` entries), and
        each field is gathered by ``index_select`` (advanced indexing costs a few µs more per tensor)."""
        index = as_rows(index)
        return MixtureState(*(field.index_select(0, index) for field in self))

    def expected_count(self) -> Tensor:
        """Expected number of targets ``Σ w_j`` (differentiable)."""
        return torch.where(self.mask, self.log_weight, torch.full_like(self.log_weight, NEG_INF)).exp().sum()


def as_rows(index: Tensor) -> Tensor:
    """``index`` as a long index of rows: a bool mask's ``True`` positions (one host sync on a GPU), else itself."""
    return index.nonzero().view(-1) if index.dtype == torch.bool else index


ALL_LABEL_PAIRS = 1024
"""Up to this many (query, key) pairs :func:`labels_in` compares every pair at once."""


def labels_in(query: Tensor, keys: Tensor) -> Tensor:
    """``torch.isin(query, keys)`` for integer labels, the same mask ``(Q,)`` by cheaper means: up to
    :data:`ALL_LABEL_PAIRS` pairs every pair compared at once, beyond that a sorted search. (``isin`` itself
    costs about 30 µs on the CPU for a few tens of labels — it sorts and uniques both — and on a GPU its
    ``unique`` is a host sync.)"""
    if keys.numel() == 0:
        return torch.zeros_like(query, dtype=torch.bool)
    if query.numel() * keys.numel() <= ALL_LABEL_PAIRS:
        return (query.unsqueeze(1) == keys).any(1)
    ordered = torch.sort(keys).values
    return ordered.index_select(0, torch.searchsorted(ordered, query).clamp_(max=keys.numel() - 1)) == query


def empty_mixture(n: int, dtype: torch.dtype = torch.float32, device=None) -> MixtureState:
    """A mixture with no component."""
    return MixtureState(torch.empty(0, dtype=dtype, device=device), torch.empty(0, n, dtype=dtype, device=device),
                        torch.empty(0, n, n, dtype=dtype, device=device),
                        torch.empty(0, dtype=torch.long, device=device),
                        torch.empty(0, dtype=torch.bool, device=device))


def concat(*states: MixtureState) -> MixtureState:
    """Concatenate mixtures along the component axis."""
    return MixtureState(*(torch.cat(parts, 0) for parts in zip(*states)))


class Matrices(NamedTuple):
    """The model for one time step, computed once per step by :meth:`GMPHD.matrices` (differentiable):
    ``F, Q (n, n)``, ``H (m, n)``, ``R (m, m)`` and the scalars ``p_S, p_D, κ``."""

    F: Tensor
    Q: Tensor
    H: Tensor
    R: Tensor
    p_survival: Tensor
    p_detection: Tensor
    clutter_density: Tensor
    log_p_survival: Tensor
    log_p_detection: Tensor
    log_p_missed: Tensor     # log(1 − p_D)
    log_clutter: Tensor      # log κ
    FF_t: Tensor             # (n², n²) (F ⊗ F)ᵀ: vec(F P Fᵀ) = vec(P) (F ⊗ F)ᵀ (row-major vec)
    selects_position: bool = False   # H = [I_m 0]: H x is a slice of x (a faster exact path)
    R_velocity: Tensor | None = None          # (m + 2, m + 2) blockdiag(R, σ_v² I): noise of [z, v]
    log_clutter_velocity: Tensor | None = None   # log κ_v, clutter density over velocities
    log_velocity_outlier: Tensor | None = None   # log ε, probability that a target's velocity is an outlier
    log_velocity_inlier: Tensor | None = None    # log(1 − ε)


class UpdateInfo(NamedTuple):
    """What :meth:`GMPHD.update` reports besides the posterior."""

    log_likelihood: Tensor | None   # () PHD predictive log-likelihood of the measurement set (None: not asked)
    log_denominator: Tensor  # (M,) log(κ(z_k) + p_D Σ_j w_j g_jk)
    gated_pairs: int         # number of (component, measurement) pairs inside the gate
    label_support: Tensor | None = None  # (L,) Σ_k Σ_{j ∈ ℓ} p_D w_j g_jk / κ(z_k) per label (``label_index``)


class GMPHD(nn.Module):
    """The GM-PHD recursion with learnable continuous parameters (all :mod:`torchtrack.params`).

    Args:
        motion: a linear motion model (default ``ConstantVelocity(2, options.q)``), state ``[x, y, vx, vy]``.
        measurement: a linear measurement model (default ``LinearPosition(2, options.sigma)``).
        options: :class:`~torchtrack.filters.trackers.options.GMPHDFilterOptions` (their meaning and bounds there):
            ``p_S``, ``p_D``, ``κ`` (learnable), ``area`` of the log-likelihood's ``−λ_c`` term (None: dropped),
            the χ² gate's probability (``γ`` its quantile, ``m`` dof), prune threshold ``T``, merge threshold
            ``U`` and rounds (see :func:`merge`), ``capacity`` ``J_max``, extraction threshold and the detector's
            velocity: with ``velocity_sigma`` ``σ_v``
            (learnable) and velocities given to the update, each detection is the 4-vector ``[z, v]`` measured
            through ``H = I_4`` with ``R_4 = blockdiag(R, σ_v² I)``, the clutter intensity of ``[z, v]`` is
            ``κ(z) κ_v`` (``velocity_clutter_density``, learnable) and ``velocity_outlier`` is ``ε`` of the
            module docstring (None ``σ_v``: velocities are not used in the update).
    """

    def __init__(self, motion: MotionModel | None = None, measurement: MeasurementModel | None = None,
                 options: GMPHDFilterOptions | None = None):
        super().__init__()
        o = self.options = options if options is not None else GMPHDFilterOptions()
        self.motion = motion if motion is not None else ConstantVelocity(2, q=o.q)
        self.measurement = measurement if measurement is not None else LinearPosition(2, sigma=o.sigma)
        if not (self.motion.is_linear and self.measurement.is_linear):
            raise TorchtrackError("GMPHD needs linear motion and measurement models")
        if self.measurement.state_dim != self.motion.state_dim:
            raise TorchtrackError(f"measurement state_dim {self.measurement.state_dim} != motion state_dim "
                                  f"{self.motion.state_dim}")
        self.p_survival = Probability(o.p_survival, "p_survival")
        self.p_detection = Probability(o.p_detection, "p_detection")
        self.clutter_density = Positive(o.clutter_density, "clutter_density")
        self.area = o.area
        m = self.measurement.meas_dim
        self.gate = chi2_quantile(o.gate_probability, m)
        self.gate_velocity = chi2_quantile(o.gate_probability, m + 2)   # gate of [z, v] (velocity_sigma)
        self.cap_hits = 0
        self.velocity_sigma = None if o.velocity_sigma is None else Positive(o.velocity_sigma, "velocity_sigma")
        self.velocity_clutter_density = (None if o.velocity_sigma is None
                                         else Positive(o.velocity_clutter_density, "velocity_clutter_density"))

    @property
    def state_dim(self) -> int:
        return self.motion.state_dim

    def matrices(self, dt: float = 1.0) -> Matrices:
        """``F, Q, H, R, p_S, p_D, κ`` for a step of ``dt`` (compute once per step; differentiable)."""
        ps, pd, kappa = self.p_survival(), self.p_detection(), self.clutter_density()
        H = self.measurement.matrix()
        m, n = H.shape
        eye = torch.eye(m, n, dtype=H.dtype, device=H.device)
        selects = bool(torch.equal(H.detach(), eye))
        R = self.measurement.noise_cov()
        R_v = log_kv = log_eps = log_in = None
        if self.velocity_sigma is not None:
            if not selects or n != m + 2:
                raise TorchtrackError("GMPHD velocity_sigma needs H = [I 0] and a state [position, velocity]")
            R_v = torch.block_diag(R, self.velocity_sigma().pow(2) * torch.eye(2, dtype=R.dtype, device=R.device))
            log_kv = torch.log(self.velocity_clutter_density())
            if self.options.velocity_outlier > 0:
                log_eps = torch.tensor(math.log(self.options.velocity_outlier), dtype=R.dtype, device=R.device)
                log_in = torch.log1p(-log_eps.exp())
        F = self.motion.transition_matrix(dt)
        return Matrices(F, self.motion.process_noise(dt), H, R, ps, pd, kappa,
                        torch.log(ps), torch.log(pd), torch.log1p(-pd), torch.log(kappa), torch.kron(F, F).T, selects,
                        R_v, log_kv, log_eps, log_in)

    def predict(self, state: MixtureState, mats: Matrices) -> MixtureState:
        """Surviving components: ``w p_S``, ``F m``, ``F P Fᵀ + Q`` (eq. 3 without the birth term)."""
        F, Q = mats.F, mats.Q
        J, n = state.mean.shape
        mean = torch.mm(state.mean, F.T)
        # F P Fᵀ + Q for all components in one product: vec(F P Fᵀ) = vec(P) (F ⊗ F)ᵀ
        cov = torch.addmm(Q.reshape(n * n), state.cov.reshape(J, n * n), mats.FF_t).view(J, n, n)
        log_w = state.log_weight + mats.log_p_survival
        return MixtureState(log_w, mean, cov, state.label, state.mask)

    def update(self, state: MixtureState, z: Tensor, mats: Matrices, velocity: Tensor | None = None,
               likelihood: bool = True, pair_loglik: PairLogLik | None = None,
               label_index: tuple[Tensor, int] | None = None) -> tuple[MixtureState, UpdateInfo]:
        """The full GM-PHD update of ``state`` (predicted, ``J`` components) with ``z (M, m)``.

        Clutter has the uniform intensity ``clutter_density``. ``velocity (M, 2)``: the detector's velocities,
        used as measurements (with ``H = I``, ``R_4 = blockdiag(R, σ_v² I)``, clutter ``κ κ_v``) when the filter
        has a ``velocity_sigma``, ignored otherwise. Returns the posterior (missed-detection components first,
        then the gated detection components ordered by component, then measurement, ``J + G`` in all) and
        :class:`UpdateInfo` (its ``log_likelihood`` is None with ``likelihood=False``, which saves its operations
        when streaming).
        ``pair_loglik(jj, kk) → (G,)``: a further log-likelihood ratio of the gated (component, detection) pairs
        ``(jj, kk)`` (two ``(G,)`` index tensors), added to each pair's weight — an attribute of the detection
        measured against the component's, over that attribute's density under clutter (e.g.
        :mod:`torchtrack.filters.gmphd.tone`); None: none.
        ``label_index = (index (J,), L)``: each component's label as an index in ``0 … L−1``; the result's
        ``label_support (L,)`` sums ``p_D w_j g_jk / κ(z_k)`` over each label's components and all detections
        (what a Bernoulli per label needs, :mod:`torchtrack.filters.gmphd.existence`).
        """
        H, R = mats.H, mats.R
        m_dim = H.shape[0]
        if z.dim() != 2 or z.shape[1] != m_dim:
            raise TorchtrackError(f"measurements must have shape (M, {m_dim}); got {tuple(z.shape)}")
        z = z.to(state.mean.dtype)
        pd, log_pd = mats.p_detection, mats.log_p_detection
        log_kappa = mats.log_clutter.expand(z.shape[0])
        gate = self.gate
        robust = False
        if velocity is not None and mats.R_velocity is not None:
            if velocity.shape != z.shape:
                raise TorchtrackError(f"velocities must have shape {tuple(z.shape)}; got {tuple(velocity.shape)}")
            z = torch.cat([z, velocity.to(z.dtype)], 1)
            R, m_dim = mats.R_velocity, m_dim + 2
            log_kappa = log_kappa + mats.log_clutter_velocity
            robust = mats.log_velocity_outlier is not None
            gate = self.gate if robust else self.gate_velocity
        neg_inf = scalar(NEG_INF, state.log_weight)
        live_w = torch.where(state.mask, state.log_weight, neg_inf)

        if mats.selects_position:                                    # H = [I 0]: slices, no products
            PHt = state.cov[:, :, :m_dim]
            S = PHt[:, :m_dim] + R
            z_hat = state.mean[:, :m_dim]
        else:
            PHt = state.cov @ H.transpose(-1, -2)                   # (J, n, m)
            S = H @ PHt + R                      # (J, m, m); Cholesky reads its lower triangle only
            z_hat = state.mean @ H.transpose(-1, -2)                # (J, m)
        # the shared Kalman update of torchtrack.gaussian: per component (J) the factor L of S, the gain
        # and P − W Wᵀ; per gated (component, measurement) pair the whitened innovation gives NIS and log ℓ
        gain = kalman_gain(S, PHt, "GMPHD update: innovation covariance S")
        K, P_upd = gain.gain, posterior_cov(state.cov, gain)
        p_dim = H.shape[0]
        base, base_pos, gain_p = log_pd + live_w, None, None                  # (J,) log p_D w_j
        if robust:         # the leading block of L is the factor of S's position block, that of L⁻¹ its inverse
            gain_p = leading_gain(gain, PHt[:, :, :p_dim])
            K_p, P_upd_p = gain_p.gain, posterior_cov(state.cov, gain_p)
            base_pos = base + mats.log_velocity_outlier + mats.log_clutter_velocity
            base = base + mats.log_velocity_inlier
        parts = _Components(z_hat, S, gain, gain_p, base, base_pos, state.mask, gate)
        weigh = _dense_pairs if state.size * z.shape[0] <= DENSE_PAIRS else _sparse_pairs
        jj, kk, det_logw, use_pos, log_den_t, support = weigh(parts, z, log_kappa, pair_loglik, label_index)
        nu = z.index_select(0, kk) - z_hat.index_select(0, jj)           # (G, m)
        mean_j = state.mean.index_select(0, jj).unsqueeze(-1)
        det_mean = torch.baddbmm(mean_j, K.index_select(0, jj), nu.unsqueeze(-1)).squeeze(-1)   # m + K ν per pair
        det_cov = P_upd.index_select(0, jj)
        if robust:
            mean_pos = torch.baddbmm(mean_j, K_p.index_select(0, jj), nu[:, :p_dim].unsqueeze(-1)).squeeze(-1)
            det_mean = torch.where(use_pos.unsqueeze(-1), mean_pos, det_mean)
            det_cov = torch.where(use_pos.view(-1, 1, 1), P_upd_p.index_select(0, jj), det_cov)

        miss_logw = live_w + mats.log_p_missed
        post = MixtureState(
            torch.cat([miss_logw, det_logw]),
            torch.cat([state.mean, det_mean]),
            torch.cat([state.cov, det_cov]),
            torch.cat([state.label, state.label.index_select(0, jj)]),
            torch.cat([state.mask, torch.ones(jj.shape[0], dtype=torch.bool, device=jj.device)]),
        )
        loglik = None
        if likelihood:
            loglik = log_den_t.sum() - pd * live_w.exp().sum()
            if self.area is not None:
                loglik = loglik - mats.clutter_density * self.area
        return post, UpdateInfo(loglik, log_den_t, int(jj.shape[0]), support)

    def prune(self, state: MixtureState) -> MixtureState:
        """Drop empty slots and components with weight below ``prune_threshold``."""
        lw = state.log_weight
        return state.select(state.mask & (lw > scalar(math.log(self.options.prune_threshold), lw)))

    def capacity_for(self, measurements: int, labels: int) -> int:
        """The component cap of a step with ``measurements`` detections and ``labels`` live labels:
        ``max(capacity, k (measurements + labels))`` with ``k =`` :data:`SCENE_COMPONENTS`, so that the cap
        follows the scene and a live track's components are not dropped to fit a constant (``capacity`` is
        the floor). Above ``capacity_limit``, where one is configured, it is an error."""
        need = max(self.options.capacity, SCENE_COMPONENTS * (measurements + labels))
        limit = self.options.capacity_limit
        if limit is not None and need > limit:
            raise TorchtrackError(f"GM-PHD: {measurements} measurements and {labels} live labels need {need} "
                                  f"components, more than capacity_limit {limit} (raise capacity_limit)")
        return need

    def cap(self, state: MixtureState, capacity: int | None = None) -> MixtureState:
        """Keep the ``capacity`` (default: the configured floor) highest-weight components; a hit cap is logged
        and counted."""
        capacity = self.options.capacity if capacity is None else capacity
        if state.size <= capacity:
            return state
        self.cap_hits += 1
        log.warning("GMPHD: component cap hit (%d components, capacity %d): lowest weights dropped",
                    state.size, capacity)
        idx = torch.topk(state.log_weight.detach(), capacity).indices
        return state.select(idx)

    def reduce(self, state: MixtureState, keep_label: Tensor | None = None,
               capacity: int | None = None) -> MixtureState:
        """Prune, merge, cap at ``capacity`` (default: the configured floor; a step's is :meth:`capacity_for`)
        (Vo & Ma 2006, Table II); ``keep_label (P,)`` labels that win a merge (see :func:`merge`). More than
        ``2 capacity`` components are capped before merging, so the pairwise merge stays bounded in memory."""
        capacity = self.options.capacity if capacity is None else capacity
        o = self.options
        lw = state.log_weight
        keep = as_rows(state.mask & (lw > scalar(math.log(o.prune_threshold), lw)))
        if keep.shape[0] > 2 * capacity or o.merge_threshold <= 0:
            state = self.cap(state.select(keep), 2 * capacity)   # bounds the merge
            return self.cap(merge(state, o.merge_threshold, o.merge_rounds, keep_label), capacity)
        # prune and sort by weight in one gather (what prune and merge's sort select, composed)
        order = keep.index_select(0, torch.argsort(lw.detach().index_select(0, keep), descending=True))
        return self.cap(merge_sorted(state.select(order), o.merge_threshold, o.merge_rounds, keep_label), capacity)

    def extract(self, state: MixtureState) -> Tensor:
        """Bool mask ``(J,)`` of components reported as targets (weight above ``extract_threshold``)."""
        lw = state.log_weight
        return state.mask & (lw > scalar(math.log(self.options.extract_threshold), lw))


PairLogLik = Callable[[Tensor, Tensor], Tensor]
"""``pair_loglik(jj, kk) → (G,)`` of :meth:`GMPHD.update`: a log-likelihood ratio per (component, measurement) pair."""


class _Components(NamedTuple):
    """What :meth:`GMPHD.update` weighs each pair with, per component (``J``): ``z_hat (J, m)``, ``S (J, m, m)``,
    the Kalman factors ``gain`` of ``S`` and ``gain_pos`` of its position block (the robust velocity: else None),
    ``base (J,)`` ``log p_D w_j`` (times ``1 − ε`` with velocity outliers), ``base_pos (J,)`` the position-only
    term's ``log p_D w_j ε κ_v`` (or None), ``mask (J,)`` and the gate ``γ``."""

    z_hat: Tensor
    S: Tensor
    gain: KalmanGain
    gain_pos: KalmanGain | None
    base: Tensor
    base_pos: Tensor | None
    mask: Tensor
    gate: float


class _PairWeights(NamedTuple):
    """The gated pairs ``(jj, kk) (G,)`` ordered by component, then measurement, their posterior log-weights
    ``(G,)``, ``use_pos (G,)`` (the position-only update wins; None without velocity outliers), the
    denominators ``log_den (M,)`` and the label support ``(L,)`` (None unless asked)."""

    jj: Tensor
    kk: Tensor
    log_weight: Tensor
    use_pos: Tensor | None
    log_den: Tensor
    support: Tensor | None


def _dense_pairs(c: _Components, z: Tensor, log_kappa: Tensor, pair_loglik: PairLogLik | None,
                 label_index: tuple[Tensor, int] | None) -> _PairWeights:
    """Every (component, measurement) pair at once, ``(J, M)`` (a small frame: fewer operations than the grid)."""
    J, M = c.z_hat.shape[0], z.shape[0]
    neg_inf = scalar(NEG_INF, c.base)
    gate = scalar(c.gate, c.base)
    nu = innovation_pairs(z, c.z_hat)                                         # (J, M, m) or m × (J, M)
    nis, loglik = innovations_likelihood(c.gain, nu)          # (J, M)  νᵀ S⁻¹ ν, log N(ν; 0, S)
    use_pos = None
    if c.gain_pos is not None:
        p = c.gain_pos.chol.shape[-1]
        nis_p, loglik_p = innovations_likelihood(c.gain_pos, nu[..., :p] if isinstance(nu, Tensor) else nu[:p])
        gated = (nis_p <= gate) & c.mask.unsqueeze(1)
        with_v, without_v = c.base.unsqueeze(1) + loglik, c.base_pos.unsqueeze(1) + loglik_p
        log_num = torch.where(gated, torch.logaddexp(with_v, without_v), neg_inf)
    else:
        gated = (nis <= gate) & c.mask.unsqueeze(1)
        log_num = torch.where(gated, c.base.unsqueeze(1) + loglik, neg_inf)
    if pair_loglik is not None:
        every_j = torch.arange(J, device=z.device).repeat_interleave(M)
        log_num = log_num + pair_loglik(every_j, torch.arange(M, device=z.device).repeat(J)).view(J, M)
    den = torch.logaddexp(log_kappa, torch.logsumexp(log_num, 0)) if J else log_kappa
    support = None
    if label_index is not None:
        support = torch.zeros(label_index[1], dtype=c.base.dtype, device=c.base.device)
        if J:
            support = support.index_add(0, label_index[0], (log_num - log_kappa.unsqueeze(0)).exp().sum(1))
    flat = gated.view(-1).nonzero().view(-1)          # row-major: ordered by component, then measurement
    jj, kk = flat.div(M, rounding_mode="floor"), flat.remainder(M)
    if c.gain_pos is not None:
        use_pos = (without_v > with_v).view(-1).index_select(0, flat)
    return _PairWeights(jj, kk, log_num.view(-1).index_select(0, flat) - den.index_select(0, kk), use_pos, den,
                        support)


def _sparse_pairs(c: _Components, z: Tensor, log_kappa: Tensor, pair_loglik: PairLogLik | None,
                 label_index: tuple[Tensor, int] | None) -> _PairWeights:
    """The gated pairs from the grid index (:func:`gated_pairs`), weighed pair by pair; each measurement's
    denominator a segment sum over its pairs (:func:`log_normaliser`)."""
    m = z.shape[1]
    robust = c.gain_pos is not None
    p = c.gain_pos.chol.shape[-1] if robust else m
    jj, kk = gated_pairs(c.z_hat, c.S, c.gain.chol_inv, z, c.gate, c.mask, p)
    nu = z.index_select(0, kk) - c.z_hat.index_select(0, jj)             # (G, m)
    nis = whitened_sq_norms(c.gain.chol_inv.index_select(0, jj), nu.unsqueeze(1))
    log_num = c.base.index_select(0, jj) + gaussian_log_likelihood(
        nis[-1].squeeze(-1), log_det_from_cholesky(c.gain.chol).index_select(0, jj), m)
    use_pos = None
    if robust:                        # the first p entries' NIS against S's leading block (whitened_sq_norms)
        without_v = c.base_pos.index_select(0, jj) + gaussian_log_likelihood(
            nis[p - 1].squeeze(-1), log_det_from_cholesky(c.gain_pos.chol).index_select(0, jj), p)
        use_pos = without_v > log_num
        log_num = torch.logaddexp(log_num, without_v)
    if pair_loglik is not None:
        log_num = log_num + pair_loglik(jj, kk)
    den = log_normaliser(kk, log_num, log_kappa)
    support = None
    if label_index is not None:
        support = torch.zeros(label_index[1], dtype=c.base.dtype, device=c.base.device).index_add(
            0, label_index[0].index_select(0, jj), (log_num - log_kappa.index_select(0, kk)).exp())
    return _PairWeights(jj, kk, log_num - den.index_select(0, kk), use_pos, den, support)


def gated_pairs(z_hat: Tensor, S: Tensor, chol_inv: Tensor, z: Tensor, gate: float, mask: Tensor,
                gate_dim: int) -> tuple[Tensor, Tensor]:
    """The (component, measurement) pairs inside the gate, ``(jj, kk)`` two ``(G,)`` long tensors ordered by
    component, then measurement (a stop-gradient selection).

    ``z_hat (J, m)`` predicted measurements, ``S (J, m, m)`` their covariances, ``chol_inv (J, m, m)`` the
    inverses of the Cholesky factors ``L`` of ``S``, ``z (M, m)``, ``mask (J,)`` live components. A pair is
    inside the gate when ``ν_gᵀ S_g⁻¹ ν_g ≤ γ`` for the leading ``gate_dim`` coordinates ``g`` of ``ν = z_k − ẑ_j``
    (the whole ``ν``, or its position alone); that NIS is ``‖(L⁻¹ ν)_g‖²``, ``L⁻¹`` being lower triangular.

    Candidates come from a grid index of the measurements (:func:`~torchtrack.association.grid.disc_candidates`)
    with the radius ``r_j = √(γ λ_max(S_j,pp))``, ``pp`` the leading ``min(m, 2)`` coordinates (the position):
    the marginal NIS of a sub-vector is at most the whole's (Schur complement), and ``ν_pᵀ S_pp⁻¹ ν_p ≥ ‖ν_p‖² /
    λ_max(S_pp)``, so an in-gate pair has ``‖ν_p‖ ≤ r_j`` and no in-gate pair is missed. Only the candidates
    within ``r_j`` are tested exactly; memory follows the candidates, not ``J M``.
    """
    p = min(z.shape[1], 2)
    with torch.no_grad():
        a, c = S[:, 0, 0], S[:, p - 1, p - 1]
        b = S[:, p - 1, 0] if p == 2 else torch.zeros_like(a)             # the lower triangle, as Cholesky's
        lam = (a + c) * 0.5 + torch.sqrt(((a - c) * 0.5).pow(2) + b.pow(2))    # λ_max of the 2 × 2 block
        radius = torch.where(mask, torch.sqrt(lam * gate) * (1 + 1e-6), torch.full_like(lam, -1.0))
        pos_hat, pos = _plane(z_hat[:, :p]), _plane(z[:, :p])
        jj, kk = disc_candidates(pos_hat, radius, pos)
        near = (squared_norm(pos.index_select(0, kk) - pos_hat.index_select(0, jj))
                <= radius.index_select(0, jj).pow(2)).nonzero().squeeze(1)
        jj, kk = jj.index_select(0, near), kk.index_select(0, near)
        nu = z[kk, :gate_dim] - z_hat[jj, :gate_dim]
        nis = whitened_sq_norms(chol_inv[:, :gate_dim, :gate_dim].index_select(0, jj), nu.unsqueeze(1))[-1].squeeze(-1)
        inside = (nis <= gate).nonzero().squeeze(1)
        jj, kk = jj.index_select(0, inside), kk.index_select(0, inside)
        order = torch.argsort(jj * z.shape[0] + kk)
        return jj.index_select(0, order), kk.index_select(0, order)


def _plane(x: Tensor) -> Tensor:
    """``x (K, 1 or 2)`` as points of the plane (a 1-D coordinate on the line ``y = 0``)."""
    return x if x.shape[1] == 2 else torch.cat([x, torch.zeros_like(x)], 1)


def log_normaliser(index: Tensor, log_term: Tensor, log_kappa: Tensor) -> Tensor:
    """``log(κ_k + Σ_{pairs of k} exp(log_term))`` per measurement ``k``, ``(M,)``: the update's denominator as a
    segment sum over the gated pairs, ``index (G,)`` their measurements, ``log_term (G,)``, ``log_kappa (M,)``.
    Each segment is shifted by its (detached) maximum, so nothing overflows and the gradient is exact."""
    shift = torch.scatter_reduce(log_kappa.detach().contiguous(), 0, index, log_term.detach(), "amax")
    total = torch.exp(log_kappa - shift).index_add(0, index, torch.exp(log_term - shift.index_select(0, index)))
    return shift + torch.log(total)


def _within_reach(mean: Tensor, cov: Tensor, threshold: float) -> tuple[Tensor, Tensor]:
    """Pairs ``(i, j)`` (two ``(K,)`` index tensors) with ``j < i`` and ``(m_i − m_j)ᵀ P_i⁻¹ (m_i − m_j) ≤ U``.

    Pairs are first screened on the position block (the first ``min(n, 2)`` coordinates): the full
    Mahalanobis distance is at least ``‖Δp‖² / λ_max(P_i,pos) ≥ ‖Δp‖² / tr(P_i,pos)``, so only pairs
    passing that bound are solved exactly (through Cholesky factors), keeping the exact test sparse. The screen
    looks only at the grid cells near each component (:func:`~torchtrack.association.grid.disc_candidates`),
    so its memory follows the pairs that are near, not ``J²``.
    """
    k = min(mean.shape[1], 2)
    lam = torch.diagonal(cov[:, :k, :k], dim1=-2, dim2=-1).sum(-1)
    pos = _plane(mean[:, :k])
    bound = lam * scalar(threshold, lam) * scalar(1 + 1e-4, lam)              # squared screening radius of i
    ii, jj = disc_candidates(pos, bound.sqrt(), pos)
    d2 = squared_norm(pos.index_select(0, ii) - pos.index_select(0, jj))
    near = ((jj < ii) & (d2 <= bound.index_select(0, ii))).nonzero().view(-1)
    ii, jj = ii.index_select(0, near), jj.index_select(0, near)
    if ii.numel():
        L, _ = torch.linalg.cholesky_ex(cov.index_select(0, ii))
        y = torch.linalg.solve_triangular(L, (mean.index_select(0, jj) - mean.index_select(0, ii)).unsqueeze(-1),
                                          upper=False)
        ok = (y.pow(2).sum((-1, -2)) <= scalar(threshold, y)).nonzero().view(-1)
        ii, jj = ii.index_select(0, ok), jj.index_select(0, ok)
    return ii, jj


def merge(state: MixtureState, threshold: float, rounds: int = 3, keep_label: Tensor | None = None) -> MixtureState:
    """Merge a mixture by a bounded number of vectorised greedy rounds (Vo & Ma 2006, Table II).

    Components are ordered by weight. Component ``i`` is *within reach* of ``j`` when
    ``(m_i − m_j)ᵀ P_i⁻¹ (m_i − m_j) ≤ U``. Each round, the live components with no live
    higher-weight component within reach become *leaders*; every live non-leader with a leader within
    reach joins its highest-weight one. Leftovers after ``rounds`` rounds stay on their own. Groups
    are moment-matched (weights add, mean and covariance match, label of the leader)::

        w = Σ wᵢ,  m = Σ wᵢ mᵢ / w,  P = Σ wᵢ (Pᵢ + (mᵢ − m)(mᵢ − m)ᵀ) / w

    This equals the sequential greedy merge except when a component is within reach of two leaders
    of which the heavier only becomes a leader in a later round. Membership is a stop-gradient
    selection; the moment matching is differentiable.

    ``state`` must be compacted (every slot live, as :meth:`GMPHD.prune` leaves it).

    With ``keep_label (P,)`` (the labels reported at the previous frame), a group containing one of those
    labels keeps it (the highest-weight such member's) instead of the leader's label, so an established
    identity is not taken over by a younger duplicate merging into it.
    """
    if state.size <= 1 or threshold <= 0:
        return state
    return merge_sorted(state.select(torch.argsort(state.log_weight.detach(), descending=True)), threshold, rounds,
                        keep_label)


def merge_sorted(state: MixtureState, threshold: float, rounds: int = 3, keep_label: Tensor | None = None
                 ) -> MixtureState:
    """:func:`merge` of a compacted mixture already ordered by decreasing weight."""
    if state.size <= 1:
        return state
    J = state.size
    mean, cov, log_w = state.mean, state.cov, state.log_weight
    # membership from detached tensors: a selection without gradient (cheaper than a no_grad block)
    idx = torch.arange(J, device=mean.device)
    if J <= DENSE_MERGE:
        owner = _owners_dense(_reach_matrix(mean.detach(), cov.detach(), threshold), rounds)
    else:
        owner = _owners_sparse(mean.detach(), cov.detach(), threshold, rounds)
        if owner is None:
            return state
    is_head = owner == idx
    heads_up_to = torch.cumsum(is_head, 0)          # group g of a head = number of heads up to it, minus 1
    G = int(heads_up_to[-1])
    gid = heads_up_to.index_select(0, owner) - 1
    if G == J:
        return state
    w_max = log_w.max()
    w = torch.exp(log_w - w_max)                                             # (J,)
    n = mean.shape[1]
    if J <= DENSE_MERGE:   # group sums as products with the (G, J) membership matrix W[g, j] = w_j [j in g]
        W = torch.zeros(G, J, dtype=w.dtype, device=w.device).index_put_((gid, idx), w)
        wsum = W.sum(1)                                                      # (G,)
        Wn = W / wsum.unsqueeze(1)
        mu = torch.mm(Wn, mean)                                              # (G, n)
    else:
        wsum = torch.zeros(G, dtype=w.dtype, device=w.device).index_add_(0, gid, w)
        mu = torch.zeros(G, n, dtype=w.dtype, device=w.device).index_add_(0, gid, w.unsqueeze(1) * mean)
        mu = mu / wsum.unsqueeze(1)
    d = mean - mu.index_select(0, gid)
    spread = (cov + d.unsqueeze(-1) * d.unsqueeze(-2)).view(J, n * n)       # P_i + (m_i − m)(m_i − m)ᵀ
    if J <= DENSE_MERGE:
        P = torch.mm(Wn, spread).view(G, n, n)
    else:
        P = (torch.zeros(G, n * n, dtype=w.dtype, device=w.device).index_add_(0, gid, w.unsqueeze(1) * spread)
             / wsum.unsqueeze(1)).view(G, n, n)
    label = state.label[is_head]
    if keep_label is not None and keep_label.numel():
        with torch.no_grad():
            key = labels_in(state.label, keep_label).to(w.dtype) * 2.0 + w / wsum.index_select(0, gid)
            best = torch.full((G,), -1.0, dtype=w.dtype, device=w.device).scatter_reduce(0, gid, key, "amax")
            win = as_rows(key == best.index_select(0, gid))
            label = label.clone().scatter_(0, gid.index_select(0, win), state.label.index_select(0, win))
    return MixtureState(torch.log(wsum) + w_max, mu, P, label,
                        torch.ones(G, dtype=torch.bool, device=w.device))


def _owners_sparse(mean: Tensor, cov: Tensor, threshold: float, rounds: int) -> Tensor | None:
    """The greedy leader rounds of :func:`merge` on screened candidate pairs; None when nothing merges."""
    J = mean.shape[0]
    ii, jj = _within_reach(mean, cov, threshold)   # i within reach of heavier j
    if ii.numel() == 0:
        return None
    big = torch.full((J,), J, dtype=torch.long, device=mean.device)
    # amin over the candidates: a non-candidate pair offers J, the initial value (no bool indexing)
    none = scalar(J, jj)
    owner = torch.arange(J, device=mean.device)
    alive = torch.ones(J, dtype=torch.bool, device=mean.device)
    for _ in range(rounds):
        live = alive.index_select(0, ii) & alive.index_select(0, jj)
        # leaders: alive, with no alive heavier component within reach
        blocked = torch.zeros(J, dtype=torch.long, device=mean.device).scatter_reduce(0, ii, live.long(), "amax")
        leader = alive & (blocked == 0)
        cand = alive.index_select(0, ii) & leader.index_select(0, jj)
        first = big.scatter_reduce(0, ii, torch.where(cand, jj, none), "amin")   # heaviest leader within reach
        joins = alive & ~leader & (first < J)
        owner = torch.where(joins, first, owner)
        alive = alive & ~leader & ~joins
        if not bool(alive.any()):
            break
    return owner


SCENE_COMPONENTS = 2
"""``k`` of :meth:`GMPHD.capacity_for`: components kept per measurement and per live label. After the merge a
target holds one or two components (its missed-detection and detected hypotheses rarely stay apart) and a
measurement adds at most one birth, so ``2 (M + L)`` leaves room for every live label's components."""


DENSE_MERGE = 128
"""Up to this many components the merge tests every pair at once (one batched solve, few operations);
above it, pairs are screened on positions first (:func:`_within_reach`, memory ``O(candidates)``)."""


def _reach_matrix(mean: Tensor, cov: Tensor, threshold: float) -> Tensor:
    """Bool ``(J, J)``: ``[i, j]`` when ``j < i`` and ``(m_i − m_j)ᵀ P_i⁻¹ (m_i − m_j) ≤ U`` (every pair in one
    batched triangular solve ``L_i⁻¹ [m_1 − m_i, …, m_J − m_i]``)."""
    L, _ = torch.linalg.cholesky_ex(cov)
    diff = (mean.unsqueeze(0) - mean.unsqueeze(1)).transpose(1, 2)              # [i, :, j] = m_j − m_i
    y = torch.linalg.solve_triangular(L, diff, upper=False)                    # (J, n, J)
    return torch.tril(y.pow(2).sum(1) <= scalar(threshold, y), diagonal=-1)


def _owners_dense(reach: Tensor, rounds: int) -> Tensor:
    """The greedy leader rounds of :func:`merge` on a dense reach matrix; ``owner (J,)`` per component."""
    owner = torch.arange(reach.shape[0], device=reach.device)
    alive = None                                   # every component, in the first round (no mask to apply)
    live = reach                                   # [i, j]: alive heavier j within reach of i
    for _ in range(rounds):
        blocked = live.any(1)                      # an alive heavier component within reach: not a leader
        if alive is not None:
            blocked = blocked & alive
        leader = ~blocked if alive is None else alive & ~blocked
        has, first = (live & leader.unsqueeze(0)).max(1)     # first (heaviest) leader within reach
        owner = torch.where(blocked & has, first, owner)     # joins its leader
        alive = blocked & ~has
        if not bool(alive.any()):
            break
        live = reach & alive.unsqueeze(0)
    return owner
