"""Class-conditioned IMM bank: one IMM per target class for every track (the gate paper, §3–4).

Each class ``c`` has its own model set and transition matrix (its own
:class:`~torchtrack.filters.imm.filter.InteractingMultipleModel` or
:class:`~torchtrack.filters.imm.cv.ConstantVelocityIMM`); every track carries one IMM state per class
and the class probabilities ``P(c | z_{1:k})`` (eq. 7). With a kinematic measurement ``z`` and,
optionally, a classifier report ``ĉ`` with confusion matrix ``C[c, ĉ] = Pr{report ĉ | true class c}``
(rows sum to one; eq. 37), the class update is::

    P(c | z_{1:k}) ∝ P(c | z_{1:k-1}) · p(z_k | c, z_{1:k-1}) · C[c, ĉ_k]

where ``p(z_k | c, z_{1:k-1})`` is class ``c``'s IMM likelihood ``Σ_j μ^{c,j}_{k|k-1} Λ^{c,j}`` (eq. 29–30).
The class-conditioned measurement prediction (eq. 30) is the Gaussian mixture over class ``c``'s
models; :meth:`ClassConditionedIMM.joint_log_density` evaluates the joint predictive density of a
kinematic measurement and a class report, ``p(z, ĉ | track) = Σ_c P(c) C[c, ĉ] p(z | c)``, used by
the class-conditioned gate.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor, nn

from torchtrack.association.gating import mixture_log_density, sample_mixture
from torchtrack.errors import TorchtrackError
from torchtrack.filters.imm.filter import IMMState, check_probabilities, probabilities_or_uniform
from torchtrack.filters.kalman.filter import GaussianState
from torchtrack.gaussian import moment_match


class BankState(NamedTuple):
    """``log_class_prob (*, C)`` and one :class:`IMMState` per class (batch ``*``)."""

    log_class_prob: Tensor
    classes: tuple[IMMState, ...]


class BankUpdateInfo(NamedTuple):
    log_likelihood: Tensor        # (*,) log p(z, ĉ | past) (kinematic only when no report)
    class_log_likelihood: Tensor  # (*, C) log p(z | c, past)
    present: Tensor               # (*,) bool


class ClassConditionedIMM(nn.Module):
    """A bank of per-class IMMs; ``confusion (C, C)`` (rows: true class, columns: report) is optional."""

    def __init__(self, imms: Sequence[nn.Module], confusion: Tensor | None = None):
        super().__init__()
        if len(imms) == 0:
            raise TorchtrackError("ClassConditionedIMM needs at least one class")
        n = [imm.state_dim for imm in imms]
        if len(set(n)) != 1:
            raise TorchtrackError(f"class IMMs must share a state layout; got mismatched model state sizes {n}")
        self.imms = nn.ModuleList(imms)
        self.state_dim = n[0]
        C = len(imms)
        conf = None if confusion is None else torch.as_tensor(confusion, dtype=torch.get_default_dtype())
        if conf is not None:
            if conf.shape != (C, C):
                raise TorchtrackError(f"confusion matrix must be ({C}, {C}); got {tuple(conf.shape)}")
            check_probabilities(conf, "rows of the confusion matrix")
        self.register_buffer("confusion", conf)

    @property
    def num_classes(self) -> int:
        return len(self.imms)

    def initial_state(self, mean: Tensor, cov: Tensor, class_prob: Tensor | None = None) -> BankState:
        """All classes and models start at ``mean (*, n)``, ``cov (*, n, n)``; ``class_prob (*, C)``."""
        C = self.num_classes
        class_prob = probabilities_or_uniform(class_prob, C, "class probabilities", mean)
        states = tuple(imm.initial_state(mean, cov) for imm in self.imms)
        batch = states[0].log_prob.shape[:-1]
        return BankState(torch.log(class_prob).expand(*batch, C), states)

    def predict(self, state: BankState, dt=1.0) -> BankState:
        """Each class IMM predicts; class probabilities are unchanged (the class is static)."""
        return BankState(state.log_class_prob, tuple(imm.predict(s, dt) for imm, s in zip(self.imms, state.classes)))

    def _report_log_prob(self, z_class: Tensor, like: Tensor) -> Tensor:
        """``log C[c, ĉ]`` for reports ``ĉ (*,)`` → ``(*, C)``."""
        if self.confusion is None:
            raise TorchtrackError("a class report needs the bank's confusion matrix")
        z_class = z_class.long()
        if bool(((z_class < 0) | (z_class >= self.num_classes)).any()):
            raise TorchtrackError(f"class reports must lie in [0, {self.num_classes})")
        return torch.log(self.confusion.to(like)).transpose(0, 1)[z_class]

    def update(self, state: BankState, z: Tensor, mask: Tensor | None = None,
               z_class: Tensor | None = None) -> tuple[BankState, BankUpdateInfo]:
        """Update every class IMM with ``z (*, m)`` and the class probabilities (with report ``z_class (*,)``)."""
        new, infos = zip(*(imm.update(s, z, mask) for imm, s in zip(self.imms, state.classes)))
        ll = torch.stack([info.log_likelihood for info in infos], -1)   # (*, C)
        joint = state.log_class_prob + ll
        present = infos[-1].present
        if z_class is not None:
            rep = self._report_log_prob(z_class, joint)
            joint = joint + torch.where(present.unsqueeze(-1), rep, torch.zeros_like(rep))
        total = torch.logsumexp(joint, -1)
        return BankState(joint - total.unsqueeze(-1), new), BankUpdateInfo(total, ll, present)

    def class_mixtures(self, state: BankState) -> tuple[Tensor, Tensor, Tensor]:
        """Per-class measurement mixtures of a predicted state (eq. 30), padded to a common model count.

        Returns ``log μ (*, C, K)`` (within-class weights; ``-inf`` for padding), ``ẑ (*, C, K, m)``,
        ``S (*, C, K, m, m)``.
        """
        parts = [imm.predicted_measurement(s) for imm, s in zip(self.imms, state.classes)]
        K = max(p[0].shape[-1] for p in parts)
        lw, zh, S = [], [], []
        for log_w, z_hat, cov in parts:
            k = log_w.shape[-1]
            models = torch.tensor([*range(k), *[0] * (K - k)], device=log_w.device)   # padding repeats model 0
            lw.append(nn.functional.pad(log_w, (0, K - k), value=-torch.inf))
            zh.append(z_hat.index_select(-2, models))
            S.append(cov.index_select(-3, models))
        return torch.stack(lw, -2), torch.stack(zh, -3), torch.stack(S, -4)

    def measurement_mixture(self, state: BankState, z_class: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """The whole predicted measurement mixture over classes × models, flattened to ``(*, C·K)``.

        With a class report ``z_class`` (a Python int or ``(*,)`` tensor) the class weights become
        ``P(c) C[c, ĉ]`` (unnormalised: the total is ``log P(ĉ | track)``).
        """
        log_w, z_hat, S = self.class_mixtures(state)
        cls = state.log_class_prob
        if z_class is not None:
            zc = torch.as_tensor(z_class, device=cls.device).expand(cls.shape[:-1])
            cls = cls + self._report_log_prob(zc, cls)
        w = cls.unsqueeze(-1) + log_w
        return w.flatten(-2), z_hat.flatten(-3, -2), S.flatten(-4, -3)

    def joint_log_density(self, state: BankState, z: Tensor, z_class: Tensor) -> Tensor:
        """``log p(z, ĉ | track)`` at per-track points ``z (*, P, m)`` with reports ``z_class (*, P)``, for a
        predicted state of batch ``*``; result ``(*, P)``. (For measurements shared by ``T`` tracks, expand
        them to ``(*, T, Mz, m)``.) Component densities are evaluated once; reports only reweight them."""
        log_w, z_hat, S = self.class_mixtures(state)                  # (*, C, K), (*, C, K, m), (*, C, K, m, m)
        comp = mixture_log_density(z, log_w.flatten(-2), z_hat.flatten(-3, -2), S.flatten(-4, -3),
                                   per_component=True)                 # (*, CK, P)
        C, K = log_w.shape[-2:]
        comp = comp.unflatten(-2, (C, K))                              # (*, C, K, P)
        in_class = torch.logsumexp(log_w.unsqueeze(-1) + comp, -2)     # (*, C, P): log p(z | c)
        # log Σ_c P(c) C[c, ĉ] p(z | c), with ĉ the report of each point
        w = state.log_class_prob.unsqueeze(-1) + self._report_log_prob(z_class, z).movedim(-1, -2)   # (*, C, P)
        return torch.logsumexp(w + in_class, -2)

    def sample_measurements(self, state: BankState, num: int,
                            generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        """``num`` draws of ``(z, ĉ)`` from the joint predictive density per track: ``(*, num, m)``, ``(*, num)``."""
        parts = [self.measurement_mixture(state, c) for c in range(self.num_classes)]
        w, mu, S = (torch.cat(p, dim) for p, dim in zip(zip(*parts), (-1, -2, -3)))
        z, comp = sample_mixture(w, mu, S, num, generator, return_component=True)
        return z, torch.div(comp, parts[0][0].shape[-1], rounding_mode="floor")

    def combine(self, state: BankState) -> GaussianState:
        """Moment match over classes × models: ``(*, n)``, ``(*, n, n)``."""
        w = torch.cat([state.log_class_prob[..., c:c + 1] + s.log_prob for c, s in enumerate(state.classes)], -1)
        return GaussianState(*moment_match(w, torch.cat([s.mean for s in state.classes], -2),
                                           torch.cat([s.cov for s in state.classes], -3)))


__all__ = ["BankState", "BankUpdateInfo", "ClassConditionedIMM"]
