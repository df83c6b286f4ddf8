"""Half-duplex transactions with a bus of Desheng servos, on top of the shared SerialLink.

No ROS here. :class:`ServoBusLink` owns the bus: one transaction at a time (a priority lock, so an
emergency stop overtakes a read cycle and a service call gets in between two reads), stale input
flushed before each request, exactly the reply of the addressed id with the expected length, a
timeout of the wire time of request + reply plus a margin, bounded retries, chains of READs sent
by the reader thread (the read loop), and frames that expect no reply (broadcast, SYNC WRITE,
ACTION) holding the bus for their own wire time.
"""

from __future__ import annotations

from collections import deque
from contextlib import contextmanager
import threading
import time
from typing import (Any, Callable, Deque, Dict, Iterable, Iterator, Optional, Protocol,
                    Sequence, Tuple)

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.protocol import Reply, StreamDecoder
from uav_serial_common.pty_port import wire_time
from uav_serial_common.serial_link import LinkDown, LinkError, LinkTimeout, SerialLink

__all__ = ['BusBusy', 'LinkDown', 'LinkError', 'LinkTimeout', 'PRIORITY_LOOP',
           'PRIORITY_SERVICE', 'PRIORITY_URGENT', 'DERIVED_MARGIN_S', 'ReadItem', 'ReadPlan',
           'ServoBusLink', 'REPLY_OVERHEAD']

# Priorities of the bus lock: lower number goes first.
PRIORITY_URGENT = 0    # emergency stop, shutdown torque-off
PRIORITY_SERVICE = 1   # commands and service calls
PRIORITY_LOOP = 2      # the read loop
# Reply frame = FF F5 ID LEN STATUS params CHK.
REPLY_OVERHEAD = 6
# Margin beyond the wire time of request + reply when response_timeout_ms is 0 ("derived"):
# the servo answers within ~0.1..1 ms, but a USB-serial adapter holds received bytes for up to its
# latency timer (16 ms by default on FTDI, twice when a reply straddles two periods), and a busy
# companion computer adds scheduling delays. Waiting 2 x 16 + 2 ms costs time only when a servo
# is really missing; a margin that is too short makes healthy servos flap offline.
DERIVED_MARGIN_S = 0.034
# After a frame without a reply, wait this much beyond its wire time before the next one, so a
# servo still parsing it never sees the next header glued to it.
IDLE_GUARD_S = 0.0001
BUS_LOCK_TIMEOUT_S = 2.0
# Weight of the newest outcome in an id's garbled-reply level (GARBLE_WEIGHT of a garbled reply
# raises it, a clean one lowers it): four garbled replies in a row take it past one half, which
# random line noise on one id practically never does, two servos answering at once (S24) soon.
GARBLE_WEIGHT = 0.2


class BusBusy(LinkError):
    """The bus stayed taken by others for too long."""


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

    def next_request(self) -> Optional[Tuple[bytes, Callable[[Reply], bool], float]]:
        bus = self.bus
        entry, self.retry = self.retry, None
        if bus._lock.waiting_above(self.priority):
            # Yield the bus between two READs; a retry that cannot go out has failed.
            if entry is not None:
                self._settle(entry[0], None)
            return None
        if entry is None:
            item = self.plan.next_read()
            if item is None:
                return None
            entry = [item, 0, None]
        stats = bus.link.stats
        entry[2] = (stats.bytes_in, stats.frames_in)
        self.sent.append(entry)
        frame, servo_id, nparams = entry[0][:3]
        return frame, bus._matcher(servo_id, nparams), bus.timeout_for(len(frame), nparams)

    def on_result(self, reply: Optional[Reply]) -> None:
        entry = self.sent.popleft()
        item = entry[0]
        if reply is None:
            self.bus._note_silence(item[1], entry[2])
        if reply is None and entry[1] < item[3]:
            entry[1] += 1
            self.bus.link.stats.retries += 1
            self.retry = entry
            return
        self._settle(item, reply)

    def _settle(self, item: ReadItem, reply: Optional[Reply]) -> None:
        self.bus.transactions += 1
        if reply is None:
            self.bus.failed_transactions += 1
        self.plan.on_read(item[4], reply)


class ServoBusLink:
    """The servo bus behind one serial port.

    Transactions raise ``LinkTimeout`` (no valid reply after every retry), ``LinkDown`` (port
    not open) or ``BusBusy``. ``on_connection(up, reason)`` is called from the reader thread:
    never start a transaction from it.
    """

    def __init__(self, port: str, baud: int, *, response_timeout_ms: float = 0.0,
                 max_retries: int = 1,
                 on_connection: Optional[Callable[[bool, str], None]] = None,
                 logger: Optional[object] = None,
                 backoff_max_s: float = 1.0) -> None:
        self.port = port
        self.baud = baud
        self.max_retries = max_retries
        self.response_timeout_ms = response_timeout_ms
        self.decoder = StreamDecoder('reply')
        self.transactions = 0
        self.failed_transactions = 0
        self.unexpected_frames = 0
        self.requests_by_id = [0] * 256
        self.replies_by_id = [0] * 256
        # Requests of an id answered by bytes that made no frame: a garbled reply, the sign of
        # two servos answering at once (S24) when it keeps happening to one id. garble_level is
        # a moving average of garbled (1) and clean (0) replies per id.
        self.garbled_by_id = [0] * 256
        self.garble_level = [0.0] * 256
        self.link = SerialLink(port, baud, self.decoder, on_frame=self._on_unsolicited,
                               on_connection=on_connection, on_tx=self._on_tx, logger=logger,
                               backoff_max_s=backoff_max_s)
        self._lock = _PriorityLock()
        self._idle_at = 0.0
        self._matchers: Dict[Tuple[int, int], Callable[[Reply], bool]] = {}

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> None:
        """Open the port (the reader thread keeps it open and reconnects)."""
        self.link.start()

    def stop(self) -> None:
        """Close the port and stop the reader thread."""
        self.link.stop()

    @property
    def connected(self) -> bool:
        """Whether the port is open."""
        return self.link.connected

    def wait_connected(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s for the port to be open."""
        return self.link.wait_connected(timeout)

    # -- timing ---------------------------------------------------------------------------------

    @property
    def margin_s(self) -> float:
        """Wait beyond the wire time: response_timeout_ms, or DERIVED_MARGIN_S when it is 0."""
        ms = self.response_timeout_ms
        return ms / 1000.0 if ms and ms > 0 else DERIVED_MARGIN_S

    def timeout_for(self, request_len: int, reply_params: int) -> float:
        """Return the reply timeout of one attempt: wire time of request + reply + margin."""
        return wire_time(request_len + reply_params + REPLY_OVERHEAD, self.baud) + self.margin_s

    def wire_limit_s(self, request_len: int, reply_params: int) -> float:
        """Return the pure wire time of one transaction (for rate comparisons)."""
        return wire_time(request_len + reply_params + REPLY_OVERHEAD, self.baud)

    # -- transactions ---------------------------------------------------------------------------

    def _matcher(self, servo_id: int, nparams: int) -> Callable[[Reply], bool]:
        key = (servo_id, nparams)
        match = self._matchers.get(key)
        if match is None:
            replies = self.replies_by_id
            garble = self.garble_level
            keep = 1.0 - GARBLE_WEIGHT

            def match(reply: Reply, servo_id=servo_id, nparams=nparams) -> bool:
                if reply.servo_id == servo_id and len(reply.params) == nparams:
                    replies[servo_id] += 1
                    garble[servo_id] *= keep
                    return True
                return False
            self._matchers[key] = match
        return match

    def _take(self, priority: int) -> None:
        if not self._lock.acquire(priority, BUS_LOCK_TIMEOUT_S):
            raise BusBusy(f'the bus on {self.port} stayed busy for {BUS_LOCK_TIMEOUT_S:.0f} s')
        idle_at = self._idle_at
        if idle_at:
            delay = idle_at - time.monotonic()
            if delay > 0:
                time.sleep(delay)

    @contextmanager
    def _holding(self, priority: int) -> Iterator[None]:
        """Own the bus for transactions that wait for their replies (the bus is idle after)."""
        self._take(priority)
        try:
            yield
        except LinkError:
            self.failed_transactions += 1
            raise
        finally:
            self._idle_at = 0.0
            self._lock.release()

    def transact(self, frame: bytes, servo_id: int, reply_params: int,
                 priority: int = PRIORITY_SERVICE, retries: Optional[int] = None,
                 timeout: Optional[float] = None) -> Reply:
        """Send one request and return the reply of ``servo_id`` with ``reply_params`` params."""
        if timeout is None:
            timeout = self.timeout_for(len(frame), reply_params)
        if retries is None:
            retries = self.max_retries
        match = self._matcher(servo_id, reply_params)
        with self._holding(priority):
            self.transactions += 1
            stats = self.link.stats
            mark = (stats.bytes_in, stats.frames_in)
            try:
                return self.link.request(frame, match, timeout, retries, flush=True)
            except LinkTimeout:
                self._note_silence(servo_id, mark)
                raise

    def probe(self, frame: bytes, servo_id: int, reply_params: int,
              priority: int = PRIORITY_SERVICE) -> Tuple[Optional[Reply], bool]:
        """Send one request once; return (its reply or None, whether a garbled reply came).

        Garbled = bytes arrived but no frame at all: on a half-duplex bus, the sign of two
        servos answering at once (S24); a plain silence is (None, False).
        """
        garbled = self.garbled_by_id[servo_id]
        try:
            return self.transact(frame, servo_id, reply_params, priority, retries=0), False
        except LinkTimeout:
            return None, self.garbled_by_id[servo_id] > garbled

    def _note_silence(self, servo_id: int, mark: Optional[Tuple[int, int]]) -> None:
        """Count an unanswered request of `servo_id` as garbled if bytes but no frame came."""
        stats = self.link.stats
        if mark is not None and stats.bytes_in > mark[0] and stats.frames_in == mark[1]:
            self.garbled_by_id[servo_id] += 1
            level = self.garble_level[servo_id]
            self.garble_level[servo_id] = level + GARBLE_WEIGHT * (1.0 - level)

    def read_chain(self, plan: 'ReadPlan', priority: int = PRIORITY_LOOP) -> int:
        """READ servos back to back, as ``plan.next_read()`` gives them, until it returns None.

        The next READ goes out the moment the previous reply is matched, from the link's reader
        thread, so a chain costs no thread hand-off per servo, also from one read cycle to the
        next. A READ that gets no reply is sent again at once, up to its own retries; then
        ``plan.on_read(tag, None)``. Replies reach ``plan.on_read(tag, reply)`` on the reader
        thread, after the next READ is on its way. The chain stops early, between two READs,
        when a caller of higher priority waits for the bus. Returns the READs sent.
        """
        chain = _ReadChain(self, plan, priority)
        with self._holding(priority):
            return self.link.request_chain(chain, flush=True)

    def send(self, frame: bytes, priority: int = PRIORITY_SERVICE) -> None:
        """Send a frame that gets no reply; the bus stays taken for its wire time."""
        self._take(priority)
        try:
            self.transactions += 1
            self.link.write(frame)
            self._idle_at = time.monotonic() + wire_time(len(frame), self.baud) + IDLE_GUARD_S
        except LinkError:
            self.failed_transactions += 1
            raise
        finally:
            self._lock.release()

    def drain(self) -> None:
        """Block until the last frame without a reply has left the wire."""
        delay = self._idle_at - time.monotonic()
        if delay > 0:
            time.sleep(delay)

    def urgent_pending(self, priority: int = PRIORITY_LOOP) -> bool:
        """Whether a caller of higher priority than ``priority`` waits for the bus."""
        return self._lock.waiting_above(priority)

    # -- instructions ---------------------------------------------------------------------------

    def ping(self, servo_id: int, priority: int = PRIORITY_SERVICE,
             retries: Optional[int] = None, timeout: Optional[float] = None) -> Reply:
        """PING one servo; returns its status reply."""
        return self.transact(proto.encode_ping(servo_id), servo_id, 0, priority, retries,
                             timeout)

    def read(self, servo_id: int, address: int, length: int,
             priority: int = PRIORITY_SERVICE, retries: Optional[int] = None) -> Reply:
        """READ ``length`` bytes at ``address``."""
        return self.transact(proto.encode_read(servo_id, address, length), servo_id, length,
                             priority, retries)

    def write(self, servo_id: int, address: int, data: bytes = b'',
              priority: int = PRIORITY_SERVICE) -> Optional[Reply]:
        """WRITE; unicast waits for the acknowledgement, broadcast (254) only for the wire."""
        frame = proto.encode_write(servo_id, address, data)
        if servo_id == proto.BROADCAST_ID:
            self.send(frame, priority)
            return None
        return self.transact(frame, servo_id, 0, priority)

    def reg_write(self, servo_id: int, address: int, data: bytes,
                  priority: int = PRIORITY_SERVICE) -> Reply:
        """REG WRITE (staged until ACTION); the servo acknowledges it (S13)."""
        return self.transact(proto.encode_reg_write(servo_id, address, data), servo_id, 0,
                             priority)

    def action(self, priority: int = PRIORITY_SERVICE) -> None:
        """Broadcast ACTION: staged writes execute now."""
        self.send(proto.encode_action(), priority)

    def reset(self, servo_id: int, priority: int = PRIORITY_SERVICE) -> Reply:
        """RESET one servo to factory settings."""
        return self.transact(proto.encode_reset(servo_id), servo_id, 0, priority)

    def sync_write_positions(self, targets: Sequence[Tuple[int, int, int]],
                             priority: int = PRIORITY_SERVICE) -> list:
        """SYNC WRITE (id, ticks, ms) in as few frames as fit; returns the frames sent."""
        frames = [proto.encode_sync_write_positions(targets[k:k + proto.MAX_SYNC_WRITE_POSITIONS])
                  for k in range(0, len(targets), proto.MAX_SYNC_WRITE_POSITIONS)]
        for frame in frames:
            self.send(frame, priority)
        return frames

    def scan(self, ids: Iterable[int], timeout: Optional[float] = None,
             priority: int = PRIORITY_SERVICE) -> list:
        """PING each id once (no retries); returns the ids that answered, garbled or not."""
        found = []
        for servo_id in ids:
            garbled = self.garbled_by_id[servo_id]
            try:
                self.ping(servo_id, priority, retries=0, timeout=timeout)
            except LinkTimeout:
                if self.garbled_by_id[servo_id] == garbled:
                    continue
            found.append(servo_id)
        return found

    # -- counters -------------------------------------------------------------------------------

    @property
    def checksum_errors(self) -> int:
        """Candidate reply frames rejected by their checksum."""
        return self.decoder.checksum_errors

    def _on_unsolicited(self, frame: Reply) -> None:
        # Late replies (after a timeout) and duplicate-id replies (S24) end up here.
        self.unexpected_frames += 1
        self.replies_by_id[frame.servo_id] += 1

    def _on_tx(self, data: bytes) -> None:
        # Every unicast instruction is answered (S13), broadcast ones never.
        if len(data) > 4 and data[2] != proto.BROADCAST_ID:
            self.requests_by_id[data[2]] += 1

    def surplus_replies(self, servo_id: int) -> int:
        """Return replies minus requests of ``servo_id`` so far; growing means a duplicate id.

        Lost replies make it smaller; a reply comes late at most once per request. So when it
        grows, more than one servo answers to this id (S24): on a real bus their replies
        collide, and no reading of that id can be trusted.
        """
        return self.replies_by_id[servo_id] - self.requests_by_id[servo_id]
