"""Small helpers that several test modules share: a fake clock and a byte stream cut up."""

from __future__ import annotations

import threading
from typing import List, Sequence


class FakeClock:
    """Monotonic seconds that move only when the test says so (``advance``, or set ``t``).

    A device core's threads may read it while the test moves it; the lock keeps that clean.
    """

    def __init__(self, t: float = 1000.0) -> None:
        self.t = t
        self._lock = threading.Lock()

    def __call__(self) -> float:
        with self._lock:
            return self.t

    def advance(self, dt: float) -> float:
        """Move the clock on by ``dt`` seconds; return the new time."""
        with self._lock:
            self.t += dt
            return self.t


def split(data: bytes, cuts: Sequence[int]) -> List[bytes]:
    """Cut ``data`` at the positions ``cuts`` (taken modulo its length + 1), in order."""
    points = sorted({c % (len(data) + 1) for c in cuts})
    bounds = [0] + points + [len(data)]
    return [data[a:b] for a, b in zip(bounds, bounds[1:])]
