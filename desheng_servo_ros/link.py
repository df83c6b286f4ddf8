"""Half-duplex transactions with a bus of Desheng servos, on top of the shared SerialLink.

No ROS here. :class:`ServoBusLink` owns the bus: one transaction at a time (a priority lock, so an
emergency stop overtakes a read cycle and a service call gets in between two reads), stale input
flushed before each request, exactly the reply of the addressed id with the expected length, a
timeout of the wire time of request + reply plus a margin, bounded retries, chains of READs sent
by the reader thread (the read loop), and frames that expect no reply (broadcast, SYNC WRITE,
ACTION) holding the bus for their own wire time; while a chain runs, such frames are handed to it
(`post`) and go out between two READs from the reader thread, with no thread hand-off.

The reply margin is derived from the port on every (re)open (`uav_serial_common.usb_latency`: a
USB adapter's latency timer is lowered where allowed; a pty or a 1 ms adapter gets a few ms), and
per servo from replies that came late (a servo that answers slowly gets a longer wait, forgotten
again after a run of timely replies). A scan PINGs with the short margin and collects late
replies by id while it goes on, then confirms those ids with a long wait (docs/protocols.md,
"Scan").
"""

from __future__ import annotations

from collections import deque
from contextlib import contextmanager
import threading
import time
from typing import (Any, Callable, Deque, Dict, Iterable, Iterator, List, Optional, Sequence,
                    Tuple)

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.bus_chain import (  # noqa: F401 - re-exported
    _PriorityLock, _ReadChain, BusBusy, Posted, PRIORITY_LOOP, PRIORITY_SERVICE,
    PRIORITY_URGENT, ReadItem, ReadPlan)
from desheng_servo_ros.bus_scan import sweep
from desheng_servo_ros.protocol import Reply, StreamDecoder
from desheng_servo_ros.schedule import (IDLE_GUARD_S, next_on_bus, REPLY_OVERHEAD,
                                        sync_write_frames, YIELD)
from uav_serial_common.pty_port import wire_time
from uav_serial_common.serial_link import LinkDown, LinkError, LinkTimeout, SerialLink
from uav_serial_common.usb_latency import BASE_MARGIN_S, inspect_latency_timer, LatencyReport

__all__ = ['BusBusy', 'LinkDown', 'LinkError', 'LinkTimeout', 'PRIORITY_LOOP',
           'PRIORITY_SERVICE', 'PRIORITY_URGENT', 'DERIVED_MARGIN_S', 'ReadItem', 'ReadPlan',
           'Posted', 'ServoBusLink', 'REPLY_OVERHEAD', 'sync_write_frames']

# Margin beyond the wire time of request + reply when response_timeout_ms is 0 ("derived") and the
# port has not been looked at yet: the servo answers within ~0.1..1 ms, but a USB-serial adapter
# holds received bytes for up to its latency timer (16 ms by default on FTDI, twice when a reply
# straddles two periods). On open the margin is derived from the port itself (LatencyReport).
DERIVED_MARGIN_S = 0.034
# A servo whose reply came later than the margin gets its own: LEARN_FACTOR times what it took,
# plus the base margin, at most MAX_LEARNED_MARGIN_S; forgotten after FORGET_AFTER_REPLIES timely
# replies in a row (a late reply may also be a moment the host stalled).
LEARN_FACTOR = 1.5
MAX_LEARNED_MARGIN_S = 0.1
FORGET_AFTER_REPLIES = 20
BUS_LOCK_TIMEOUT_S = 2.0
# Weight of the newest outcome in an id's garbled-reply level (GARBLE_WEIGHT of a garbled reply
# raises it, a clean one lowers it): four garbled replies in a row take it past one half, which
# random line noise on one id practically never does, two servos answering at once (S24) soon.
GARBLE_WEIGHT = 0.2
# A request that got no reply may still be answered, late (the device or the host stalled): its
# reply is then no second servo. Such a late reply is expected for LATE_REPLY_S after the wait
# for it ended; one that comes later counts as a reply no request explains.
LATE_REPLY_S = 2.0


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
                 backoff_max_s: float = 1.0, adjust_latency_timer: bool = True,
                 on_latency: Optional[Callable[[LatencyReport], None]] = None) -> None:
        self.port = port
        self.baud = baud
        self.max_retries = max_retries
        self.adjust_latency_timer = adjust_latency_timer
        # What the port's latency timer was and what was done, as of the last open (None
        # before the first); the derived margin follows it.
        self.latency: Optional[LatencyReport] = None
        self._on_latency = on_latency
        self._derived_margin = DERIVED_MARGIN_S
        self._response_timeout_ms = response_timeout_ms
        self._margin = self._pick_margin()
        self._wire: Dict[Tuple[int, int], float] = {}
        # Per id: when the last request went out and its length (late replies are judged by
        # them), the margin learned from late replies, timely replies since.
        self.sent_at = [0.0] * 256
        self.sent_len = [0] * 256
        self.slow_margin = [0.0] * 256
        self._timely = [0] * 256
        self._late_sink: Optional[Dict[int, float]] = None
        # Frames without a reply handed to the running read chain (post); _posting says
        # whether a chain takes them.
        self._posted: Deque[Posted] = deque()
        self._posted_item: Optional[Posted] = None
        self._posting = False
        self._post_lock = threading.Lock()
        self.decoder = StreamDecoder('reply')
        self.transactions = 0
        self.failed_transactions = 0
        self.unexpected_frames = 0
        self.requests_by_id = [0] * 256
        self.replies_by_id = [0] * 256
        self._unsolicited: Dict[Tuple[int, int], int] = {}
        # Per id: until when each request that went unanswered may still be answered late
        # (oldest first), and the replies that no request explains (S24: a second servo).
        self._owed: List[Deque[float]] = [deque() for _ in range(256)]
        self.surplus_by_id = [0] * 256
        # Requests of an id answered by bytes that made no frame: a garbled reply, the sign of
        # two servos answering at once (S24) when it keeps happening to one id. garble_level is
        # a moving average of garbled (1) and clean (0) replies per id.
        self.garbled_by_id = [0] * 256
        self.garble_level = [0.0] * 256
        self.link = SerialLink(port, baud, self.decoder, on_frame=self._on_unsolicited,
                               on_connection=on_connection, on_tx=self._on_tx, logger=logger,
                               backoff_max_s=backoff_max_s, on_open=self._on_port_open)
        self._lock = _PriorityLock()
        self._closed = False  # after send_last: no transaction any more
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
    def port_open(self) -> bool:
        """Whether the port is open."""
        return self.link.port_open

    def wait_port_open(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s for the port to be open."""
        return self.link.wait_port_open(timeout)

    # -- timing ---------------------------------------------------------------------------------

    @property
    def response_timeout_ms(self) -> float:
        """The margin the user set [ms]; 0 = derived from the port."""
        return self._response_timeout_ms

    @response_timeout_ms.setter
    def response_timeout_ms(self, value: float) -> None:
        self._response_timeout_ms = value
        self._margin = self._pick_margin()

    def _pick_margin(self) -> float:
        ms = self._response_timeout_ms
        return ms / 1000.0 if ms and ms > 0 else self._derived_margin

    @property
    def margin_s(self) -> float:
        """Wait beyond the wire time: response_timeout_ms, or the port's derived margin if 0."""
        return self._margin

    def margin_for(self, servo_id: int) -> float:
        """Return the margin of one servo: the bus's, or longer when it answered late."""
        slow = self.slow_margin[servo_id]
        return slow if slow > self._margin else self._margin

    def timeout_for(self, request_len: int, reply_params: int, servo_id: int = 0) -> float:
        """Return the reply timeout of one attempt: wire time of request + reply + margin."""
        key = (request_len, reply_params)
        wire = self._wire.get(key)
        if wire is None:
            wire = self._wire[key] = wire_time(request_len + reply_params + REPLY_OVERHEAD,
                                               self.baud)
        slow = self.slow_margin[servo_id]
        return wire + (slow if slow > self._margin else self._margin)

    def _on_port_open(self, port: Any) -> None:
        """Look at the port's latency timer on every (re)open (reader thread, before use)."""
        def low_latency() -> None:
            port.set_low_latency_mode(True)
        report = inspect_latency_timer(self.port, allow_change=self.adjust_latency_timer,
                                       request_low_latency=low_latency)
        self.latency = report
        self._derived_margin = report.reply_margin_s()
        self._margin = self._pick_margin()
        if self._on_latency is not None:
            self._on_latency(report)

    def _learn(self, servo_id: int, margin: float) -> None:
        """Give `servo_id` a longer margin after a reply that needed `margin` beyond its wire."""
        value = min(MAX_LEARNED_MARGIN_S, LEARN_FACTOR * margin + BASE_MARGIN_S)
        self._timely[servo_id] = 0
        if value > self.slow_margin[servo_id]:
            self.slow_margin[servo_id] = value

    def _reply_margin(self, servo_id: int, reply_len: int) -> float:
        """Return how long the reply just received took beyond the wire time of its exchange."""
        arrived = self.link.last_rx_time or time.monotonic()
        return arrived - self.sent_at[servo_id] - wire_time(
            self.sent_len[servo_id] + reply_len, self.baud)

    def _slow_servo_replied(self, servo_id: int, reply_len: int) -> None:
        """Count a timely reply of a servo with a learned margin; forget it after a run."""
        if self._reply_margin(servo_id, reply_len) > self._margin:
            self._timely[servo_id] = 0
            return
        self._timely[servo_id] += 1
        if self._timely[servo_id] >= FORGET_AFTER_REPLIES:
            self.slow_margin[servo_id] = 0.0
            self._timely[servo_id] = 0

    # -- transactions ---------------------------------------------------------------------------

    def _matcher(self, servo_id: int, nparams: int) -> Callable[[Reply], bool]:
        key = (servo_id, nparams)
        match = self._matchers.get(key)
        if match is None:
            replies = self.replies_by_id
            garble = self.garble_level
            slow = self.slow_margin
            keep = 1.0 - GARBLE_WEIGHT

            def match(reply: Reply, servo_id=servo_id, nparams=nparams) -> bool:
                if reply.servo_id == servo_id and len(reply.params) == nparams:
                    replies[servo_id] += 1
                    garble[servo_id] *= keep
                    if slow[servo_id]:
                        self._slow_servo_replied(servo_id, len(reply.raw))
                    return True
                return False
            self._matchers[key] = match
        return match

    def _take(self, priority: int) -> None:
        if not self._lock.acquire(priority, BUS_LOCK_TIMEOUT_S):
            raise BusBusy(f'the bus on {self.port} stayed busy for {BUS_LOCK_TIMEOUT_S:.0f} s')
        if self._closed:
            self._lock.release()
            raise LinkDown(f'{self.port}: the driver is shutting down')
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
            self._lock.release()

    def transact(self, frame: bytes, servo_id: int, reply_params: int,
                 priority: int = PRIORITY_SERVICE, retries: Optional[int] = None,
                 timeout: Optional[float] = None, flush: bool = True) -> Reply:
        """Send one request and return the reply of ``servo_id`` with ``reply_params`` params.

        Sent again up to `retries` times when no reply comes; a caller of higher priority that
        waits (an emergency stop) goes between two attempts. `flush` False keeps what arrived
        before the request (a scan collects late replies).
        """
        if timeout is None:
            timeout = self.timeout_for(len(frame), reply_params, servo_id)
        if retries is None:
            retries = self.max_retries
        match = self._matcher(servo_id, reply_params)
        self._take(priority)
        held = True
        attempt = 0
        try:
            self.transactions += 1
            stats = self.link.stats
            mark = (stats.bytes_in, stats.frames_in)
            while True:
                try:
                    return self.link.request(frame, match, timeout, 0, flush=flush)
                except LinkTimeout:
                    if attempt >= retries:
                        self._note_silence(servo_id, mark)
                        raise
                    self._note_silence(servo_id, None)
                attempt += 1
                stats.timeouts -= 1  # one per request, as SerialLink counts them
                stats.retries += 1
                if next_on_bus(self._lock.waiting_above(priority), False, True) == YIELD:
                    # An emergency stop waits: it goes between two attempts (schedule.py).
                    held = False
                    self._lock.release()
                    self._take(priority)
                    held = True
        except LinkError as exc:
            self.failed_transactions += 1
            exc.sent = exc.sent or attempt > 0
            raise
        finally:
            if held:
                self._lock.release()

    def probe(self, frame: bytes, servo_id: int, reply_params: int,
              priority: int = PRIORITY_SERVICE,
              flush: bool = True) -> Tuple[Optional[Reply], bool]:
        """Send one request once; return (its reply or None, whether a garbled reply came).

        Garbled = bytes arrived but no frame at all: on a half-duplex bus, the sign of two
        servos answering at once (S24); a plain silence is (None, False). `flush` False keeps
        what arrived before the request (as `transact`).
        """
        garbled = self.garbled_by_id[servo_id]
        try:
            return self.transact(frame, servo_id, reply_params, priority, retries=0,
                                 flush=flush), False
        except LinkTimeout:
            return None, self.garbled_by_id[servo_id] > garbled

    def _note_silence(self, servo_id: int, mark: Optional[Tuple[int, int]]) -> None:
        """Note an unanswered request of `servo_id`, which may still be answered late.

        Counted as garbled if bytes but no frame came since `mark` (None: not judged).
        """
        self._owed[servo_id].append(time.monotonic() + LATE_REPLY_S)
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
            with self._post_lock:
                self._posting = True
            error: Optional[LinkError] = None
            try:
                return self.link.request_chain(chain, flush=True)
            except LinkError as exc:
                error = exc
                raise
            finally:
                self._end_posting(error)

    def post(self, frames: Sequence[bytes], wait_s: Optional[float] = None) -> Optional[Posted]:
        """Hand frames without a reply to the running read chain; None if none runs.

        The chain's reader thread writes them between two READs (after the reply in flight),
        each holding the bus for its wire time; no thread hand-off. With `wait_s`, block until
        they are written: raises what writing raised, or BusBusy after `wait_s`.
        """
        item = Posted(frames)
        with self._post_lock:
            if not self._posting:
                return None
            self._posted.append(item)
        if wait_s is not None:
            if not item.wait(wait_s):
                raise BusBusy(f'the bus on {self.port} took no command for {wait_s:.0f} s')
            if item.error is not None:
                raise item.error
        return item

    def discard_posted(self) -> None:
        """Drop frames posted and not sent yet (an emergency stop); their waiters are told."""
        with self._post_lock:
            items = list(self._posted)
            self._posted.clear()
        for item in items:
            item.settle(LinkError('dropped by an emergency stop'))

    def _next_posted(self) -> bytes:
        """Take the next posted frame (reader thread, chain lock held)."""
        with self._post_lock:
            item = self._posted[0]
            frame = item.frames.pop(0)
            if not item.frames:
                self._posted.popleft()
                self._posted_item = item
        self.transactions += 1
        return frame

    def _posted_done(self, error: Optional[LinkError] = None) -> None:
        item, self._posted_item = self._posted_item, None
        if item is not None:
            item.settle(error)

    def _end_posting(self, error: Optional[LinkError]) -> None:
        """After a chain (bus held): settle its last posted frame, send what is still posted."""
        with self._post_lock:
            self._posting = False
            left = list(self._posted)
            self._posted.clear()
        self._posted_done(error)
        for item in left:
            try:
                for frame in item.frames:
                    self._write_held(frame)
            except LinkError as exc:
                item.settle(exc)
                continue
            item.settle()

    def _write_held(self, frame: bytes) -> None:
        """Write a frame without a reply while holding the bus; it holds it for its wire time."""
        delay = self._idle_at - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        self.transactions += 1
        try:
            self.link.write(frame)
        except LinkError:
            self.failed_transactions += 1
            raise
        self._idle_at = time.monotonic() + wire_time(len(frame), self.baud) + IDLE_GUARD_S

    def send(self, frame: bytes, priority: int = PRIORITY_SERVICE) -> None:
        """Send a frame that gets no reply; the bus stays taken for its wire time."""
        self._take(priority)
        try:
            self._write_held(frame)
        finally:
            self._lock.release()

    def send_last(self, frames: Sequence[bytes]) -> None:
        """Send `frames` ahead of every waiter, then close the bus to all others for good.

        The shutdown's frames (torque off): a service or command that wanted the bus meanwhile
        gets LinkDown, so nothing follows them on the wire. Returns once they left the line.
        """
        self._take(PRIORITY_URGENT)
        try:
            self._closed = True
            for frame in frames:
                self._write_held(frame)
            self.drain()
        finally:
            self._lock.release()

    def drain(self) -> None:
        """Block until the last frame without a reply has left the wire."""
        delay = self._idle_at - time.monotonic()
        if delay > 0:
            time.sleep(delay)

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
                             priority: int = PRIORITY_SERVICE, wait: bool = True) -> list:
        """SYNC WRITE (id, ticks, ms) in as few frames as fit; returns the frames.

        While the read chain runs they go out from it at the next READ boundary (`post`; with
        `wait`, this returns once they are written), else at once under the bus lock.
        """
        frames = sync_write_frames(targets)
        if self.post(frames, BUS_LOCK_TIMEOUT_S if wait else None) is None:
            for frame in frames:
                self.send(frame, priority)
        return frames

    def scan(self, ids: Iterable[int], priority: int = PRIORITY_SERVICE) -> List[int]:
        """PING each id once; return the ids that answered (cleanly, late or garbled), in order.

        The PINGs use the normal margin, so an absent id costs a few ms; late replies are
        collected by id while the sweep goes on, garbled ones make suspects, and both are
        confirmed with a long wait (`bus_scan.sweep`; docs/protocols.md, "Scan").
        """
        return sweep(self, ids, priority)

    def learn_from(self, servo_id: int, reply: Reply) -> None:
        """Give `servo_id` a margin of its own if `reply` came later than the bus's margin."""
        needed = self._reply_margin(servo_id, len(reply.raw))
        if needed > self._margin:
            self._learn(servo_id, needed)

    # -- counters -------------------------------------------------------------------------------

    @property
    def checksum_errors(self) -> int:
        """Candidate reply frames rejected by their checksum."""
        return self.decoder.checksum_errors

    def _on_unsolicited(self, frame: Reply) -> None:
        # Late replies (after a timeout) and duplicate-id replies (S24) end up here. A reply
        # later than its servo's margin is a slow servo (or a stalled host): it gets a margin of
        # its own. A duplicate's second reply follows the first at once, within the margin.
        servo_id = frame.servo_id
        self.unexpected_frames += 1
        self.replies_by_id[servo_id] += 1
        kind = (servo_id, len(frame.params))
        self._unsolicited[kind] = self._unsolicited.get(kind, 0) + 1
        if not self._late_reply(servo_id):
            self.surplus_by_id[servo_id] += 1
        if self.sent_at[servo_id]:
            needed = self._reply_margin(servo_id, len(frame.raw))
            if needed > self.margin_for(servo_id):
                self._learn(servo_id, needed)
        sink = self._late_sink
        if sink is not None:
            sink.setdefault(servo_id, time.monotonic())

    def _late_reply(self, servo_id: int) -> bool:
        """Whether an unanswered request of `servo_id` may explain a reply no one waited for.

        It then has had its reply (a request is answered at most once). The reply another
        request took early is the same: that request's own reply comes unsolicited after it.
        """
        owed = self._owed[servo_id]
        now = time.monotonic()
        while owed:
            if owed.popleft() >= now:
                return True
        return False

    def _on_tx(self, data: bytes) -> None:
        # Every unicast instruction is answered (S13), broadcast ones never.
        if len(data) > 4:
            servo_id = data[2]
            if servo_id != proto.BROADCAST_ID:
                self.requests_by_id[servo_id] += 1
                self.sent_at[servo_id] = time.monotonic()
                self.sent_len[servo_id] = len(data)

    def unsolicited_replies(self, servo_id: int, nparams: int) -> int:
        """Return the replies of `servo_id` with `nparams` params that no request waited for."""
        return self._unsolicited.get((servo_id, nparams), 0)

    def surplus_replies(self, servo_id: int) -> int:
        """Return the replies of ``servo_id`` that no request explains; growing: a duplicate id.

        A reply that no request waited for is a late one when a request of that id went
        unanswered (within LATE_REPLY_S): each such request explains one reply. Beyond those,
        more than one servo answers to this id (S24): on a real bus their replies collide, and
        no reading of that id can be trusted. (Replies minus requests would not do: replies
        owed when it is looked at, and answered after, would make it grow with one servo.)
        """
        return self.surplus_by_id[servo_id]
