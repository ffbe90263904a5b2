"""Tunable parameters of a filter module, by dotted name.

Every constrained parameter of :mod:`torchtrack.params` (``Positive``, ``Probability``,
``RowStochastic``, ``Covariance``) inside a filter is addressed by its dotted module path, e.g.
``motion.q`` or ``measurement.sigma`` of a :class:`~torchtrack.filters.kalman.filter.KalmanFilter`. Its
*value* is the constrained tensor (``param()``); its *raw* value is the unconstrained
``nn.Parameter`` (``param.raw``) that the optimiser moves.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import torch
from torch import Tensor, nn

from torchtrack.errors import TorchtrackError
from torchtrack.params import Covariance, Positive, Probability, RowStochastic, inverse_softplus

CONSTRAINED = (Positive, Probability, RowStochastic, Covariance)


def tunable_parameters(module: nn.Module) -> dict[str, nn.Module]:
    """Every constrained parameter of ``module`` by dotted name, in module order."""
    return {name: m for name, m in module.named_modules() if isinstance(m, CONSTRAINED) and name}


def checked_parameters(module: nn.Module, names: Iterable[str], what: str = "parameter",
                       where: str = "") -> dict[str, nn.Module]:
    """:func:`tunable_parameters`, after checking that each of ``names`` is one of them (an error starting
    with ``where`` lists the valid names otherwise)."""
    params = tunable_parameters(module)
    unknown = [n for n in names if n not in params]
    if unknown:
        raise TorchtrackError(f"{where}unknown {what} {', '.join(map(repr, unknown))}; valid names: "
                              f"{', '.join(sorted(params)) or '(none)'}")
    return params


def plain(values: Mapping[str, Tensor]) -> dict[str, float | list]:
    """``{name: float}`` for one-entry tensors, ``{name: nested list}`` otherwise (for YAML and JSON)."""
    return {n: float(v) if v.numel() == 1 else v.tolist() for n, v in values.items()}


def select_trainable(module: nn.Module, names: Iterable[str]) -> dict[str, nn.Module]:
    """Freeze every constrained parameter of ``module`` except ``names``; return the trainable ones.

    Every other ``nn.Parameter`` of the module is frozen too. Raises :class:`TorchtrackError` listing
    the valid names when a name does not exist, or when ``names`` is empty.
    """
    names = list(names)
    params = checked_parameters(module, names, "trainable parameter")
    if not names:
        raise TorchtrackError(f"no trainable parameter selected; valid names: {', '.join(sorted(params))}")
    for p in module.parameters():
        p.requires_grad_(False)
    for n in names:
        params[n].raw.requires_grad_(True)
    return {n: params[n] for n in names}


def raw_from_value(param: nn.Module, value: Tensor) -> Tensor:
    """The unconstrained ``raw`` giving the constrained ``value`` (the inverse transform)."""
    if isinstance(param, Positive):
        if not bool((value > param.floor).all()):
            raise TorchtrackError(f"{param.name} must be > {param.floor}; got {value.tolist()}")
        return inverse_softplus(value - param.floor)
    if isinstance(param, Probability):
        if not bool(((value > 0) & (value < 1)).all()):
            raise TorchtrackError(f"{param.name} must lie strictly between 0 and 1; got {value.tolist()}")
        return torch.logit(value)
    if isinstance(param, RowStochastic):
        if not bool((value > 0).all()) or not bool(((value.sum(-1) - 1).abs() < 1e-6).all()):
            raise TorchtrackError(f"{param.name} must have positive rows summing to 1; got {value.tolist()}")
        return torch.log(value)
    L, info = torch.linalg.cholesky_ex(value)
    if bool((info != 0).any()):
        raise TorchtrackError(f"{param.name} must be positive definite")
    raw = L.clone()
    idx = torch.arange(L.shape[-1])
    raw[..., idx, idx] = inverse_softplus(torch.diagonal(L, dim1=-2, dim2=-1))
    return raw


def get_values(module: nn.Module, names: Iterable[str] | None = None) -> dict[str, Tensor]:
    """Constrained values ``{name: tensor}``, detached copies (all tunable parameters when ``names`` is None)."""
    names = list(tunable_parameters(module) if names is None else names)
    params = checked_parameters(module, names)
    with torch.no_grad():
        return {n: params[n]().detach().clone() for n in names}


def get_raw(module: nn.Module, names: Iterable[str] | None = None) -> dict[str, Tensor]:
    """Unconstrained values ``{name: raw tensor}``, detached copies (a snapshot to restore)."""
    params = tunable_parameters(module)
    names = list(params) if names is None else list(names)
    return {n: params[n].raw.detach().clone() for n in names}


def set_raw(module: nn.Module, raw: Mapping[str, Tensor]) -> None:
    """Copy unconstrained values into the module (shapes must match), keeping ``requires_grad``."""
    params = checked_parameters(module, raw)
    with torch.no_grad():
        for n, value in raw.items():
            target = params[n].raw
            value = torch.as_tensor(value, dtype=target.dtype, device=target.device)
            if value.shape != target.shape:
                raise TorchtrackError(f"parameter {n!r} must have shape {tuple(target.shape)}; got "
                                      f"{tuple(value.shape)}")
            target.copy_(value)


def set_values(module: nn.Module, values: Mapping[str, Tensor]) -> None:
    """Set constrained values (through the inverse transform of each parameter)."""
    params = checked_parameters(module, values)
    raw = {}
    for n, value in values.items():
        ref = params[n].raw
        raw[n] = raw_from_value(params[n], torch.as_tensor(value, dtype=ref.dtype, device=ref.device))
    set_raw(module, raw)
