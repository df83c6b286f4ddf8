"""A caller's frame or request handed to whichever thread carries it out, and its fate.

A caller makes a :class:`Ticket`, hands it over with its frame (to a plan, a queue, a read
chain), then waits for it with a timeout. Whichever thread carries the frame out settles the
ticket once with what became of it: an ``outcome`` (the carrier's word: ``'sent'``,
``'refused'``, ...) and a ``detail`` (why, a reply, an exception). The first settle wins; a
later one changes nothing. The ticket holds its own fate, so a settle after the caller gave up
waiting keeps nothing for nobody: the ticket goes when the last thread lets go of it.

No clock: a time the carrier needs (when the frame left) is part of its ``detail``.
"""

from __future__ import annotations

import threading
from typing import Any

__all__ = ['Ticket']


class Ticket:
    """What became of one frame or request handed to another thread, settled once."""

    __slots__ = ('_lock', '_event', 'outcome', 'detail', '__weakref__')

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._event = threading.Event()
        self.outcome: Any = None
        """What became of it (the carrier's word), once `settled`."""
        self.detail: Any = None
        """Why, or what came of it (a reply, an exception), once `settled`."""

    @property
    def settled(self) -> bool:
        """Whether its fate is known."""
        return self._event.is_set()

    def settle(self, outcome: Any, detail: Any = None) -> bool:
        """Record what became of it and wake whoever waits; False if it was settled already."""
        with self._lock:
            if self._event.is_set():
                return False
            self.outcome, self.detail = outcome, detail
            self._event.set()
        return True

    def wait(self, timeout: float) -> bool:
        """Wait at most ``timeout`` s for its fate; return whether it is settled."""
        return self._event.wait(max(0.0, timeout))

    def __repr__(self) -> str:
        state = f'{self.outcome!r}, {self.detail!r}' if self.settled else 'pending'
        return f'{type(self).__name__}({state})'
