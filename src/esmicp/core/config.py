"""The base of the configuration tree: frozen dataclasses whose fields are checked when made and
round-trip through a JSON-ready dict.

A configuration class derives from :class:`Config` and declares each field with one of
:func:`count`, :func:`number`, :func:`fraction`, :func:`flag` (True or False), :func:`span` (a
range), :func:`numbers_tuple` or :func:`part` (a nested configuration), which
record what the field accepts. Making an instance (directly, by :func:`dataclasses.replace` or by
:meth:`Config.from_dict`) checks every field and raises :class:`~esmicp.errors.InvalidInputError`
naming the class and the field; :meth:`Config.from_dict` refuses unknown keys.

The core's own tuned values are here too: :class:`NeighbourIndexConfig`, the nearest-neighbour
index's (:class:`esmicp.core.correspondence.NearestNeighbors`).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from ..errors import InvalidInputError

C = TypeVar("C", bound="Config")


def count(default: int, *, least: int = 1):
    """A whole-number field (a count), at least ``least``."""
    return dataclasses.field(default=default, metadata={"check": ("count", least)})


def number(default: float, *, above: float | None = None, least: float | None = None,
           below: float | None = None, most: float | None = None):
    """A finite real field: greater than ``above`` / at least ``least``, less than ``below`` / at
    most ``most`` (each bound optional); stored as a float."""
    return dataclasses.field(default=default, metadata={"check": ("number", above, least, below, most)})


def fraction(default: float):
    """A real field in [0, 1] (a fraction, a ratio, a confidence)."""
    return number(default, least=0.0, most=1.0)


def flag(default: bool):
    """A field that is True or False (a choice between two ways of working)."""
    return dataclasses.field(default=default, metadata={"check": ("flag",)})


def span(default: tuple[float, float]):
    """A range ``(low, high)`` of two finite reals with ``low < high``; stored as a tuple of floats."""
    return dataclasses.field(default=default, metadata={"check": ("span",)})


def numbers_tuple(default: tuple):
    """A tuple of finite reals, or of such tuples (a schedule); lists are read as tuples, whole
    numbers stay whole."""
    return dataclasses.field(default=default, metadata={"check": ("tuple",)})


def part(kind: type):
    """A nested configuration of class ``kind`` (its defaults unless given); a dict is read by
    ``kind.from_dict``."""
    return dataclasses.field(default_factory=kind, metadata={"check": ("part", kind)})


def _is_real(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)


def _numbers(value):
    """``value`` as a tuple of finite reals or of such tuples (lists read as tuples), else None."""
    if not isinstance(value, (tuple, list)):
        return None
    out = []
    for item in value:
        if isinstance(item, (tuple, list)):
            item = _numbers(item)
            if item is None:
                return None
        elif not _is_real(item):
            return None
        out.append(item)
    return tuple(out)


def _bounds(above, least, below, most) -> str:
    words = [f"> {above:g}" if above is not None else None, f">= {least:g}" if least is not None else None,
             f"< {below:g}" if below is not None else None, f"<= {most:g}" if most is not None else None]
    return " and ".join(word for word in words if word)


def _lists(value):
    return [_lists(item) for item in value] if isinstance(value, tuple) else value


@dataclass(frozen=True)
class Config:
    """A frozen, validated configuration (see the module docstring)."""

    def __post_init__(self) -> None:
        owner = type(self).__name__
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            checked = type(self).checked(field.name, value, f"{owner}.{field.name}")
            if checked is not value:
                object.__setattr__(self, field.name, checked)

    @classmethod
    def checked(cls, name: str, value, where: str | None = None):
        """``value`` checked as field ``name`` (a count as an int, a number as a float, a nested
        configuration read from a dict); :class:`InvalidInputError` naming ``where`` (default
        ``Class.name``) otherwise."""
        field = {field.name: field for field in dataclasses.fields(cls)}[name]
        where = where or f"{cls.__name__}.{name}"
        check = field.metadata.get("check")
        if check is None:
            return value
        if check[0] == "count":
            least = check[1]
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < least:
                raise InvalidInputError(f"{where}: expected a whole number >= {least}, got {value!r}")
            return int(value)
        if check[0] == "number":
            above, least, below, most = check[1:]
            if not _is_real(value) or (above is not None and not value > above) \
                    or (least is not None and not value >= least) or (below is not None and not value < below) \
                    or (most is not None and not value <= most):
                bounds = _bounds(above, least, below, most)
                raise InvalidInputError(f"{where}: expected a finite number{' ' + bounds if bounds else ''}, "
                                        f"got {value!r}")
            return float(value)
        if check[0] == "flag":
            if not isinstance(value, (bool, np.bool_)):
                raise InvalidInputError(f"{where}: expected True or False, got {value!r}")
            return bool(value)
        if check[0] == "span":
            if not (isinstance(value, (tuple, list)) and len(value) == 2 and all(map(_is_real, value))
                    and value[0] < value[1]):
                raise InvalidInputError(f"{where}: expected (low, high) with low < high, got {value!r}")
            return value if isinstance(value, tuple) and all(type(v) is float for v in value) \
                else (float(value[0]), float(value[1]))
        if check[0] == "tuple":
            read = _numbers(value)
            if read is None:
                raise InvalidInputError(f"{where}: expected a tuple of finite numbers, got {value!r}")
            return value if read == value and type(value) is tuple else read
        kind = check[1]
        if isinstance(value, dict):
            return kind.from_dict(value, where=where) if issubclass(kind, Config) else kind.from_dict(value)
        if not isinstance(value, kind):
            raise InvalidInputError(f"{where}: expected a {kind.__name__} or a dict, got {type(value).__name__}")
        return value

    def to_dict(self) -> dict:
        """A JSON-ready dict of every field (nested configurations as dicts, pairs as lists)."""
        out: dict[str, Any] = {}
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if hasattr(value, "to_dict"):  # a nested configuration
                value = value.to_dict()
            elif isinstance(value, tuple):
                value = _lists(value)
            out[field.name] = value
        return out

    @classmethod
    def from_dict(cls: type[C], data: dict, *, where: str | None = None) -> C:
        """The configuration ``data`` describes (as :meth:`to_dict` writes it; a missing field keeps
        its default, a nested configuration may be a dict).

        Raises
        ------
        InvalidInputError
            ``data`` is not a dict, names a field the class does not have, or holds an invalid value.
        """
        where = where or cls.__name__
        if not isinstance(data, dict):
            raise InvalidInputError(f"{where}: expected a dict of fields, got {type(data).__name__}")
        known = {field.name for field in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known, key=str)
        if unknown:
            raise InvalidInputError(f"{where}: unknown field(s) {', '.join(map(repr, unknown))}; "
                                    f"known: {', '.join(sorted(known))}")
        return cls(**data)

    @classmethod
    def of(cls: type[C], value, name: str = "config") -> C:
        """``value`` as a ``cls``: None gives the defaults, an instance is kept, a dict is read by
        :meth:`from_dict`; anything else raises :class:`InvalidInputError` naming ``name``."""
        if value is None:
            return cls()
        if isinstance(value, cls):
            return value
        if isinstance(value, dict):
            return cls.from_dict(value)
        raise InvalidInputError(f"{name}: expected a {cls.__name__} or a dict, got {type(value).__name__}")


@dataclass(frozen=True)
class NeighbourIndexConfig(Config):
    """When the nearest-neighbour index (:class:`esmicp.core.correspondence.NearestNeighbors`)
    answers through its voxel hash and its neighbour graph. The answers are exact whatever the
    values: only the speed changes.

    Attributes
    ----------
    near_cell_spacings : float
        Cell edge of the voxel hash of ``query_near``, in target point spacings (gain): queries
        whose nearest target point lies within one cell are answered by the hash.
    near_query_min : int
        Below this many query points ``query_near`` and ``step`` use the KD-tree alone (count):
        a few queries do not pay for building the hash.
    hash_miss_limit : float
        The voxel hash is skipped while more than this fraction of the last call's points had
        their neighbour beyond one cell (0-1): a scan far from its sensor, or a start far from the
        solution, where the hash would only delay the tree.
    graph_neighbours : int
        Neighbours per target point of the graph that ``step`` walks from the warm starts
        (count; 0: no graph).
    graph_rms_spacings : float
        ``step`` walks the graph (and builds it, the first time) while the last step's RMS
        distance is within this many target point spacings (gain): farther, few walks certify
        their answer.

    References
    ----------
    The costs of the hash, the tree and the graph: ``docs/speed.md``.
    """

    near_cell_spacings: float = number(5.0, above=0.0)
    near_query_min: int = count(256, least=0)
    hash_miss_limit: float = fraction(0.5)
    graph_neighbours: int = count(8, least=0)
    graph_rms_spacings: float = number(3.0, least=0.0)
