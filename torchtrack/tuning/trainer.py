"""The optimisation loop: mini-batches, Adam or L-BFGS, early stopping, non-finite guard.

Every step draws a mini-batch of training items (without replacement within an epoch), evaluates
the tunable's loss, and moves the selected unconstrained parameters. Every ``eval_every`` steps the
held-out loss is computed; training stops when it has not improved by ``min_delta`` for ``patience``
evaluations, and the parameters with the best held-out loss are restored. A non-finite loss or
gradient stops training at once with a message and restores the last parameters whose loss was
finite. L-BFGS (``torch.optim.LBFGS`` with strong-Wolfe line search) re-evaluates the same batch
inside a step, so it is used with full batches by default.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import torch
from torch import Tensor, nn

from torchtrack.config import from_mapping
from torchtrack.errors import TorchtrackError
from torchtrack.params import Positive
from torchtrack.tuning.config import EarlyStopping, OptimizerOptions
from torchtrack.tuning.parameters import get_values, select_trainable
from torchtrack.tuning.registry import Tunable, TuneData


class NonFiniteLoss(RuntimeError):
    """Raised inside a step when the loss or a gradient is not finite."""


def step_scale(param: nn.Module) -> Tensor:
    """Per-entry scale ``s`` of the optimisation variable ``u`` with ``raw = raw₀ + s u``.

    For a :class:`Positive` ``v = softplus(θ)``, ``s = v / softplus'(θ) = softplus(θ) / sigmoid(θ)``, so a
    unit step in ``u`` is a relative change of about 1 in ``v`` whatever its magnitude (a standard
    deviation of 300 m and a clutter density of 1e-4 px⁻² move alike); other parameters (logits,
    log-probabilities, Cholesky factors) keep ``s = 1``.
    """
    raw = param.raw.detach()
    if isinstance(param, Positive):
        return (nn.functional.softplus(raw) / torch.sigmoid(raw)).clamp_min(1.0)
    return torch.ones_like(raw)


class Reparametrised:
    """Optimise ``u`` (starting at 0) with ``raw = raw₀ + s u`` for the selected parameters.

    While active, each parameter module's ``raw`` is a plain tensor recomputed from ``u`` by
    :meth:`apply`; :meth:`close` puts back parameters (``nn.Parameter``) holding the final values.
    """

    def __init__(self, params: Mapping[str, nn.Module]):
        self.params = dict(params)
        self.base = {n: p.raw.detach().clone() for n, p in self.params.items()}
        self.scale = {n: step_scale(p) for n, p in self.params.items()}
        self.u = {n: torch.zeros_like(b, requires_grad=True) for n, b in self.base.items()}
        for p in self.params.values():
            del p.raw
        self.apply()

    def apply(self) -> None:
        for n, p in self.params.items():
            p.raw = self.base[n] + self.scale[n] * self.u[n]

    def snapshot(self) -> dict[str, Tensor]:
        return {n: u.detach().clone() for n, u in self.u.items()}

    def restore(self, snap: Mapping[str, Tensor]) -> None:
        with torch.no_grad():
            for n, u in self.u.items():
                u.copy_(snap[n])
        self.apply()

    def close(self) -> None:
        for n, p in self.params.items():
            value = (self.base[n] + self.scale[n] * self.u[n]).detach()
            del p.raw
            p.raw = nn.Parameter(value, requires_grad=True)


@dataclass
class FitResult:
    """What :func:`fit` did: the per-step training loss, held-out evaluations, the chosen step."""

    train_loss: list[float] = field(default_factory=list)          # per step, at the parameters entering it
    held_out: list[tuple[int, float]] = field(default_factory=list)  # (updates done, loss); 0 = the start
    best_step: int | None = None
    stopped: str = "finished"          # finished | early-stopped | non-finite
    message: str = ""
    evaluations: int = 0               # items filtered (training + held-out), forward passes
    frames: int = 0                    # time steps filtered in those passes
    seconds: float = 0.0
    start: dict[str, Tensor] = field(default_factory=dict)
    final: dict[str, Tensor] = field(default_factory=dict)


def _batches(n: int, batch_size: int, generator: torch.Generator):
    """Endless index batches, a fresh permutation each epoch."""
    while True:
        perm = torch.randperm(n, generator=generator).tolist()
        for s in range(0, n, batch_size):
            yield perm[s: s + batch_size]


def _finite(t: Tensor) -> bool:
    return bool(torch.isfinite(t).all())


def evaluate_loss(tunable: Tunable, module: nn.Module, items: Sequence, loss: str, batch_size: int) -> float:
    """Mean loss over ``items`` in batches (weights: batch sizes), without gradients."""
    total, count = 0.0, 0
    with torch.no_grad():
        for s in range(0, len(items), batch_size):
            chunk = items[s: s + batch_size]
            total += float(tunable.loss(module, chunk, loss)) * len(chunk)
            count += len(chunk)
    return total / max(count, 1)


def fit(tunable: Tunable, module: nn.Module, trainable: Sequence[str], data: TuneData, loss: str | None = None,
        optimizer: Mapping[str, Any] | None = None, early_stopping: Mapping[str, Any] | None = None,
        generator: torch.Generator | None = None, progress: bool = True) -> FitResult:
    """Fit ``trainable`` parameters of ``module`` on ``data.train``; early-stop on ``data.held_out``.

    The optimiser moves ``u`` with ``raw = raw₀ + s u`` (:class:`Reparametrised`, :func:`step_scale`),
    so ``lr`` is about a relative change per step for positive parameters of any magnitude.

    ``optimizer``: ``name`` (``adam`` | ``lbfgs``), ``lr``, ``lr_final`` (Adam: cosine decay from ``lr``
    to ``lr_final`` over ``steps``, so that mini-batch noise dies down; default constant), ``steps``,
    ``batch_size`` (items per
    step; default all for L-BFGS, 8 for Adam), ``max_iter`` (L-BFGS iterations per step),
    ``eval_every`` (steps between held-out evaluations; default one epoch).
    ``early_stopping``: ``patience`` (evaluations without improvement), ``min_delta``,
    ``restore_best`` (default true: end with the parameters of the best held-out evaluation; false:
    keep the last ones).
    """
    opts = from_mapping(OptimizerOptions, optimizer, "tune config", "optimizer")
    stop = from_mapping(EarlyStopping, early_stopping, "tune config", "early_stopping")
    loss = tunable.loss_name(loss)
    if not data.train:
        raise TorchtrackError("the training set is empty: data selects no training sequence/window")
    generator = generator or torch.Generator().manual_seed(0)
    name = opts.name
    n_train = len(data.train)
    batch_size = min(opts.batch_size or (n_train if name == "lbfgs" else 8), n_train)
    steps = opts.steps or (20 if name == "lbfgs" else 200)
    eval_every = opts.eval_every or max(1, math.ceil(n_train / batch_size))

    params = select_trainable(module, trainable)
    result = FitResult(start=get_values(module, trainable))
    scaled = Reparametrised(params)
    leaves = list(scaled.u.values())
    schedule = None
    if name == "adam":
        opt = torch.optim.Adam(leaves, lr=opts.lr or 0.05)
        if opts.lr_final is not None:
            schedule = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(steps - 1, 1),
                                                                  eta_min=opts.lr_final)
    else:
        opt = torch.optim.LBFGS(leaves, lr=opts.lr or 1.0, max_iter=opts.max_iter, line_search_fn="strong_wolfe")

    last_good = scaled.snapshot()
    best = (math.inf, None, last_good)
    bad_evals = 0
    t0 = time.perf_counter()
    batches = _batches(n_train, batch_size, generator)

    def closure(items: list) -> Tensor:
        """The loss on ``items`` with its gradient; :class:`NonFiniteLoss` where either is not finite."""
        nonlocal last_good
        opt.zero_grad()
        scaled.apply()
        current = scaled.snapshot()
        try:
            value = tunable.loss(module, items, loss)
        except TorchtrackError as exc:
            raise NonFiniteLoss(f"the filter failed ({exc})") from exc
        result.evaluations += len(items)
        result.frames += sum(tunable.item_frames(i) for i in items)
        if not _finite(value):
            raise NonFiniteLoss(f"loss is {float(value.detach())}")
        value.backward()
        for n, u in scaled.u.items():
            if u.grad is not None and not _finite(u.grad):
                raise NonFiniteLoss(f"gradient of {n} is not finite")
        last_good = current
        return value

    held_frames = sum(tunable.item_frames(i) for i in data.held_out)

    def evaluate_held_out(step: int) -> float:
        """Held-out loss after ``step`` updates (inf where the filter fails), counted and recorded."""
        try:
            held = evaluate_loss(tunable, module, data.held_out, loss, max(batch_size, 1))
        except TorchtrackError:
            held = math.inf
        result.evaluations += len(data.held_out)
        result.frames += held_frames
        result.held_out.append((step, held))
        return held

    if data.held_out:   # the start point, so that the curve begins where training does
        best = (evaluate_held_out(0), 0, scaled.snapshot())

    from tqdm import tqdm

    bar = tqdm(range(1, steps + 1), desc=f"tune {tunable.name}", disable=not progress, leave=False)
    try:
        for step in bar:
            items = [data.train[i] for i in next(batches)]
            try:
                if name == "adam":
                    value = closure(items)
                    opt.step()
                    if schedule is not None:
                        schedule.step()
                else:
                    value = opt.step(partial(closure, items))
            except NonFiniteLoss as exc:
                scaled.restore(last_good)
                result.stopped = "non-finite"
                result.message = (f"stopped at step {step}: {exc}; kept the last parameters with a finite loss "
                                  f"({_describe(get_values(module, trainable))})")
                break
            scaled.apply()
            result.train_loss.append(float(value.detach()))
            postfix = {"loss": f"{result.train_loss[-1]:.4g}"}
            if data.held_out and (step % eval_every == 0 or step == steps):
                held = evaluate_held_out(step)
                postfix["held_out"] = f"{held:.4g}"
                if held < best[0]:
                    bad_evals = 0 if held < best[0] - stop.min_delta else bad_evals + 1
                    best = (held, step, scaled.snapshot())
                else:
                    bad_evals = bad_evals + 1 if math.isfinite(held) else stop.patience   # non-finite: stop
                if bad_evals >= stop.patience:
                    result.stopped = "early-stopped"
                    result.message = f"held-out loss did not improve for {stop.patience} evaluations (step {step})"
                    break
            bar.set_postfix(postfix)
    finally:
        bar.close()
        if result.stopped != "non-finite" and best[1] is not None and stop.restore_best and result.train_loss:
            scaled.restore(best[2])
            result.best_step = best[1]
        scaled.close()
    if result.best_step is None and result.stopped != "non-finite":
        result.best_step = len(result.train_loss)
    select_trainable(module, trainable)   # the fresh raw parameters of the trainable ones, the rest frozen
    result.final = get_values(module, trainable)
    result.seconds = time.perf_counter() - t0
    return result


def _describe(values: Mapping[str, Tensor]) -> str:
    return ", ".join(f"{n}={_fmt(v)}" for n, v in values.items())


def _fmt(v: Tensor) -> str:
    return f"{float(v):.6g}" if v.numel() == 1 else str([round(x, 6) for x in v.flatten().tolist()])
