"""The clock of a device model: time moves when the caller says so, output leaves when it is due.

A driver's device model (its ``simulation.py``) is plain Python with no clock of its own: a test
moves it in steps, ``VirtualDeviceRunner`` in real time. A model built on `ClockedModel` says
when its next internal event is (``_next_internal_event``) and what happens at the model's time
(``_process_events``), and queues what it sends with ``_queue(due, data)``. `ClockedModel` runs
the events in time order up to the time asked for and hands out the bytes due by then
(``step``, ``advance``); ``next_event_time`` tells the runner when to come back.
"""

from __future__ import annotations

import heapq
from typing import List, Optional, Tuple


class ClockedModel:
    """Base of an event-driven device model, clocked by its caller (no I/O, no threads)."""

    def __init__(self, now: float = 0.0) -> None:
        self._now = float(now)
        self._out: List[Tuple[float, int, bytes]] = []  # heap of (due, sequence, data)
        self._seq = 0

    @property
    def now(self) -> float:
        """The model's current time in seconds."""
        return self._now

    def step(self, now: float) -> bytes:
        """Advance the model to ``now`` and return the bytes it has sent by then."""
        self._advance_to(now)
        return self._collect()

    def advance(self, dt: float) -> bytes:
        """Advance the model by ``dt`` seconds and return the bytes it has sent by then."""
        return self.step(self._now + dt)

    def next_event_time(self) -> Optional[float]:
        """Earliest time at which the model will send or change something on its own."""
        times = [t for t in (self._next_internal_event(),
                             self._out[0][0] if self._out else None) if t is not None]
        return min(times) if times else None

    # -- for the model --------------------------------------------------------------------------

    def _next_internal_event(self) -> Optional[float]:
        """Return when the model next changes on its own, None if never."""
        raise NotImplementedError

    def _process_events(self) -> None:
        """Do what is due at ``self._now``."""
        raise NotImplementedError

    def _advance_to(self, now: float) -> None:
        # An earlier time (two callers racing in a wrapper) means "now": nothing happens twice.
        now = max(float(now), self._now)
        while True:
            t = self._next_internal_event()
            if t is None or t > now:
                break
            self._now = max(self._now, t)
            self._process_events()
        self._now = now

    def _queue(self, due: float, data: bytes) -> None:
        """Send ``data`` at ``due``; data due at the same time leaves in the order queued."""
        self._seq += 1
        heapq.heappush(self._out, (due, self._seq, data))

    def _collect(self) -> bytes:
        out = bytearray()
        while self._out and self._out[0][0] <= self._now:
            out += heapq.heappop(self._out)[2]
        return bytes(out)

    def _drop_output(self) -> None:
        """Forget everything queued (the device lost power)."""
        self._out.clear()
