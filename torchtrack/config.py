"""Where configuration files come from (a path, or the name of a preset shipped as package data) and how a
YAML mapping becomes a typed configuration.

The presets under ``torchtrack/configs/`` (the repository's ``configs/`` folder points there) install with
the package and are read through :mod:`importlib.resources`, so ``--config gmphd-paper`` or
``--benchmark wpafb-benchmark`` work from any folder after a non-editable install.

:func:`from_mapping` is the one loader of every YAML section of the project (trackers, pipeline, video,
detector, tune): a mapping onto a (nested) dataclass whose fields carry the type, the default and, in the
class docstring, the meaning of each option. Unknown keys are refused by their full dotted path
(``gmphd.filter.q_typo``); values are converted to the field's type where that is unambiguous (YAML reads
``1e-4`` as a string: a numeric string is accepted for a float field) and refused otherwise, naming the key.

The allowed values of a field are declared beside its type and default with :func:`option` (``max_age: int =
option(1, ge=0)``); a dataclass deriving from :class:`Checked` checks them whenever it is built, from YAML or in
Python, and :func:`from_mapping` names the file and the dotted key of a value out of range
(``s.yaml: sort.max_age must be >= 0; got -1``).
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import MISSING, dataclass
from importlib import resources
from pathlib import Path
from typing import Any, TypeVar

import yaml

from torchtrack.errors import TorchtrackError

T = TypeVar("T")


@dataclass(frozen=True)
class Bounds:
    """The values a field allows: ``ge``/``gt``/``le``/``lt`` bounds on a number (on each item of a tuple),
    ``one_of`` a set of choices, ``multiple_of`` an integer step, ``ordered`` a ``(low, high)`` pair with
    ``low <= high``. ``None`` (an optional field unset) and booleans pass the numeric bounds; NaN fails them."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    one_of: tuple = ()
    multiple_of: int | None = None
    ordered: bool = False

    def problem(self, name: str, value: Any) -> tuple[str, str] | None:
        """``(key, reason)`` where ``value`` of field ``name`` is out of bounds (``key``: ``name`` or one of its
        items, ``name[i]``), else None."""
        if value is None:
            return None
        if self.one_of and value not in self.one_of:
            return name, f"must be one of {', '.join(map(repr, self.one_of))}; got {value!r}"
        if isinstance(value, (tuple, list)):
            for i, item in enumerate(value):
                found = self.problem(f"{name}[{i}]", item)
                if found:
                    return found
            if self.ordered and len(value) == 2 and not value[0] <= value[1]:
                return name, f"must be a range [low, high] with low <= high; got {list(value)}"
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return None
        if not self._inside(value):
            return name, f"must be {self.describe()}; got {value!r}"
        if self.multiple_of and value % self.multiple_of:
            return name, f"must be a multiple of {self.multiple_of}; got {value!r}"
        return None

    def _inside(self, value: float) -> bool:
        return ((self.ge is None or value >= self.ge) and (self.gt is None or value > self.gt)
                and (self.le is None or value <= self.le) and (self.lt is None or value < self.lt)
                and value == value)

    def describe(self) -> str:
        low = (self.ge, "[") if self.ge is not None else (self.gt, "(") if self.gt is not None else None
        high = (self.le, "]") if self.le is not None else (self.lt, ")") if self.lt is not None else None
        if low and high:
            return f"in {low[1]}{low[0]:g}, {high[0]:g}{high[1]}"
        if low:
            return f"{'>=' if low[1] == '[' else '>'} {low[0]:g}"
        if high:
            return f"{'<=' if high[1] == ']' else '<'} {high[0]:g}"
        return "a number"


def option(default: Any = MISSING, *, factory: Any = MISSING, **bounds: Any) -> Any:
    """A dataclass field with its default (or ``factory``) and its :class:`Bounds` (``ge``, ``gt``, ``le``,
    ``lt``, ``one_of``, ``multiple_of``, ``ordered``), checked by :class:`Checked`."""
    return dataclasses.field(default=default, default_factory=factory, metadata={"bounds": Bounds(**bounds)})


class OutOfRange(TorchtrackError):
    """A field of a :class:`Checked` dataclass out of its bounds; ``key`` and ``reason`` let
    :func:`from_mapping` name the file and the dotted key instead of the class."""

    def __init__(self, owner: str, key: str, reason: str):
        super().__init__(f"{owner}.{key} {reason}")
        self.key, self.reason = key, reason


class Checked:
    """Base of a dataclass whose fields' :class:`Bounds` (declared with :func:`option`) are checked whenever it
    is built; a subclass with its own ``__post_init__`` calls ``super().__post_init__()`` and raises
    :meth:`refuse` for checks across fields."""

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            bounds = f.metadata.get("bounds")
            found = bounds.problem(f.name, getattr(self, f.name)) if bounds is not None else None
            if found:
                raise self.refuse(*found)

    def refuse(self, key: str, reason: str) -> OutOfRange:
        """The error for field ``key`` (``reason``: ``must be ...; got ...``), named ``Class.key`` (or by the
        section name a class sets in ``dotted_name``, e.g. ``registration.key``)."""
        return OutOfRange(getattr(self, "dotted_name", type(self).__name__), key, reason)


def preset_names() -> list[str]:
    """The names of the shipped presets (file names without ``.yaml``), sorted."""
    folder = resources.files("torchtrack") / "configs"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml"))


def preset_path(name_or_path: str | Path, presets: Sequence[str] | None = None) -> Path:
    """The file a ``--config`` value names: an existing path as given, otherwise a shipped preset by name
    (``gmphd-paper``, ``gmphd-paper.yaml`` or ``configs/gmphd-paper.yaml``) among ``presets`` (default: all
    of them); an error naming those presets where it is neither."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    known = preset_names() if presets is None else list(presets)
    stem = path.name[:-5] if path.name.endswith(".yaml") else path.name
    candidate = resources.files("torchtrack") / "configs" / f"{stem}.yaml"
    if path.parent in (Path("."), Path("configs")) and stem in known and candidate.is_file():
        return Path(str(candidate))
    raise TorchtrackError(f"{name_or_path}: no such file or preset (presets: {', '.join(known)})")


def read_mapping(path: str | Path, what: str) -> dict:
    """The YAML mapping in ``path`` (empty file: ``{}``); one-line errors naming ``what`` and the file."""
    path = Path(path)
    if not path.is_file():
        raise TorchtrackError(f"{what} {path}: no such file")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
        raise TorchtrackError(f"{what} {where}: cannot read: {getattr(exc, 'problem', None) or exc}") from None
    if not isinstance(data, dict):
        raise TorchtrackError(f"{what} {path}: expected a mapping at the top level")
    return data


def from_mapping(cls: type[T], values: Mapping | None, source: str = "config", prefix: str = "",
                 base: T | None = None) -> T:
    """Build the dataclass ``cls`` from ``values``: keys absent take their value from ``base`` (default:
    the field defaults); nested dataclass fields take nested mappings (merged onto the base's value the same
    way). ``source`` (a file name) and the dotted ``prefix`` (``gmphd.filter``) name a bad key in the error."""
    if values is None:
        values = {}
    if isinstance(values, cls):
        return values
    if not isinstance(values, Mapping):
        raise TorchtrackError(f"{source}: {prefix or 'the config'} must be a mapping; got {values!r}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(_dotted(prefix, k) for k in values if k not in fields)
    if unknown:
        raise TorchtrackError(f"{source}: unknown key(s) {unknown}; known: {sorted(fields)}")
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, value in values.items():
        key = _dotted(prefix, name)
        hint = hints[name]
        if dataclasses.is_dataclass(hint):
            kwargs[name] = from_mapping(hint, value, source, key,
                                        getattr(base, name) if base is not None else None)
        else:
            kwargs[name] = convert(value, hint, source, key)
    try:
        return dataclasses.replace(base, **kwargs) if base is not None else cls(**kwargs)
    except OutOfRange as exc:
        raise TorchtrackError(f"{source}: {_dotted(prefix, exc.key)} {exc.reason}") from None


def convert(value: Any, hint: Any, source: str, key: str) -> Any:
    """``value`` as the type ``hint`` (float, int, bool, str, ``X | None``, ``tuple[...]``, dict, list,
    a dataclass); a :class:`TorchtrackError` naming ``source`` and ``key`` where it is not one."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        options = typing.get_args(hint)
        if value is None and type(None) in options:
            return None
        kinds = [t for t in options if t is not type(None)]
        if len(kinds) == 1:                  # ``X | None``: X's own error, naming what is wrong inside it
            return convert(value, kinds[0], source, key)
        exact = [t for t in options if t is not type(None) and isinstance(value, typing.get_origin(t) or t)
                 and not (t is int and isinstance(value, bool))]
        for t in exact + [t for t in options if t is not type(None) and t not in exact]:
            try:
                return convert(value, t, source, key)
            except TorchtrackError:
                continue
        raise _bad(source, key, value, " or ".join(_name(t) for t in options))
    if dataclasses.is_dataclass(hint):
        return from_mapping(hint, value, source, key)
    if hint is Any:
        return value
    if hint is float:
        try:
            number = None if isinstance(value, bool) else float(value)
        except (TypeError, ValueError, OverflowError):
            number = None
        if number is None or not math.isfinite(number):     # .inf / .nan in YAML: refused where read
            raise _bad(source, key, value, "a finite number")
        return number
    if hint in _TAKEN_AS_IS:        # never converted (a bool is not a whole number here)
        if isinstance(value, hint) and not (hint is int and isinstance(value, bool)):
            return value
        raise _bad(source, key, value, _TAKEN_AS_IS[hint])
    if origin is tuple or hint is tuple:
        args = typing.get_args(hint)
        if not isinstance(value, (list, tuple)):
            raise _bad(source, key, value, "a list")
        if not args:
            return tuple(value)
        if len(args) == 2 and args[1] is Ellipsis:
            args = (args[0],) * len(value)
        elif args and len(args) != len(value):
            raise _bad(source, key, value, f"a list of {len(args)}")
        return tuple(convert(v, t, source, f"{key}[{i}]") for i, (v, t) in enumerate(zip(value, args)))
    if origin is dict or hint is dict:
        if not isinstance(value, Mapping):
            raise _bad(source, key, value, "a mapping")
        return dict(value)
    if origin is list or hint is list:
        if not isinstance(value, (list, tuple)):
            raise _bad(source, key, value, "a list")
        return list(value)
    return value


_TAKEN_AS_IS = {int: "a whole number", bool: "true or false", str: "a string"}


def _bad(source: str, key: str, value: Any, expected: str) -> TorchtrackError:
    return TorchtrackError(f"{source}: {key} must be {expected}; got {value!r}")


def _name(hint: Any) -> str:
    return "null" if hint is type(None) else getattr(hint, "__name__", str(hint))


def _dotted(prefix: str, key: Any) -> str:
    return f"{prefix}.{key}" if prefix else str(key)


def load_sections(path: str | Path, preset: str) -> dict:
    """Read a scenario YAML that stands in for the shipped ``preset``: the same sections and keys, each value
    of the preset's kind (:func:`conform`)."""
    reference = read_mapping(preset_path(preset), "preset")
    return conform(read_mapping(path, "--config"), reference, str(path))


def conform(values: Any, reference: Any, source: str, key: str = "") -> Any:
    """``values`` checked against ``reference``, the shipped preset it replaces: mappings with the same keys
    (none unknown, none missing), numbers where the reference has numbers (numeric strings — PyYAML reads
    ``1e-4`` as one — become numbers), true/false, strings and lists where it has those (list items against
    the reference's items); ``null`` in the reference takes anything. A one-line error naming ``source`` and
    the dotted key otherwise."""
    if isinstance(reference, Mapping):
        if not isinstance(values, Mapping):
            raise _bad(source, key or "the config", values, "a mapping")
        for problem, names in (("unknown", set(values) - set(reference)), ("missing", set(reference) - set(values))):
            if names:
                raise TorchtrackError(f"{source}: {problem} key(s) {sorted(_dotted(key, k) for k in names)}; "
                                      f"expected: {sorted(reference)}")
        return {k: conform(v, reference[k], source, _dotted(key, k)) for k, v in values.items()}
    if isinstance(reference, list):
        if not isinstance(values, list):
            raise _bad(source, key, values, "a list")
        if not reference:
            return values
        return [conform(v, reference[min(i, len(reference) - 1)], source, f"{key}[{i}]") for i, v in enumerate(values)]
    if isinstance(reference, bool) or isinstance(reference, str):
        return convert(values, type(reference), source, key)
    if isinstance(reference, (int, float)):
        if isinstance(values, (int, float)) and not isinstance(values, bool):
            return values
        number = convert(values, float, source, key)
        return int(number) if isinstance(reference, int) and number.is_integer() else number
    return values
