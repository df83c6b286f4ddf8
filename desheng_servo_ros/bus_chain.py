"""The bus lock, frames handed to the read chain, and the read chain: the link's machinery.

:class:`PriorityLock` serves the bus's callers by priority (an emergency stop before commands
and services, those before the read loop); :class:`Posted` are frames without a reply handed to
a running chain, each a :class:`~uav_serial_common.ticket.Ticket` its poster may wait on (the
thread that wrote or dropped them settles it); :class:`ReadChain` runs a :class:`ReadPlan` as a
request chain of the serial link, deciding at each READ boundary what goes next by the
schedule's ``next_on_bus``. Used by :class:`~desheng_servo_ros.link.ServoBusLink`, which owns
the port.
"""

from __future__ import annotations

from collections import deque
import threading
import time
from typing import Any, Callable, Deque, Optional, Protocol, Sequence, Tuple, TYPE_CHECKING

from desheng_servo_ros.protocol import Reply
from desheng_servo_ros.schedule import IDLE_GUARD_S, next_on_bus, POSTED, YIELD
from uav_serial_common.pty_port import wire_time
from uav_serial_common.serial_link import LinkError
from uav_serial_common.ticket import Ticket

if TYPE_CHECKING:  # pragma: no cover
    from desheng_servo_ros.link import ServoBusLink

# Priorities of the bus lock: lower number goes first.
PRIORITY_URGENT = 0    # emergency stop, shutdown torque-off
PRIORITY_SERVICE = 1   # commands and service calls
PRIORITY_LOOP = 2      # the read loop


class BusBusy(LinkError):
    """The bus stayed taken by others for too long."""


class Posted(Ticket):
    """Frames without a reply handed to the read chain (`ServoBusLink.post`), and their fate.

    Settled once (`settle`) by whichever thread wrote them or dropped them: ``'written'`` or
    ``'failed'``, with the error and when it happened as its ``detail``.
    """

    __slots__ = ('frames', 'size')

    def __init__(self, frames: Sequence[bytes]) -> None:
        super().__init__()
        self.frames = list(frames)
        self.size = sum(map(len, frames))
        """Bytes of all the frames."""

    @property
    def error(self) -> Optional[LinkError]:
        """What writing them raised (or why they were dropped), once `settled`."""
        return self.detail[0] if self.settled else None

    @property
    def written_at(self) -> float:
        """When the last frame had left the line (monotonic), once `settled`."""
        return self.detail[1] if self.settled else 0.0

    def settle(self, error: Optional[LinkError] = None) -> bool:  # type: ignore[override]
        """Record the outcome and wake whoever waits; False if it was settled already."""
        return super().settle('written' if error is None else 'failed',
                              (error, time.monotonic()))


class _PriorityLock:
    """A lock whose waiters are served by priority (lower number first), then arrival order."""

    def __init__(self, levels: int = 3) -> None:
        self._cond = threading.Condition(threading.Lock())
        self._busy = False
        self._waiting = [0] * levels

    def acquire(self, level: int, timeout: float) -> bool:
        with self._cond:
            if not self._busy and not any(self._waiting[:level]):
                self._busy = True
                return True
            deadline = time.monotonic() + timeout
            self._waiting[level] += 1
            try:
                while self._busy or any(self._waiting[:level]):
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        return False
                    self._cond.wait(remaining)
                self._busy = True
                return True
            finally:
                self._waiting[level] -= 1

    def release(self) -> None:
        with self._cond:
            self._busy = False
            self._cond.notify_all()

    def waiting_above(self, level: int) -> bool:
        """Whether someone of a higher priority than ``level`` is waiting."""
        return any(self._waiting[:level])


# One READ of a chain: (frame, servo id, reply params, retries, tag for the plan).
ReadItem = Tuple[bytes, int, int, int, Any]


class ReadPlan(Protocol):
    """What :meth:`ServoBusLink.read_chain` asks of its caller."""

    def next_read(self) -> Optional[ReadItem]:
        """Return the next READ, or None to end the chain (called on the reader thread)."""

    def on_read(self, tag: Any, reply: Optional[Reply]) -> None:
        """Take the reply of the READ tagged `tag` (None: no reply after its retries)."""


class _ReadChain:
    """A :class:`ReadPlan` as a request chain of the serial link, with retries per READ."""

    __slots__ = ('bus', 'plan', 'priority', 'sent', 'retry')
    # An entry of `sent` is [item, attempts, (bytes_in, frames_in) when it was sent].

    def __init__(self, bus: 'ServoBusLink', plan: ReadPlan, priority: int) -> None:
        self.bus = bus
        self.plan = plan
        self.priority = priority
        self.sent: Deque[list] = deque()  # [item, attempts] of READs awaiting their result
        self.retry: Optional[list] = None

    def next_request(self) -> Optional[Tuple[bytes, Optional[Callable[[Reply], bool]], float]]:
        bus = self.bus
        if bus._posted_item is not None:
            bus._posted_done()  # the frame before this request left without an error
        entry, self.retry = self.retry, None
        step = next_on_bus(bus._lock.waiting_above(self.priority), bool(bus._posted),
                           entry is not None)
        if step == YIELD:
            # Yield the bus between two READs; a retry that cannot go out has failed.
            if entry is not None:
                self._settle(entry[0], None)
            return None
        if step == POSTED:
            # A frame without a reply (a command) goes out between two READs; the READ to be
            # retried, if any, follows it.
            self.retry = entry
            frame = bus._next_posted()
            return frame, None, wire_time(len(frame), bus.baud) + IDLE_GUARD_S
        stats = bus.link.stats
        if entry is None:
            item = self.plan.next_read()
            if item is None:
                return None
            entry = [item, 0, None]
        else:
            stats.retries += 1  # counted as it goes out: one that yields the bus never does
        entry[2] = (stats.bytes_in, stats.frames_in)
        self.sent.append(entry)
        frame, servo_id, nparams = entry[0][:3]
        return (frame, bus._matcher(servo_id, nparams),
                bus.timeout_for(len(frame), nparams, servo_id))

    def on_result(self, reply: Optional[Reply]) -> None:
        entry = self.sent.popleft()
        item = entry[0]
        if reply is None:
            self.bus._note_silence(item[1], entry[2])
        if reply is None and entry[1] < item[3]:
            entry[1] += 1
            self.retry = entry
            return
        self._settle(item, reply)

    def _settle(self, item: ReadItem, reply: Optional[Reply]) -> None:
        self.bus.transactions += 1
        if reply is None:
            self.bus.failed_transactions += 1
        self.plan.on_read(item[4], reply)
