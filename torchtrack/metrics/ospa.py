"""OSPA (Schuhmacher, Vo & Vo 2008) and GOSPA (Rahmathullah, García-Fernández & Svensson 2017).

Both compare a set ``X`` (ground truth, ``|X| = n``) with a set ``Y`` (estimates, ``|Y| = m``) of points in
R^d through the cut-off distance ``d_c(x, y) = min(||x - y||, c)``. Sets of one frame, or a batch of frames,
live in fixed-capacity tensors with masks: ``X`` (*, N, d) with ``x_mask`` (*, N), ``Y`` (*, M, d) with
``y_mask`` (*, M); every leading index ``*`` (frames, Monte Carlo runs) is one pair of sets.

OSPA of order p (Schuhmacher et al. 2008, eq. (3)), for ``n <= m`` (swap otherwise)::

    d_p^(c)(X, Y) = ( (1/m) * ( min_pi sum_{i<=n} d_c(x_i, y_pi(i))^p + c^p (m - n) ) )^(1/p)

with 0 when both sets are empty; ``localisation`` and ``cardinality`` are the two terms inside, each raised
to 1/p as in the paper (so ``total^p = localisation^p + cardinality^p``).

GOSPA with ``alpha = 2`` (Rahmathullah et al. 2017, eq. (2) and Prop. 1)::

    d_p^(c,2)(X, Y) = ( min_gamma sum_{(i,j) in gamma} d(x_i, y_j)^p + c^p/2 (n + m - 2 |gamma|) )^(1/p)

over partial assignments ``gamma`` whose pairs are closer than ``c``. It splits into ``localisation`` (the
sum over assigned pairs), ``missed`` (``c^p/2`` per unassigned truth) and ``false`` (``c^p/2`` per unassigned
estimate), reported in units of distance^p so that ``total^p = localisation + missed + false``. Other
``alpha`` in (0, 2] give the total of eq. (1) (``c^p/alpha`` per cardinality mismatch) and NaN parts.

The optimal assignment is a discrete, stop-gradient step (scipy's Hungarian algorithm, one call per set
pair); given it, the values are differentiable with respect to ``X`` and ``Y`` (a GOSPA loss).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import MOTData


class OSPAResult(NamedTuple):
    """Per-set-pair OSPA, each of shape ``(*,)``."""

    total: torch.Tensor
    localisation: torch.Tensor
    cardinality: torch.Tensor

    def mean(self) -> dict[str, float]:
        """Averages over all set pairs (e.g. frames)."""
        return {k: float(v.mean()) for k, v in self._asdict().items()}


class GOSPAResult(NamedTuple):
    """Per-set-pair GOSPA, each of shape ``(*,)``; parts in distance^p, counts as float tensors."""

    total: torch.Tensor
    localisation: torch.Tensor
    missed: torch.Tensor
    false: torch.Tensor
    num_missed: torch.Tensor
    num_false: torch.Tensor

    def mean(self) -> dict[str, float]:
        """Averages over all set pairs (e.g. frames)."""
        return {k: float(v.mean()) for k, v in self._asdict().items()}


def _prepare(X: torch.Tensor, Y: torch.Tensor, x_mask, y_mask, c: float, p: float):
    if X.dim() < 2 or Y.dim() < 2 or X.shape[-1] != Y.shape[-1]:
        raise TorchtrackError(f"X (*, N, d) and Y (*, M, d) must share d, got {tuple(X.shape)} and {tuple(Y.shape)}")
    if not c > 0 or not p >= 1:
        raise TorchtrackError(f"need c > 0 and p >= 1, got c={c}, p={p}")
    batch = torch.broadcast_shapes(X.shape[:-2], Y.shape[:-2])
    dtype = torch.promote_types(X.dtype, Y.dtype)
    X = X.to(dtype).expand(*batch, *X.shape[-2:])
    Y = Y.to(dtype).expand(*batch, *Y.shape[-2:])
    xm = torch.ones(X.shape[:-1], dtype=torch.bool, device=X.device) if x_mask is None else x_mask.bool()
    ym = torch.ones(Y.shape[:-1], dtype=torch.bool, device=Y.device) if y_mask is None else y_mask.bool()
    xm, ym = xm.expand(X.shape[:-1]), ym.expand(Y.shape[:-1])
    n_x, n_y = X.shape[-2], Y.shape[-2]
    B = batch.numel()
    X, Y = X.reshape(B, n_x, X.shape[-1]), Y.reshape(B, n_y, Y.shape[-1])
    xm, ym = xm.reshape(B, n_x), ym.reshape(B, n_y)
    # (B, N, M) distances (exact differences, not the matrix-product form; zero gradient at zero distance)
    # and cut-off distances to the power p
    if X.shape[0] * n_x * n_y:
        dist = torch.cdist(X, Y, compute_mode="donot_use_mm_for_euclid_dist")
    else:
        dist = X.new_zeros(X.shape[0], n_x, n_y)
    dc_p = dist.clamp(max=c) ** p
    return batch, dist, dc_p, xm, ym


def _assign(cost: torch.Tensor, xm: torch.Tensor, ym: torch.Tensor) -> torch.Tensor:
    """(B, N, M) boolean assignment minimising ``cost`` over the masked rows and columns (stop-gradient)."""
    cost_np = cost.detach().cpu().numpy()
    xm_np, ym_np = xm.cpu().numpy(), ym.cpu().numpy()
    out = torch.zeros(cost.shape, dtype=torch.bool)
    for b in range(cost.shape[0]):  # the discrete solver, one set pair at a time
        rows, cols = xm_np[b].nonzero()[0], ym_np[b].nonzero()[0]
        if rows.size and cols.size:
            r, k = linear_sum_assignment(cost_np[b][rows][:, cols])
            out[b, rows[r], cols[k]] = True
    return out.to(cost.device)


def ospa(X: torch.Tensor, Y: torch.Tensor, c: float, p: float = 1.0,
         x_mask: torch.Tensor | None = None, y_mask: torch.Tensor | None = None) -> OSPAResult:
    """OSPA distance of order ``p`` with cut-off ``c`` between the sets ``X`` and ``Y`` (module docstring).

    Shapes: ``X (*, N, d)``, ``Y (*, M, d)``, masks ``(*, N)`` and ``(*, M)`` (default: all present); result
    ``(*,)``.
    """
    batch, _, dc_p, xm, ym = _prepare(X, Y, x_mask, y_mask, c, p)
    assigned = _assign(dc_p, xm, ym)
    n, m = xm.sum(-1), ym.sum(-1)
    big = torch.maximum(n, m).to(dc_p.dtype)
    loc_sum = (dc_p * assigned).sum((-2, -1))
    card_sum = (c**p) * (n - m).abs().to(dc_p.dtype)
    safe = big.clamp_min(1)
    empty = big == 0
    zero = torch.zeros_like(loc_sum)
    loc = torch.where(empty, zero, loc_sum / safe)
    card = torch.where(empty, zero, card_sum / safe)
    root = 1.0 / p
    total = _root(loc + card, root)
    return OSPAResult(total.reshape(batch), _root(loc, root).reshape(batch), _root(card, root).reshape(batch))


def _root(v: torch.Tensor, r: float) -> torch.Tensor:
    """``v ** r`` with a finite gradient at 0."""
    return torch.where(v > 0, v.clamp_min(torch.finfo(v.dtype).tiny) ** r, torch.zeros_like(v))


def gospa(X: torch.Tensor, Y: torch.Tensor, c: float, p: float = 2.0, alpha: float = 2.0,
          x_mask: torch.Tensor | None = None, y_mask: torch.Tensor | None = None) -> GOSPAResult:
    """GOSPA of order ``p``, cut-off ``c`` and ``alpha`` between truth ``X`` and estimates ``Y``.

    Shapes: ``X (*, N, d)``, ``Y (*, M, d)``, masks ``(*, N)`` and ``(*, M)`` (default: all present); result
    fields ``(*,)``.
    ``localisation``, ``missed`` and ``false`` are in distance^p (module docstring); NaN unless alpha = 2.
    """
    if not 0 < alpha <= 2:
        raise TorchtrackError(f"alpha must be in (0, 2], got {alpha}")
    batch, dist, dc_p, xm, ym = _prepare(X, Y, x_mask, y_mask, c, p)
    assigned = _assign(dc_p, xm, ym)
    n, m = xm.sum(-1), ym.sum(-1)
    cp = c**p
    if alpha == 2:
        kept = assigned & (dist.detach() < c)  # cut-off pairs are one miss and one false target each
        n_pairs = kept.sum((-2, -1))
        loc = (dc_p * kept).sum((-2, -1))
        n_missed = (n - n_pairs).to(dc_p.dtype)
        n_false = (m - n_pairs).to(dc_p.dtype)
        missed, false = 0.5 * cp * n_missed, 0.5 * cp * n_false
        total = _root(loc + missed + false, 1.0 / p)
    else:
        loc_all = (dc_p * assigned).sum((-2, -1))
        total = _root(loc_all + cp / alpha * (n - m).abs().to(dc_p.dtype), 1.0 / p)
        nan = torch.full_like(total, float("nan"))
        loc = missed = false = n_missed = n_false = nan
    return GOSPAResult(*(v.reshape(batch) for v in (total, loc, missed, false, n_missed, n_false)))


MAX_PAIRS = 1 << 24
"""Largest number of (truth, estimate) pairs evaluated in one batched chunk of frames."""


def _padded(data: MOTData, frames: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Centres of ``data`` in ``frames`` as (T, N, 2) float64 with a (T, N) mask (N = most in a frame)."""
    data = data.sorted()
    lo = np.searchsorted(data.frame, frames, "left")
    hi = np.searchsorted(data.frame, frames, "right")
    counts = hi - lo
    width = int(counts.max()) if counts.size else 0
    offsets = np.r_[0, np.cumsum(counts)[:-1]]  # where each frame starts among the points taken
    flat = np.arange(int(counts.sum()))
    row = np.repeat(np.arange(frames.size), counts)
    col = flat - np.repeat(offsets, counts)
    take = flat + np.repeat(lo - offsets, counts)
    points = torch.zeros(frames.size, width, 2, dtype=torch.float64)
    mask = torch.zeros(frames.size, width, dtype=torch.bool)
    points[row, col] = torch.from_numpy(data.centers()[take])
    mask[row, col] = True
    return points, mask


def mot_ospa_gospa(gt: MOTData, pred: MOTData, c: float = 10.0, p_ospa: float = 1.0,
                   p_gospa: float = 2.0) -> tuple[np.ndarray, OSPAResult, GOSPAResult]:
    """Per-frame OSPA and GOSPA (alpha = 2) between the box centres of ``gt`` and ``pred`` (ids ignored).

    Frames are the union of the frames present in either; returns ``(frames (T,), OSPAResult,
    GOSPAResult)`` with (T,) fields, computed in chunks of frames of at most :data:`MAX_PAIRS` pairs.
    """
    frames = np.union1d(gt.frame, pred.frame)
    X, xm = _padded(gt, frames)
    Y, ym = _padded(pred, frames)
    if X.shape[1] * Y.shape[1] > MAX_PAIRS:
        raise TorchtrackError(f"a frame has {X.shape[1]} truth and {Y.shape[1]} estimated points: more than "
                              f"{MAX_PAIRS} pairs for OSPA/GOSPA")
    step = max(1, MAX_PAIRS // max(1, X.shape[1] * Y.shape[1]))
    o, g = [], []
    for s in range(0, frames.size, step):
        sl = slice(s, s + step)
        o.append(ospa(X[sl], Y[sl], c, p_ospa, xm[sl], ym[sl]))
        g.append(gospa(X[sl], Y[sl], c, p_gospa, 2.0, xm[sl], ym[sl]))
    if not o:
        empty = torch.zeros(0, dtype=torch.float64)
        return frames, OSPAResult(*[empty] * 3), GOSPAResult(*[empty] * 6)
    return (frames, OSPAResult(*(torch.cat(v) for v in zip(*o))), GOSPAResult(*(torch.cat(v) for v in zip(*g))))
