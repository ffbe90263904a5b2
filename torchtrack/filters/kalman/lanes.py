"""Linear Kalman filter steps in a structure-of-arrays ("lanes") layout, for many tracks at once.

Storage is **batch last**: ``B`` tracks are a mean ``x (n, B)`` and a covariance ``P (n, n, B)``, and
the model matrices ``F (n, n)``, ``Q (n, n)``, ``H (m, n)``, ``R (m, m)`` are shared by all tracks.
Every small-matrix product is then either one GEMM of a shared matrix against all lanes, or an
elementwise (rank-one) update over contiguous lanes — never a batched GEMM of tiny per-track
matrices, whose per-matrix overhead dominates the batch-first formulation. The ``m × m`` innovation
covariance is factorised and solved with unrolled Cholesky arithmetic per lane (no inverse).

Equations (Bar-Shalom, Li & Kirubarajan 2001, §5.2; the maneuver paper, eq. 3–7), ``C = P⁻ Hᵀ``::

    predict   x⁻ = F x,   P⁻ = F P Fᵀ + Q                                      (3), (4)
    update    S = H C + R = L Lᵀ,   Kᵀ = L⁻ᵀ L⁻¹ Cᵀ,   ν = z − H x⁻              (5), (6)
              x⁺ = x⁻ + K ν
              A P⁻ = P⁻ − K Cᵀ                     (A = I − K H, and H P⁻ = Cᵀ)
              P⁺ = A P⁻ Aᵀ + K R Kᵀ = A P⁻ − (A P⁻ Hᵀ − K R) Kᵀ    (Joseph form of (7), A never formed)
              NIS = |L⁻¹ ν|²,   log ℓ = −½ (NIS + 2 Σᵢ log Lᵢᵢ + m log 2π)

:func:`step` (predict + update) is plain tensor code: differentiable, and compiled by
``torch.compile`` into one fused loop over the lanes when :func:`compiled_step` is used.
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.gaussian import (
    LOG_2PI,
    cholesky_entries,
    solve_lower_entries,
    solve_upper_t_entries,
    symmetrize,
)

# largest state / measurement sizes for which the unrolled per-lane arithmetic is used
MAX_STATE = 8
MAX_MEAS = 4


class LaneUpdate(NamedTuple):
    """Output of :func:`update`; ``B`` lanes."""

    mean: Tensor            # (n, B)
    cov: Tensor             # (n, n, B)
    innovation: Tensor      # (m, B)
    innovation_cov: Tensor  # (m, m, B)
    nis: Tensor             # (B,) 0 where missing
    log_likelihood: Tensor  # (B,) 0 where missing
    ok: Tensor              # (B,) bool: Cholesky of S succeeded


def _left(A: Tensor, X: Tensor) -> Tensor:
    """``[i, …] = Σ_k A[i, k] X[k, …]`` for a shared ``A``: one GEMM over all lanes."""
    return (A @ X.reshape(X.shape[0], -1)).reshape(A.shape[0], *X.shape[1:])


def predict(x: Tensor, P: Tensor, F: Tensor, Q: Tensor) -> tuple[Tensor, Tensor]:
    """``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q`` for ``x (n, B)``, ``P (n, n, B)``, ``F, Q (n, n)``."""
    return _left(F, x), symmetrize(F @ _left(F, P) + Q.unsqueeze(-1), (0, 1))   # F @ X: X Fᵀ per lane


def update(x: Tensor, P: Tensor, z: Tensor, present: Tensor | None, H: Tensor, R: Tensor) -> LaneUpdate:
    """Joseph-form measurement update of ``x (n, B)``, ``P (n, n, B)`` with ``z (m, B)``.

    ``present (B,)`` bool marks lanes with a measurement (``None``: all); elsewhere the state passes
    through and NIS / log-likelihood are 0. ``z`` must be finite (zero-filled where missing).
    """
    m = H.shape[0]
    C = H @ P                                                       # (n, m, B): (P Hᵀ)[i, r]
    S = symmetrize(_left(H, C) + R.unsqueeze(-1), (0, 1))
    L, ok = cholesky_entries(S)
    nu = z - _left(H, x)                                            # (m, B)
    Ct = C.transpose(0, 1)                                          # (m, n, B): rows of Cᵀ = H P
    Kt = solve_upper_t_entries(L, solve_lower_entries(L, list(Ct.unbind(0))))     # rows of Kᵀ, each (n, B)
    nu_rows = list(nu.unbind(0))
    mean = _dot([x] + [Kt[r] * nu_rows[r] for r in range(m)], x)
    AP = P
    for r in range(m):
        AP = torch.addcmul(AP, Kt[r].unsqueeze(1), Ct[r].unsqueeze(0), value=-1)   # A P = P − K Cᵀ
    D = H @ AP                                                      # (n, m, B): (A P Hᵀ)[i, r]
    KRt = _left(R.transpose(0, 1), torch.stack(Kt))                 # (m, n, B): rows of (K R)ᵀ
    cov = AP
    for r in range(m):
        cov = torch.addcmul(cov, (D[:, r] - KRt[r]).unsqueeze(1), Kt[r].unsqueeze(0), value=-1)
    cov = symmetrize(cov, (0, 1))
    nis = _dot([w * w for w in solve_lower_entries(L, nu_rows)], x)
    loglik = -0.5 * (nis + m * LOG_2PI) - _dot([torch.log(L[r][r]) for r in range(m)], x)
    if present is not None:
        mean = torch.where(present, mean, x)
        cov = torch.where(present, cov, P)
        nis = torch.where(present, nis, torch.zeros_like(nis))
        loglik = torch.where(present, loglik, torch.zeros_like(loglik))
    return LaneUpdate(mean, cov, nu, S, nis, loglik, ok)


def step(x: Tensor, P: Tensor, z: Tensor, present: Tensor | None, F: Tensor, Q: Tensor, H: Tensor,
         R: Tensor, predict_first: bool = True) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Predict (unless not ``predict_first``) then update; returns ``(x⁺, P⁺, nis, log ℓ, ok)``."""
    if predict_first:
        x, P = predict(x, P, F, Q)
    u = update(x, P, z, present, H, R)
    return u.mean, u.cov, u.nis, u.log_likelihood, u.ok


Pattern = tuple[tuple[int, ...], ...]


def structure(M: Tensor) -> Pattern:
    """Structural codes of a model matrix: 0 where an entry is exactly 0, 1 where exactly 1, else 2."""
    return tuple(tuple(0 if v == 0 else 1 if v == 1 else 2 for v in row) for row in M.tolist())


def _dot(terms: list[Tensor | None], like: Tensor) -> Tensor:
    """Sum of the terms that are not structurally zero (``None``)."""
    kept = [t for t in terms if t is not None]
    return sum(kept[1:], kept[0]) if kept else torch.zeros_like(like)


def _times(M: Tensor, code: Pattern | None, i: int, k: int, v: Tensor) -> Tensor | None:
    """``M[i, k] · v``: ``None`` for a structural zero, ``v`` for a structural one."""
    c = 2 if code is None else code[i][k]
    return None if c == 0 else v if c == 1 else M[i, k] * v


def _plus(v: Tensor, M: Tensor, code: Pattern | None, i: int, k: int) -> Tensor:
    """``v + M[i, k]``, skipping a structural zero."""
    return v if code is not None and code[i][k] == 0 else v + M[i, k]


def fused_step(x: Tensor, P: Tensor, z: Tensor, present: Tensor | None, F: Tensor, Q: Tensor, H: Tensor,
               R: Tensor, x_out: Tensor, P_out: Tensor, nis_out: Tensor, loglik_acc: Tensor, ok_out: Tensor,
               predict_first: bool = True, pattern: tuple[Pattern, Pattern, Pattern, Pattern] | None = None) -> None:
    """:func:`step` written entry by entry: every quantity is one ``(B,)`` lane vector, so
    ``torch.compile`` emits a single loop over the lanes with all ``n × n`` arithmetic in registers.
    Writes ``x⁺ → x_out (n, B)``, ``P⁺ → P_out (n, n, B)``, ``nis → nis_out (B,)``, ``ok → ok_out (B,)``
    and adds log ℓ to ``loglik_acc (B,)`` (no autograd).

    Same equations as :func:`predict` / :func:`update`; covariances are formed on and above the
    diagonal and mirrored (exactly symmetric) instead of averaged with their transpose. ``pattern``
    (:func:`structure` of ``F, Q, H, R``; compile-time constants) drops products with structural zeros
    and ones, e.g. half of ``F`` and three quarters of ``H`` for constant velocity.
    """
    pF, pQ, pH, pR = pattern if pattern is not None else (None,) * 4
    n, m = x.shape[0], H.shape[0]
    X = [x[i] for i in range(n)]
    Pm = [[P[i, j] for j in range(n)] for i in range(n)]
    if predict_first:
        X = [_dot([_times(F, pF, i, k, X[k]) for k in range(n)], X[0]) for i in range(n)]
        FP = [[_dot([_times(F, pF, i, k, Pm[k][j]) for k in range(n)], X[0]) for j in range(n)] for i in range(n)]
        up = {(i, j): _plus(_dot([_times(F, pF, j, k, FP[i][k]) for k in range(n)], X[0]), Q, pQ, i, j)
              for i in range(n) for j in range(i, n)}
        Pm = [[up[min(i, j), max(i, j)] for j in range(n)] for i in range(n)]
    C = [[_dot([_times(H, pH, r, j, Pm[i][j]) for j in range(n)], X[0]) for r in range(m)] for i in range(n)]
    S = [[_plus(_dot([_times(H, pH, r, i, C[i][s]) for i in range(n)], X[0]), R, pR, r, s) for s in range(m)]
         for r in range(m)]
    S = [[S[max(r, s)][min(r, s)] for s in range(m)] for r in range(m)]
    L, ok = cholesky_entries(S)
    nu = [z[r] - _dot([_times(H, pH, r, j, X[j]) for j in range(n)], X[0]) for r in range(m)]
    K = [solve_upper_t_entries(L, solve_lower_entries(L, C[i])) for i in range(n)]                           # rows of K
    mean = [X[i] + _dot([K[i][r] * nu[r] for r in range(m)], X[0]) for i in range(n)]
    AP = [[Pm[i][j] - _dot([K[i][r] * C[j][r] for r in range(m)], X[0]) for j in range(n)] for i in range(n)]
    E = [[_dot([_times(H, pH, r, j, AP[i][j]) for j in range(n)], X[0])
          - _dot([_times(R, pR, s, r, K[i][s]) for s in range(m)], X[0]) for r in range(m)]
         for i in range(n)]                                                                     # A P Hᵀ − K R
    up = {(i, j): AP[i][j] - _dot([E[i][r] * K[j][r] for r in range(m)], X[0])
          for i in range(n) for j in range(i, n)}
    cov = [[up[min(i, j), max(i, j)] for j in range(n)] for i in range(n)]
    nis = _dot([w * w for w in solve_lower_entries(L, nu)], X[0])
    loglik = -0.5 * (nis + m * LOG_2PI) - _dot([torch.log(L[r][r]) for r in range(m)], X[0])
    if present is not None:
        mean = [torch.where(present, a, b) for a, b in zip(mean, X)]
        cov = [[torch.where(present, a, b) for a, b in zip(ra, rb)] for ra, rb in zip(cov, Pm)]
        nis = torch.where(present, nis, torch.zeros_like(nis))
        loglik = torch.where(present, loglik, torch.zeros_like(loglik))
    x_out.copy_(torch.stack(mean))
    P_out.copy_(torch.stack([e for row in cov for e in row]).view(n, n, -1))
    nis_out.copy_(nis)
    loglik_acc.add_(loglik)
    ok_out.copy_(ok)


class Compiled:
    """``torch.compile(fn, **options)``, made at the first call; where compiling or running it fails (no
    C compiler, unsupported platform) a warning naming ``what`` is issued and ``fn`` runs eagerly (same
    results, only slower) from then on. ``dynamic_args``: arguments whose last dimension (the lanes) is
    marked dynamic, so that one kernel serves every track count."""

    def __init__(self, fn, what: str, dynamic_args: tuple[int, ...] = (), **options):
        self.fn, self.what, self.dynamic_args, self.options = fn, what, dynamic_args, options
        self.compiled = None
        self.failed = False

    def __call__(self, *args):
        if not self.failed:
            for i in self.dynamic_args:
                if args[i] is not None:
                    torch._dynamo.maybe_mark_dynamic(args[i], args[i].dim() - 1)
            try:
                if self.compiled is None:
                    self.compiled = torch.compile(self.fn, **self.options)
                return self.compiled(*args)
            except Exception as err:  # noqa: BLE001 - any backend failure means: run eagerly
                warnings.warn(f"torch.compile failed for {self.what} ({err}); running eagerly", stacklevel=2)
                self.failed = True
        return self.fn(*args)


# one fused loop: a large fusion group, stacked outputs stored by that loop, and few intermediates
# spilled to memory (inlining everything makes lowering blow up); shapes specialise per model
compiled_step = Compiled(fused_step, "the Kalman filter", dynamic_args=(0, 1, 2, 3, 8, 9, 10, 11, 12),
                         fullgraph=True, options={"max_fusion_size": 4096, "max_pointwise_cat_inputs": 1,
                                                  "realize_opcount_threshold": 60, "realize_reads_threshold": 8})
