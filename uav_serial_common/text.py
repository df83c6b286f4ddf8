"""Bounded text for replies and log lines: name a few offenders, count the rest.

A request may carry thousands of entries, each a string of any length. A refusal that lists them
all is unreadable and, logged, floods the log; these helpers keep every message short whatever the
input.
"""

from __future__ import annotations

from typing import Any, Iterable

MAX_ITEM_CHARS = 40
MAX_ITEMS = 5
MAX_MESSAGE_CHARS = 600


def short(value: Any, limit: int = MAX_ITEM_CHARS) -> str:
    """Return ``repr``-like text of `value` (strings quoted), at most `limit` characters."""
    text = repr(value) if isinstance(value, str) else str(value)
    if len(text) <= limit:
        return text
    return text[:max(0, limit - 4)] + '...' + (text[-1] if isinstance(value, str) else '')


def few(items: Iterable[Any], limit: int = MAX_ITEMS) -> str:
    """Return ``a, b, c and 9997 more``: the first `limit` items, then how many are left out."""
    shown = []
    count = 0
    for item in items:
        if count < limit:
            shown.append(short(item))
        count += 1
    text = ', '.join(shown)
    if count > limit:
        text += f' and {count - limit} more'
    return text


def clip(text: str, limit: int = MAX_MESSAGE_CHARS) -> str:
    """Return `text` cut to `limit` characters, saying how much was cut."""
    if len(text) <= limit:
        return text
    cut = len(text) - limit
    return f'{text[:limit]}... ({cut} more characters)'
