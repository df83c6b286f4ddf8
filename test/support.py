"""Helpers that several test modules share: a fake clock, byte streams, asking again, stamps."""

from __future__ import annotations

import threading
from typing import Callable, List, Sequence, Tuple, TypeVar

T = TypeVar('T')


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


def ask_again(ask: Callable[[], T], again: Callable[[T], bool],
              attempts: int = 3) -> Tuple[T, int]:
    """Call ``ask`` until ``again(answer)`` is false, at most ``attempts`` times.

    For an answer that is true and says the host was too slow (a reply not read in time, a time
    budget spent): on a loaded host a user asks again, and so does a test. Returns the last
    answer and how many calls it took; the caller asserts on the answer.
    """
    for count in range(1, attempts + 1):
        answer = ask()
        if not again(answer):
            break
    return answer, count


def arm_parachute(ros, service: str = '/parachute/arm'):
    """Arm the parachute over ROS; return the reply, asserted a success.

    The status the arm rule reads may go unanswered past its two tries on a loaded host (the
    virtual module is a process): refused, nothing sent, truly. A user arms again.
    """
    from std_srvs.srv import SetBool  # (here: the core tests use this module with no ROS)
    reply, _ = ask_again(lambda: ros.call(SetBool, service, SetBool.Request(data=True)),
                         lambda r: not r.success and 'status not read' in r.message)
    assert reply.success, reply.message
    return reply


def stamp_s(msg) -> float:
    """Return a stamped ROS message's ``header.stamp`` in seconds."""
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
