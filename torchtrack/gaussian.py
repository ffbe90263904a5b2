"""Batched Gaussian algebra through Cholesky factors.

Shapes follow ``torch.distributions``: vectors are ``(*batch, n)``, covariances ``(*batch, n, n)``,
and batch dimensions broadcast. Nothing here forms an explicit inverse.

Notation (Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to Tracking and Navigation*,
ch. 5): predicted state ``x⁻, P⁻``; measurement ``z = H x + v``, ``v ~ N(0, R)``; innovation
``ν = z − H x⁻``; innovation covariance ``S = H P⁻ Hᵀ + R``; gain ``K = P⁻ Hᵀ S⁻¹``.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.errors import TorchtrackError

LOG_2PI = math.log(2.0 * math.pi)


class GaussianState(NamedTuple):
    """A batch of Gaussian densities: ``mean (*, n)``, ``cov (*, n, n)``."""

    mean: Tensor
    cov: Tensor


@functools.lru_cache(maxsize=256)
def _cached_scalar(value: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    with torch.inference_mode(False):       # usable in autograd graphs even when first made while streaming
        return torch.tensor(value, dtype=dtype, device=device)


def scalar(value: float, like: Tensor) -> Tensor:
    """A cached 0-dim tensor ``value`` of ``like``'s dtype and device (no gradient).

    ``x * scalar(c, x)`` computes exactly what ``x * c`` does (a Python number is cast to ``x``'s dtype)
    but with one tensor operation instead of five (the number is not converted on every call). Under
    ``torch.compile`` the constant is traced directly (the compiler folds it; it does not trace the cache).
    """
    if torch.compiler.is_compiling():
        return torch.tensor(float(value), dtype=like.dtype, device=like.device)
    return _cached_scalar(float(value), like.dtype, like.device)


def symmetrize(P: Tensor, dims: tuple[int, int] = (-1, -2)) -> Tensor:
    """``(P + Pᵀ) / 2`` over the matrix dimensions ``dims`` (the last two; ``(0, 1)`` for batch-last storage)."""
    return (P + P.transpose(*dims)) * scalar(0.5, P)


def chi2_quantile(p: float, dof: int) -> float:
    """The ``p`` quantile of χ²(``dof``): closed form ``−2 log(1 − p)`` for 2 dof, scipy otherwise;
    ``inf`` for ``p = 1``. Raises :class:`TorchtrackError` unless ``0 < p <= 1``."""
    if not 0.0 < p <= 1.0:
        raise TorchtrackError(f"chi-square quantile: probability must lie in (0, 1]; got {p!r}")
    if p == 1.0:
        return float("inf")
    if dof == 2:
        return -2.0 * math.log1p(-p)
    from scipy.stats import chi2

    return float(chi2.ppf(p, dof))


# Below this size, many small factorisations and triangular solves are done as unrolled
# elementwise arithmetic over the batch (LAPACK's per-matrix call overhead dominates otherwise).
SMALL_N = 4
SMALL_BATCH = 64


def _batch_size(*tensors: Tensor) -> int:
    """The largest number of matrices in the batches of ``tensors`` (from the shapes alone: no tensor
    operation and no ``torch.broadcast_shapes``, which cost microseconds per call; a loop, not a generator
    and ``math.prod``, for the common ``(batch, n, k)`` shapes: this runs several times per filter step)."""
    most = 1
    for t in tensors:
        shape = t.shape
        size = shape[0] if len(shape) == 3 else math.prod(shape[:-2])
        if size > most:
            most = size
    return most


def _is_small(A: Tensor, B: Tensor | None = None) -> bool:
    return A.shape[-1] <= SMALL_N and _batch_size(A, *(() if B is None else (B,))) >= SMALL_BATCH


def cholesky_entries(S) -> tuple[list[list[Tensor]], Tensor]:
    """Cholesky–Banachiewicz, unrolled for a small ``m``: ``S[i][j]`` are tensors of one shape (the
    batch, elementwise: entries of an ``(m, m, *)`` tensor, nested lists, or ``P[..., i, j]``).

    Returns the rows of per-entry factors ``L[i][j]``, ``j ≤ i``, and ``ok`` (the pivots were > 0); a
    failed pivot is replaced by 1 so that no NaN is produced (the caller raises).
    """
    m = len(S)
    L: list[list[Tensor]] = [[] for _ in range(m)]
    ok = torch.ones_like(S[0][0], dtype=torch.bool)
    for j in range(m):
        s = S[j][j]
        for k in range(j):
            s = s - L[j][k] * L[j][k]
        ok = ok & (s > 0)
        d = torch.sqrt(torch.where(s > 0, s, torch.ones_like(s)))
        for i in range(j, m):
            if i == j:
                L[j].append(d)
                continue
            t = S[i][j]
            for k in range(j):
                t = t - L[i][k] * L[j][k]
            L[i].append(t / d)
    return L, ok


def solve_lower_entries(L: list[list[Tensor]], rows: list[Tensor]) -> list[Tensor]:
    """Forward substitution ``L Y = B`` with ``L`` from :func:`cholesky_entries` and ``B`` given as
    its ``m`` rows (broadcasting against the entries of ``L``)."""
    out: list[Tensor] = []
    for i, b in enumerate(rows):
        for j in range(i):
            b = b - L[i][j] * out[j]
        out.append(b / L[i][i])
    return out


def solve_upper_t_entries(L: list[list[Tensor]], rows: list[Tensor]) -> list[Tensor]:
    """Back substitution ``Lᵀ X = Y`` with ``Y`` given as its rows."""
    m = len(rows)
    out: list[Tensor] = [rows[0]] * m
    for i in reversed(range(m)):
        b = rows[i]
        for j in range(i + 1, m):
            b = b - L[j][i] * out[j]
        out[i] = b / L[i][i]
    return out


def _cholesky_unrolled(P: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`cholesky_entries` on ``(*, n, n)``, stacked back into ``(*, n, n)``, and ``info`` (0 = ok)."""
    n = P.shape[-1]
    L, ok = cholesky_entries([[P[..., i, j] for j in range(n)] for i in range(n)])
    zero = torch.zeros_like(P[..., 0, 0])
    rows = [torch.stack([L[i][j] if j <= i else zero for j in range(n)], -1) for i in range(n)]
    return torch.stack(rows, -2), (~ok).to(torch.int32)


def _rows(B: Tensor) -> list[Tensor]:
    """The rows ``B[..., i, :]`` of ``B (*, n, k)``, as :func:`solve_lower_entries` takes them."""
    return [B[..., i, :] for i in range(B.shape[-2])]


def _entries(L: Tensor) -> list[list[Tensor]]:
    """The lower-triangular entries ``L[..., i, j, None]`` of ``L (*, n, n)`` (broadcasting against rows)."""
    return [[L[..., i, j, None] for j in range(i + 1)] for i in range(L.shape[-1])]


def cholesky(P: Tensor, what: str = "covariance", check: bool = True) -> Tensor:
    """Lower Cholesky factor ``L`` with ``L Lᵀ = P``; shape ``(*batch, n, n)``.

    With ``check`` a failed factorisation raises :class:`TorchtrackError` naming ``what`` (one host
    synchronisation); without it a failed factor is left as returned by ``cholesky_ex``.
    """
    L, info = _cholesky_unrolled(P) if _is_small(P) else torch.linalg.cholesky_ex(P)
    if check and bool(info.any()):
        bad = int((info != 0).sum())
        raise TorchtrackError(f"{what} is not positive definite ({bad} of {info.numel()} matrices failed "
                              "Cholesky factorisation)")
    return L


def solve_lower(L: Tensor, B: Tensor) -> Tensor:
    """``L⁻¹ B`` for lower-triangular ``L (*, n, n)`` and ``B (*, n, k)`` (batch dims broadcast)."""
    if _is_small(L, B):
        return torch.stack(solve_lower_entries(_entries(L), _rows(B)), -2)
    return torch.linalg.solve_triangular(L, B, upper=False)


def chol_solve(L: Tensor, B: Tensor) -> Tensor:
    """``P⁻¹ B`` from the Cholesky factor ``L`` of ``P``; ``B (*, n, k)``."""
    if _is_small(L, B):
        Le = _entries(L)
        return torch.stack(solve_upper_t_entries(Le, solve_lower_entries(Le, _rows(B))), -2)
    return torch.cholesky_solve(B, L)


def matmul(A: Tensor, B: Tensor) -> Tensor:
    """``A @ B`` that runs a shared 2-D ``A (n, k)`` against a batch ``B (*, k, m)`` as one GEMM
    (``(Bᵀ Aᵀ)ᵀ``) instead of ``torch.matmul``'s expand-and-batch; otherwise plain ``@``."""
    if A.dim() == 2 and B.dim() > 2:
        return (B.transpose(-1, -2) @ A.transpose(0, 1)).transpose(-1, -2)
    return A @ B


def log_det_from_cholesky(L: Tensor) -> Tensor:
    """``log |P|`` from the Cholesky factor ``L`` of ``P``; shape ``(*batch,)``."""
    return torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1) * scalar(2.0, L)


def mahalanobis_sq(x: Tensor, mean: Tensor, L: Tensor) -> Tensor:
    """Squared Mahalanobis distance ``(x − μ)ᵀ P⁻¹ (x − μ)`` with ``L = chol(P)``.

    Shapes: ``x, mean (*, n)``, ``L (*, n, n)`` broadcast; result ``(*,)``.
    """
    diff = (x - mean).unsqueeze(-1)
    batch = torch.broadcast_shapes(diff.shape[:-2], L.shape[:-2])
    y = solve_lower(L.expand(*batch, *L.shape[-2:]), diff.expand(*batch, *diff.shape[-2:]))
    return y.squeeze(-1).pow(2).sum(-1)


def gaussian_log_likelihood(nis: Tensor, log_det: Tensor, m: int) -> Tensor:
    """``log N(ν; 0, S) = −½ (νᵀ S⁻¹ ν + log |S| + m log 2π)`` from the NIS and ``log |S|`` (broadcast)."""
    return (nis + log_det + scalar(m * LOG_2PI, nis)) * scalar(-0.5, nis)


def log_prob_from_cholesky(x: Tensor, mean: Tensor, L: Tensor) -> Tensor:
    """``log N(x; μ, P)`` with ``L = chol(P)``; broadcasting shapes as :func:`mahalanobis_sq`."""
    return gaussian_log_likelihood(mahalanobis_sq(x, mean, L), log_det_from_cholesky(L), x.shape[-1])


def log_prob(x: Tensor, mean: Tensor, cov: Tensor) -> Tensor:
    """``log N(x; μ, Σ)``; ``x, mean (*, n)``, ``cov (*, n, n)``, broadcasting; result ``(*,)``."""
    return log_prob_from_cholesky(x, mean, cholesky(cov, "covariance"))


# The Kalman measurement update, in pieces that every filter shares (Bar-Shalom et al. 2001,
# eq. 5.2.3-9 … 5.2.3-18; the maneuver paper, eq. 5–7):
#
#     C = P⁻ Hᵀ,  S = H C + R = L Lᵀ                  innovation_cov, cholesky
#     W = C L⁻ᵀ,  K = C S⁻¹ = W L⁻¹                     kalman_gain
#     x⁺ = x⁻ + K ν
#     P⁺ = P⁻ − W Wᵀ  (= P⁻ − K S Kᵀ)  or the Joseph form (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ
#                                                        posterior_cov, joseph_cov
#     NIS = |L⁻¹ ν|²,  log ℓ = −½ (NIS + log |S| + m log 2π)       innovation(s)_likelihood
#
# S is never inverted: L⁻¹ is one triangular solve per factor, applied by (small) matrix products to
# C and to any number of innovations. For an EKF or UKF ``C`` is the cross-covariance of state and
# measurement and ``S`` its own. Engines with their own layout (kalman_lanes, kalman_axes, imm_cv)
# write the same steps on entries with cholesky_entries / solve_lower_entries.


def innovation_cov(cov: Tensor, H: Tensor, R: Tensor) -> tuple[Tensor, Tensor]:
    """``C = P Hᵀ (*, n, m)`` and the symmetrised ``S = H C + R (*, m, m)``; ``cov (*, n, n)``,
    ``H (*, m, n)`` (a shared 2-D ``H`` runs as one GEMM), ``R (*, m, m)``, batches broadcast."""
    C = cov @ H.transpose(-1, -2)
    return C, symmetrize(matmul(H, C) + R)


class KalmanGain(NamedTuple):
    """Result of :func:`kalman_gain`."""

    chol: Tensor      # (*, m, m) L, S = L Lᵀ
    chol_inv: Tensor  # (*, m, m) L⁻¹ (triangular), the whitening: |L⁻¹ ν|² = νᵀ S⁻¹ ν
    white_cross: Tensor  # (*, n, m) W = C L⁻ᵀ, so that K S Kᵀ = W Wᵀ
    gain: Tensor      # (*, n, m) K = C S⁻¹ = W L⁻¹


def kalman_gain(S: Tensor, C: Tensor, what: str = "innovation covariance S", check: bool = True) -> KalmanGain:
    """Cholesky factor ``L`` of ``S (*, m, m)``, its triangular inverse (one triangular solve per
    factor), ``W = C L⁻ᵀ`` and the gain ``K = W L⁻¹ = C S⁻¹`` for ``C (*, n, m)``; a failed
    factorisation raises :class:`TorchtrackError` naming ``what`` (with ``check``)."""
    return gain_from_cholesky(cholesky(S, what, check=check), C)


def gain_from_cholesky(L: Tensor, C: Tensor) -> KalmanGain:
    """:func:`kalman_gain` from an existing factor ``L`` of ``S``."""
    return _gain(L, solve_lower(L, _identity(L.shape[-1], L.dtype, L.device).expand_as(L)), C)


def leading_gain(gain: KalmanGain, C: Tensor) -> KalmanGain:
    """:func:`kalman_gain` of ``S``'s leading ``p × p`` block from ``S``'s own ``gain``, for ``C (*, n, p)``: the
    leading blocks of ``L`` and ``L⁻¹`` are that block's factor and its inverse (forward substitution on the
    first ``p`` rows reads nothing else), so no factorisation or solve is repeated — the same numbers as
    :func:`gain_from_cholesky` on ``L[..., :p, :p]``."""
    p = C.shape[-1]
    return _gain(gain.chol[..., :p, :p], gain.chol_inv[..., :p, :p], C)


def _gain(L: Tensor, Linv: Tensor, C: Tensor) -> KalmanGain:
    W = small_matmul(C, Linv.transpose(-1, -2))
    return KalmanGain(L, Linv, W, small_matmul(W, Linv))


@functools.lru_cache(maxsize=64)
def _identity(n: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """A cached ``n × n`` identity (read only: expanded, never written)."""
    with torch.inference_mode(False):
        return torch.eye(n, dtype=dtype, device=device)


def batched_matmul(A: Tensor, B: Tensor) -> Tensor:
    """``A @ B``, as ``torch.bmm`` itself for two 3-D operands with the same batch size (``@`` spends
    several tensor operations on broadcasting bookkeeping before it reaches the same kernel)."""
    if A.dim() == 3 and B.dim() == 3 and A.shape[0] == B.shape[0]:
        return torch.bmm(A, B)
    return A @ B


def small_matmul(A: Tensor, B: Tensor) -> Tensor:
    """``A @ B`` (batches broadcast); for many matrices with a short inner dimension (≤ ``SMALL_N``) the
    sum over it is unrolled into elementwise products (batched GEMMs of tiny matrices are slow)."""
    if A.shape[-1] > SMALL_N or _batch_size(A, B) < SMALL_BATCH:
        return batched_matmul(A, B)
    out = A[..., :, 0:1] * B[..., 0:1, :]
    for k in range(1, A.shape[-1]):
        out = out + A[..., :, k:k + 1] * B[..., k:k + 1, :]
    return out


def posterior_cov(P: Tensor, gain: KalmanGain) -> Tensor:
    """``P⁺ = P − W Wᵀ`` (``= P − K S Kᵀ``, the posterior of the optimal gain), symmetrised."""
    W = gain.white_cross
    return symmetrize(P - small_matmul(W, W.transpose(-1, -2)))


def innovation_likelihood(L: Tensor, nu: Tensor) -> tuple[Tensor, Tensor]:
    """NIS ``νᵀ S⁻¹ ν`` and ``log N(ν; 0, S)`` from ``L = chol(S) (*, m, m)`` and ``ν (*, m)``, batches
    broadcast (for many innovations per factor :func:`innovations_likelihood` is faster)."""
    nis = mahalanobis_sq(nu, torch.zeros_like(nu[..., :1]), L)
    return nis, gaussian_log_likelihood(nis, log_det_from_cholesky(L), nu.shape[-1])


def _planes_pay_off(pairs: int, m: int) -> bool:
    """Whether ``pairs`` innovations of size ``m`` are whitened faster entry by entry (:func:`whitened_sq_norms`)
    than by one batched product: from about ``128 m³`` pairs on the CPU (one thread: 1,000 pairs of size 2,
    8,000 of size 4); below that the entry-wise version's ``m(m+1)/2`` operations cost more than they save."""
    return pairs >= 128 * m**3


def innovation_pairs(z: Tensor, z_hat: Tensor) -> Tensor | list[Tensor]:
    """The innovations ``ν_ij = z_j − ẑ_i`` of every pair of ``ẑ (N, m)`` and ``z (M, m)``: an ``(N, M, m)`` tensor,
    or for many pairs (:func:`_planes_pay_off`) ``m`` planes ``(N, M)``, entry ``k`` of every innovation in plane
    ``k`` (contiguous: elementwise work on them is several times faster than on an ``(N, M, m)`` tensor, whose
    short last dimension broadcasts and reduces slowly). Either form goes to :func:`innovations_likelihood`."""
    m = z.shape[-1]
    if _planes_pay_off(z.shape[0] * z_hat.shape[0], m):
        return [z[:, k] - z_hat[:, k:k + 1] for k in range(m)]
    return z.unsqueeze(0) - z_hat.unsqueeze(1)


def _vector_entries(x: Tensor | list[Tensor]) -> list[Tensor]:
    """The entries of vectors ``x (*, m)`` as ``m`` tensors ``(*,)``; planes (a list, :func:`innovation_pairs`)
    are that already."""
    return [x[..., k] for k in range(x.shape[-1])] if isinstance(x, Tensor) else x


def squared_norm(x: Tensor | list[Tensor]) -> Tensor:
    """``Σ_k x_k²`` of vectors ``x (*, m)`` (or their ``m`` planes ``(*,)``) → ``(*,)``, entry by entry (a
    reduction over a short last dimension is several times slower on the CPU)."""
    entries = _vector_entries(x)
    total = entries[0] * entries[0]
    for e in entries[1:]:
        total = torch.addcmul(total, e, e)
    return total


def whitened_sq_norms(chol_inv: Tensor, nu: Tensor | list[Tensor]) -> list[Tensor]:
    """The running sums ``Σ_{i≤k} (L⁻¹ ν)_i²``, ``k = 0 … m−1``, ``(*, K)`` each, for a lower-triangular ``L⁻¹``
    (``chol_inv (*, m, m)``) and the innovations ``nu (*, K, m)`` or their ``m`` planes ``(*, K)``
    (:func:`innovation_pairs`).

    The last is the NIS ``νᵀ S⁻¹ ν``; the ``p``-th is that of the first ``p`` entries against the leading
    ``p × p`` block of ``S`` (its factor is ``L``'s leading block, and ``L⁻¹``'s leading block is its inverse).
    Entry by entry (``m(m+1)/2`` products): a batched product with ``m`` columns followed by a reduction over a
    last dimension of ``m`` is several times slower on the CPU."""
    nu = _vector_entries(nu)
    sums, total = [], None
    for i in range(len(nu)):
        white = chol_inv[..., i, 0].unsqueeze(-1) * nu[0]
        for k in range(1, i + 1):
            white = torch.addcmul(white, chol_inv[..., i, k].unsqueeze(-1), nu[k])
        total = white * white if total is None else torch.addcmul(total, white, white)
        sums.append(total)
    return sums


def innovations_nis(chol_inv: Tensor, nu: Tensor | list[Tensor]) -> Tensor:
    """NIS ``νᵀ S⁻¹ ν`` ``(*, k)`` of many innovations per factor: ``ν (*, k, m)`` or its ``m`` planes ``(*, k)``
    (:func:`innovation_pairs`) against the lower-triangular ``L⁻¹`` ``(*, m, m)``: entry by entry
    (:func:`whitened_sq_norms`) for planes and for many pairs, else by one batched product."""
    if isinstance(nu, Tensor):
        m = nu.shape[-1]
        if not _planes_pay_off(nu.numel() // max(m, 1), m):
            white = batched_matmul(nu, chol_inv.transpose(-1, -2))
            return (white * white).sum(-1)
    return whitened_sq_norms(chol_inv, nu)[-1]


def innovations_likelihood(gain: KalmanGain, nu: Tensor | list[Tensor]) -> tuple[Tensor, Tensor]:
    """:func:`innovation_likelihood` for many innovations per factor (:func:`innovations_nis`) → NIS and log ℓ
    ``(*, k)``."""
    nis = innovations_nis(gain.chol_inv, nu)
    m = nu.shape[-1] if isinstance(nu, Tensor) else len(nu)
    return nis, gaussian_log_likelihood(nis, log_det_from_cholesky(gain.chol).unsqueeze(-1), m)


def joseph_cov(P: Tensor, K: Tensor, H: Tensor, R: Tensor) -> Tensor:
    """Joseph-form posterior covariance ``(I − K H) P (I − K H)ᵀ + K R Kᵀ`` (symmetrised); valid for
    any gain. ``P (*, n, n)``, ``K (*, n, m)``, ``H (*, m, n)``, ``R (*, m, m)``."""
    A = torch.eye(P.shape[-1], dtype=P.dtype, device=P.device) - K @ H
    return symmetrize(A @ P @ A.transpose(-1, -2) + K @ matmul(R, K.transpose(-1, -2)))


class KalmanUpdate(NamedTuple):
    """Result of :func:`kalman_update`; shapes for state size ``n`` and measurement size ``m``."""

    mean: Tensor          # (*, n) posterior mean x⁺
    cov: Tensor           # (*, n, n) posterior covariance P⁺ (Joseph form, symmetrised)
    innovation: Tensor    # (*, m) ν = z − ẑ
    innovation_cov: Tensor  # (*, m, m) S
    nis: Tensor           # (*,) normalised innovation squared νᵀ S⁻¹ ν
    log_likelihood: Tensor  # (*,) log N(ν; 0, S)
    gain: Tensor          # (*, n, m) K


def kalman_update(mean: Tensor, cov: Tensor, z: Tensor, H: Tensor, R: Tensor,
                  z_pred: Tensor | None = None, check: bool = True) -> KalmanUpdate:
    """Kalman measurement update through a Cholesky factor of ``S`` (the equations above; Joseph form).

    ``ẑ = H x⁻``, or ``z_pred`` for an EKF. Shapes: ``mean (*, n)``, ``cov (*, n, n)``, ``z (*, m)``,
    ``H (*, m, n)``, ``R (*, m, m)``; all batch dimensions broadcast.
    """
    nu = z - (z_pred if z_pred is not None else matmul(H, mean.unsqueeze(-1)).squeeze(-1))
    C, S = innovation_cov(cov, H, R)
    g = kalman_gain(S, C, check=check)
    new_mean = mean + (g.gain @ nu.unsqueeze(-1)).squeeze(-1)
    nis, loglik = innovation_likelihood(g.chol, nu)
    return KalmanUpdate(new_mean, joseph_cov(cov, g.gain, H, R), nu, S, nis, loglik, g.gain)


def moment_match(log_weight: Tensor, mean: Tensor, cov: Tensor, dim: int = -1) -> tuple[Tensor, Tensor]:
    """Collapse a Gaussian mixture to one Gaussian with the same first two moments.

    ``μ = Σ wᵢ μᵢ``, ``Σ = Σ wᵢ (Σᵢ + (μᵢ − μ)(μᵢ − μ)ᵀ)`` with ``w = softmax(log_weight)``.

    Shapes: ``log_weight (*, K)``, ``mean (*, K, n)``, ``cov (*, K, n, n)`` with the mixture axis at
    ``dim`` of ``log_weight`` (the matching axis of ``mean``/``cov`` is ``dim-1``/``dim-2`` when
    ``dim`` is negative). Returns ``(*, n)`` and ``(*, n, n)``. Components with ``-inf`` log-weight
    are ignored.
    """
    if dim >= 0:
        dim = dim - log_weight.dim()
    w = torch.softmax(log_weight, dim=dim)
    mu = (w.unsqueeze(-1) * mean).sum(dim - 1)
    d = mean - mu.unsqueeze(dim - 1)
    spread = cov + d.unsqueeze(-1) * d.unsqueeze(-2)
    P = (w.unsqueeze(-1).unsqueeze(-1) * spread).sum(dim - 2)
    return mu, symmetrize(P)


def sample(mean: Tensor, cov: Tensor, generator: torch.Generator | None = None,
           sample_shape: tuple[int, ...] = ()) -> Tensor:
    """Draw ``x ~ N(μ, Σ)`` with shape ``(*sample_shape, *batch, n)``, reproducible via ``generator``."""
    L = cholesky(cov, "covariance")
    batch = torch.broadcast_shapes(mean.shape[:-1], L.shape[:-2])
    eps = torch.randn((*sample_shape, *batch, mean.shape[-1], 1), generator=generator, dtype=mean.dtype,
                      device=mean.device)
    return mean + (L @ eps).squeeze(-1)
