"""Frozen dataclass records copied with changes on the hot paths, without ``replace``'s work.

``dataclasses.replace`` runs ``__init__`` field by field (5-10 us for the parachute's snapshot,
which every status frame replaces; ~1 us this way). Only for frozen dataclasses without
``__post_init__`` or derived fields: the copy is the old instance's ``__dict__`` with the
changes laid over it.
"""

from __future__ import annotations

from dataclasses import fields
from typing import Any, Dict, FrozenSet, TypeVar

T = TypeVar('T')

_FIELDS: Dict[type, FrozenSet[str]] = {}


def evolve(record: T, **changes: Any) -> T:
    """Return a copy of `record` with `changes`; unknown names raise TypeError, as replace()."""
    cls = type(record)
    names = _FIELDS.get(cls)
    if names is None:
        names = _FIELDS[cls] = frozenset(f.name for f in fields(cls))
    unknown = changes.keys() - names
    if unknown:
        raise TypeError(f'{cls.__name__} has no field(s) {", ".join(sorted(unknown))}')
    new = object.__new__(cls)
    state = new.__dict__
    state.update(record.__dict__)
    state.update(changes)
    return new
