"""The read loop's cycles as a plan for the link's chain of READs (the clock added).

What is next and when is the schedule's (:class:`~desheng_servo_ros.schedule.ReadSchedule`);
:class:`ReadCycles` gives it the clock and the servo list, and hands results and cycle starts
and ends to the core. It runs on the link's reader thread (replies) and the read loop.
"""

from __future__ import annotations

from typing import Any, Callable, Optional, Sequence, Tuple

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.link import ReadItem
from desheng_servo_ros.schedule import EMPTY, ReadSchedule
from desheng_servo_ros.state import ServoRecord


class ReadCycles:
    """The read loop's cycles (the schedule's ``ReadSchedule``) as a plan for a chain of READs.

    The link asks for each next READ the moment the previous reply is in, so consecutive cycles
    follow each other on the wire without a gap when ``publish_rate_hz`` asks for more than the
    bus carries; otherwise the chain ends after a cycle and the read loop waits for the next
    one. Runs on the link's reader thread (replies) and the read loop (timeouts). What is next
    and when is the schedule's; this adds the clock, the servo list and where results and cycle
    starts/ends go. ``enabled`` (READs may go out) is an attribute its owner sets: it is read
    for every READ.
    """

    def __init__(self, *, clock: Callable[[], float], servos: Callable[[], Sequence[ServoRecord]],
                 period_s: float,
                 on_read: Callable[[ServoRecord, int, float, Optional[proto.Reply]], None],
                 on_cycle_start: Callable[[float], None],
                 on_cycle_done: Callable[[], None], retries: int = 1) -> None:
        self._clock = clock
        self._servos = servos
        self.schedule = ReadSchedule(period_s, retries, clock())
        self.enabled = False
        self._on_read = on_read
        self._on_cycle_start = on_cycle_start
        self._on_cycle_done = on_cycle_done
        self.behind_logged = False

    @property
    def in_cycle(self) -> bool:
        """Whether a cycle has READs left to send."""
        return self.schedule.in_cycle

    @property
    def next_cycle(self) -> float:
        """When the next cycle is due (clock time)."""
        return self.schedule.next_cycle

    def reset(self) -> None:
        """Drop the cycle in progress (the servo list or the port changed); the next is due."""
        self.schedule.reset(self._clock())

    def next_read(self) -> Optional[ReadItem]:
        """Return the next READ of this cycle, or of the next one when it is due, else None."""
        if not self.enabled:
            return None
        schedule = self.schedule
        if schedule.pos >= len(schedule.plan) and not self._start_cycle():
            return None
        return schedule.take()

    def on_read(self, tag: Tuple[ServoRecord, int, float, bool],
                reply: Optional[proto.Reply]) -> None:
        """Take the result of one READ; the last one of a cycle completes it."""
        s, kind, started, last = tag
        self._on_read(s, kind, started, reply)
        if last:
            self._on_cycle_done()

    def start(self) -> bool:
        """Plan a cycle now if one is due (for read_cycle); returns whether it has READs."""
        self.schedule.plan, self.schedule.pos = [], 0
        return self._start_cycle()

    def _start_cycle(self) -> bool:
        now = self._clock()
        schedule = self.schedule
        if not schedule.begin_cycle(now):
            return False
        self._on_cycle_start(now)
        if schedule.plan_cycle(self._servos()) == EMPTY:
            # Every servo is offline and none is due for a probe: publish that all the same.
            self._on_cycle_done()
            return False
        return True


class _OneCycle:
    """A ReadPlan of the cycle planned in a ReadCycles, and no more (read_cycle)."""

    def __init__(self, cycles: ReadCycles) -> None:
        self.cycles = cycles

    def next_read(self) -> Optional[ReadItem]:
        if not self.cycles.in_cycle:
            return None
        return self.cycles.next_read()

    def on_read(self, tag: Any, reply: Optional[proto.Reply]) -> None:
        self.cycles.on_read(tag, reply)
