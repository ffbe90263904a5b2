"""Registry of tunable filters: name → builder, data loader and losses.

A tunable filter is a :class:`Tunable` subclass listed under a name (``kalman``, ``imm``, ``gmphd``,
``pf``) in ``_TUNABLES``, in its own module of this package; modules are imported on first use, so a
filter whose module is missing only fails when asked for.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from torchtrack.errors import TorchtrackError

# name → (module, class), imported on first use
_TUNABLES = {
    "kalman": ("torchtrack.tuning.kalman", "KalmanTunable"),
    "imm": ("torchtrack.tuning.imm", "IMMTunable"),
    "gmphd": ("torchtrack.tuning.gmphd", "GMPHDTunable"),
    "pf": ("torchtrack.tuning.pf", "ParticleTunable"),
}


class TuneData(NamedTuple):
    """Training and held-out items (sequences or windows; the item type belongs to the tunable), and
    ``draws``: further draws of the held-out items' simulated measurements, by seed (scored only)."""

    train: list
    held_out: list
    draws: dict[int, list] = {}


class Tunable:
    """Base class. Subclasses set ``name``, ``losses`` (the first is the default) and implement
    :meth:`build`, :meth:`load_data` and :meth:`loss`; :meth:`evaluate` is optional."""

    name: str = ""
    losses: tuple[str, ...] = ()

    def __init__(self, options: Mapping[str, Any] | None = None):
        self.options = dict(options or {})

    def number(self, key: str, default: float, kind: type = float) -> float:
        """The option ``key`` of the ``model`` section as ``kind`` (``float`` or ``int``); a value that is not
        one is an error naming ``model.key`` and the value."""
        value = self.options.get(key, default)
        try:
            if isinstance(value, bool):
                raise ValueError
            return kind(value)
        except (TypeError, ValueError):
            raise TorchtrackError(f"model.{key} must be a{'n integer' if kind is int else ' number'}; "
                                  f"got {value!r}") from None

    def build(self) -> nn.Module:
        """The filter module from ``self.options`` (start values of the parameters included)."""
        raise NotImplementedError

    def loss_name(self, loss: str | None) -> str:
        """``loss`` (None: the default, the first of :attr:`losses`), checked to be one of :attr:`losses`."""
        loss = loss or self.losses[0]
        if loss not in self.losses:
            raise TorchtrackError(f"unknown loss {loss!r} for filter {self.name!r}; choose from "
                                  f"{', '.join(self.losses)}")
        return loss

    def load_data(self, config: Mapping[str, Any], generator: torch.Generator) -> TuneData:
        """Training and held-out items from the ``data`` section of a tune config."""
        raise NotImplementedError

    def loss(self, module: nn.Module, items: Sequence, loss: str) -> Tensor:
        """Scalar loss (a mean per measurement / frame) of ``module`` on a batch of ``items``."""
        raise NotImplementedError

    def item_frames(self, item) -> int:
        """Time steps in one item (here a single-target track ``item.z (T, m)``), to count the filter's work."""
        return int(item.z.shape[0])

    def evaluate(self, module: nn.Module, items: Sequence) -> dict[str, float]:
        """Task metrics on held-out items (e.g. MOTA, OSPA); none by default."""
        return {}

    def score(self, module: nn.Module, items: Sequence, metric: str) -> dict[str, float]:
        """Task metrics including ``metric``, for a search (grid, line search) that ranks by it; the
        default is :meth:`evaluate`, a tunable may skip metrics that cost time and are not asked for."""
        return self.evaluate(module, items)

    def truth(self, data_config: Mapping[str, Any]) -> dict[str, Any]:
        """True parameter values ``{dotted name: value}`` where the data are simulated; none by default."""
        return {}

    def derived(self, module: nn.Module) -> dict[str, Any]:
        """Quantities computed from the parameters that users think in (e.g. a clutter rate); none by default."""
        return {}

    def export(self, module: nn.Module) -> tuple[str, dict] | None:
        """``(file name, document)``: the fitted values as the options file of another command (e.g. a
        ``torchtrack track --config`` file), or None."""
        return None


def search_scores(tunable: Tunable, module: nn.Module, items: Sequence, metric: str, where: str) -> dict[str, float]:
    """:meth:`Tunable.score` for a search ranking by ``metric``; an error naming the config key ``where``
    (e.g. ``grid.metric``) when the tunable does not report that metric."""
    scores = tunable.score(module, items, metric)
    if metric not in scores:
        raise TorchtrackError(f"{where} {metric!r} is not reported by {tunable.name}; choose from "
                              f"{', '.join(scores)}")
    return scores


def tunable_names() -> list[str]:
    return sorted(_TUNABLES)


def get_tunable(name: str, options: Mapping[str, Any] | None = None) -> Tunable:
    """An instance of the tunable filter ``name`` with builder ``options``."""
    if name not in _TUNABLES:
        raise TorchtrackError(f"unknown filter {name!r}; tunable filters: {', '.join(tunable_names())}")
    module, cls = _TUNABLES[name]
    try:
        tunable = getattr(importlib.import_module(module), cls)
    except ModuleNotFoundError as exc:
        raise TorchtrackError(f"filter {name!r} cannot be tuned in this installation: {exc}") from exc
    return tunable(options)


def check_keys(section: Mapping[str, Any], allowed: Sequence[str], where: str) -> None:
    """Raise naming ``where`` when ``section`` has keys outside ``allowed``."""
    if not isinstance(section, Mapping):
        raise TorchtrackError(f"{where} must be a mapping; got {type(section).__name__}")
    extra = sorted(set(section) - set(allowed))
    if extra:
        raise TorchtrackError(f"unknown key(s) {', '.join(map(repr, extra))} in {where}; allowed: "
                              f"{', '.join(sorted(allowed))}")


def fold_bounds(n: int, folds: int) -> list[tuple[int, int]]:
    """``[start, stop)`` of ``folds`` contiguous blocks covering ``range(n)``, lengths differing by ≤ 1."""
    if not (isinstance(folds, int) and 2 <= folds <= n):
        raise TorchtrackError(f"folds must be an integer from 2 to the number of items or frames ({n}); got "
                              f"{folds!r}")
    edges = [round(i * n / folds) for i in range(folds + 1)]
    return list(zip(edges[:-1], edges[1:]))


def split_items(items: list, held_out, where: str) -> TuneData:
    """Split ``items`` into training and held-out: ``held_out`` is a count (the last items), a
    fraction in (0, 1), or ``{fold: k, folds: K}``: block ``k`` (0-based) of ``K`` contiguous blocks
    (cross-validation, :mod:`torchtrack.tuning.crossval`)."""
    n = len(items)
    if isinstance(held_out, Mapping):
        check_keys(held_out, ("fold", "folds"), f"{where}.held_out")
        fold, folds = held_out.get("fold"), held_out.get("folds")
        bounds = fold_bounds(n, folds)
        if not (isinstance(fold, int) and 0 <= fold < folds):
            raise TorchtrackError(f"{where}.held_out.fold must be an integer from 0 to {folds - 1}; got {fold!r}")
        lo, hi = bounds[fold]
        return TuneData(items[:lo] + items[hi:], items[lo:hi])
    if held_out is None or held_out == 0:
        k = 0
    elif isinstance(held_out, float) and 0 < held_out < 1:
        k = max(1, int(round(held_out * n)))
    elif isinstance(held_out, int) and held_out > 0:
        k = held_out
    else:
        raise TorchtrackError(f"{where}.held_out must be a count >= 0 or a fraction in (0, 1); got {held_out!r}")
    if k >= n:
        raise TorchtrackError(f"{where}: held_out ({k}) leaves no training data out of {n} item(s)")
    return TuneData(items[: n - k], items[n - k:])
