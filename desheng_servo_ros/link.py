"""The servo bus behind one serial port: its counters, margins and blocking requests.

No ROS here. :class:`ServoBusLink` owns the port (the shared SerialLink) and what is counted on
it, and gives the services their blocking requests; every decision of the bus (one
transaction at a time, the READs, the commands, an emergency stop first, retries and deadlines)
is the schedule's (``bus_schedule.BusSchedule``), which ``bus_runtime.BusRuntime`` steps on this
port: a request here is a ``transact``/``send`` call of the runtime, waited on with a timeout.

The reply margin is derived from the port on every (re)open (`uav_serial_common.usb_latency`: a
USB adapter's latency timer is lowered where allowed; a pty or a 1 ms adapter gets a few ms), and
per servo from replies that came late (a servo that answers slowly gets a longer wait, forgotten
again after a run of timely replies); the schedule reads both. A scan PINGs with the short
margin and collects late replies by id while it goes on, then confirms those ids with a long
wait (`bus_scan.sweep`; docs/protocols.md, "Scan").
"""

from __future__ import annotations

from collections import deque
import time
from typing import Any, Callable, Deque, Dict, Iterable, List, Optional, Sequence, Tuple

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.bus_scan import sweep
from desheng_servo_ros.protocol import Reply, StreamDecoder
from desheng_servo_ros.schedule import exchange_wire, REPLY_OVERHEAD, sync_write_frames
from uav_serial_common.pty_port import wire_time
from uav_serial_common.serial_link import LinkDown, LinkError, LinkTimeout, SerialLink
from uav_serial_common.usb_latency import BASE_MARGIN_S, inspect_latency_timer, LatencyReport

__all__ = ['BusBusy', 'LinkDown', 'LinkError', 'LinkTimeout', 'DERIVED_MARGIN_S',
           'ServoBusLink', 'REPLY_OVERHEAD', 'sync_write_frames']


class BusBusy(LinkError):
    """The bus did not take the request in time (held, or its answer never came)."""


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
# How long a caller waits for the bus to carry its request beyond its own wire time (the bus may
# be held by a service meanwhile).
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
    """The servo bus behind one serial port (module doc).

    Requests raise ``LinkTimeout`` (no valid reply after every retry), ``LinkDown`` (port not
    open) or ``BusBusy`` (not carried in time). ``runtime`` (a ``BusRuntime``) carries them; it
    sets ``on_reply``/``on_bytes`` to step its schedule from the reader thread.
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
        self.on_reply: Optional[Callable[[Reply], None]] = None
        self.on_bytes: Optional[Callable[[bytes], None]] = None
        self.on_link: Optional[Callable[[bool, str], None]] = None  # the runtime's
        self._on_connection = on_connection  # the owner's, after the runtime's
        self.runtime: Any = None  # the BusRuntime that carries the requests
        self.link = SerialLink(port, baud, self.decoder, on_frame=self._on_frame,
                               on_connection=self._connection, on_tx=self._on_tx,
                               on_rx=self._on_rx, logger=logger,
                               backoff_max_s=backoff_max_s, on_open=self._on_port_open)

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
            wire = self._wire[key] = exchange_wire(request_len, reply_params, self.baud)
        return wire + self.margin_for(servo_id)

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

    def learn_from(self, servo_id: int, reply: Reply) -> None:
        """Give `servo_id` a margin of its own if `reply` came later than the bus's margin."""
        needed = self._reply_margin(servo_id, len(reply.raw))
        if needed > self._margin:
            self._learn(servo_id, needed)

    # -- what the runtime tells (its stepping thread, under its lock) ---------------------------

    def note_reply(self, frame: Reply, taken: bool) -> None:
        """Count a reply: `taken` when it ended the transaction awaiting it."""
        servo_id = frame.servo_id
        self.replies_by_id[servo_id] += 1
        if taken:
            self.garble_level[servo_id] *= 1.0 - GARBLE_WEIGHT
            if self.slow_margin[servo_id]:
                self._slow_servo_replied(servo_id, len(frame.raw))
            return
        # Late replies (after a timeout) and duplicate-id replies (S24) end up here. A reply
        # later than its servo's margin is a slow servo (or a stalled host): it gets a margin
        # of its own. A duplicate's second reply follows the first at once, within the margin.
        self.unexpected_frames += 1
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

    def note_silence(self, servo_id: int, garbled: Optional[bool]) -> None:
        """Note an attempt of `servo_id` that got no reply (it may still be answered late).

        `garbled`: its last attempt, answered by bytes and no frame (None: not the last).
        """
        self._owed[servo_id].append(time.monotonic() + LATE_REPLY_S)
        stats = self.link.stats
        if garbled is None:
            stats.retries += 1
            return
        stats.timeouts += 1
        self.failed_transactions += 1
        if garbled:
            self.garbled_by_id[servo_id] += 1
            level = self.garble_level[servo_id]
            self.garble_level[servo_id] = level + GARBLE_WEIGHT * (1.0 - level)

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

    def _on_frame(self, frame: Reply) -> None:
        if self.on_reply is not None:
            self.on_reply(frame)
        else:
            self.note_reply(frame, False)

    def _connection(self, up: bool, reason: str) -> None:
        for handler in (self.on_link, self._on_connection):
            if handler is not None:
                handler(up, reason)

    def _on_rx(self, data: bytes) -> None:
        if self.on_bytes is not None:
            self.on_bytes(data)

    def _on_tx(self, data: bytes) -> None:
        # Every unicast instruction is answered (S13), broadcast ones never.
        self.transactions += 1
        if len(data) > 4:
            servo_id = data[2]
            if servo_id != proto.BROADCAST_ID:
                self.requests_by_id[servo_id] += 1
                self.sent_at[servo_id] = time.monotonic()
                self.sent_len[servo_id] = len(data)

    # -- requests (a caller's thread; carried by the runtime) -----------------------------------

    def _runtime(self) -> Any:
        runtime = self.runtime
        if runtime is None or runtime.closed:
            raise LinkDown(f'{self.port}: the driver is shutting down')
        if not self.port_open:
            raise LinkDown(f'{self.port} is not open ({self.link.last_error or "not connected"})')
        return runtime

    def transact(self, frame: bytes, servo_id: int, reply_params: int,
                 retries: Optional[int] = None,
                 timeout: Optional[float] = None, flush: bool = True) -> Reply:
        """Send one request and return the reply of ``servo_id`` with ``reply_params`` params.

        Sent again up to `retries` times when no reply comes (an emergency stop goes between
        two attempts: the schedule's rule); `timeout`: the wait of an attempt (default: wire
        time + margin). `flush` False keeps what arrived before the request (a scan collects
        late replies). What goes first on the bus (an emergency stop, a service before the
        read loop) is the schedule's to decide.
        """
        runtime = self._runtime()
        if retries is None:
            retries = self.max_retries
        attempts = retries + 1
        wait = timeout if timeout is not None else self.timeout_for(len(frame), reply_params,
                                                                    servo_id)
        answer = runtime.call('transact', frame, servo_id, reply_params, retries, timeout,
                              flush, timeout=BUS_LOCK_TIMEOUT_S + attempts * wait)
        return self._reply_of(answer, servo_id, runtime)

    def _reply_of(self, answer: Any, servo_id: int, runtime: Any) -> Reply:
        """Return the reply of a request's `answer`, or raise what became of it."""
        if answer is None:
            error: LinkError = BusBusy(f'the bus on {self.port} did not carry the request in '
                                       f'{BUS_LOCK_TIMEOUT_S:.0f} s')
            error.sent = True  # it may have left meanwhile
            raise error
        if answer.reply is not None:
            return answer.reply
        error = (LinkTimeout(f'no reply from servo {servo_id}') if answer.ok is False and
                 self.port_open and not runtime.closed else
                 LinkDown(f'{self.port}: the link went down during the request'))
        # A call the shutdown dropped before its request left sent nothing.
        error.sent = not answer.text.startswith('shutting down') or 'had left' in answer.text
        raise error

    def call(self, name: str, *args: Any, busy_s: float = 0.0) -> Any:
        """Step a call of the schedule and return its answer, done (ok) or raised.

        ``LinkDown`` when the port is not open (nothing sent) or the answer says it did not
        happen; ``BusBusy`` when no answer came in time: BUS_LOCK_TIMEOUT_S, and `busy_s` more
        for the call's own transactions.
        """
        timeout = BUS_LOCK_TIMEOUT_S + busy_s
        answer = self._runtime().call(name, *args, timeout=timeout)
        if answer is None:
            error: LinkError = BusBusy(f'the bus on {self.port} did not take {name} in '
                                       f'{timeout:.1f} s')
            error.sent = True  # it may have left meanwhile
            raise error
        if not answer.ok:
            error = LinkDown(f'{self.port}: {answer.text}')
            error.sent = 'had left' in answer.text
            raise error
        return answer

    def send(self, frame: bytes) -> None:
        """Send a frame that gets no reply; returns once the schedule put it on the wire."""
        self.send_all([frame])

    def send_all(self, frames: Sequence[bytes]) -> None:
        """Send frames without a reply, back to back."""
        self.call('send', list(frames))

    # -- instructions ---------------------------------------------------------------------------

    def ping(self, servo_id: int, retries: Optional[int] = None,
             timeout: Optional[float] = None) -> Reply:
        """PING one servo; returns its status reply."""
        return self.transact(proto.encode_ping(servo_id), servo_id, 0, retries, timeout)

    def read(self, servo_id: int, address: int, length: int,
             retries: Optional[int] = None) -> Reply:
        """READ ``length`` bytes at ``address``.

        The schedule sends it at a length of its own (``schedule.own_read``: a reply names no
        address, so a READ of the length of another READ of that servo could take its late
        reply) and answers with the bytes asked for.
        """
        frame = proto.encode_read(servo_id, address, length)  # (refuses a bad one here)
        runtime = self._runtime()
        if retries is None:
            retries = self.max_retries
        wait = self.timeout_for(len(frame), length + 2, servo_id)  # (+2: own_read's usual most)
        answer = runtime.call('read_register', servo_id, address, length, retries,
                              timeout=BUS_LOCK_TIMEOUT_S + (retries + 1) * wait)
        return self._reply_of(answer, servo_id, runtime)

    def write(self, servo_id: int, address: int, data: bytes = b'') -> Optional[Reply]:
        """WRITE; unicast waits for the acknowledgement, broadcast (254) only for the wire."""
        frame = proto.encode_write(servo_id, address, data)
        if servo_id == proto.BROADCAST_ID:
            self.send(frame)
            return None
        return self.transact(frame, servo_id, 0)

    def torque(self, ids: Sequence[int], enable: bool) -> List[Tuple[int, Optional[Reply]]]:
        """Switch torque of `ids`, each WRITE read back; return (id, reply) of each READ.

        The reply is None when the servo did not answer the READ (``BusSchedule``'s
        ``set_torque``: the model searches this very call).
        """
        attempts = self.max_retries + 1
        frame = len(proto.encode_write(1, 0, b'\x00'))  # = a READ's, 8 bytes
        busy = sum(attempts * (self.timeout_for(frame, 0, i) + self.timeout_for(frame, 3, i))
                   for i in ids)
        return self.call('set_torque', tuple(ids), enable, busy_s=busy).result

    def reg_write(self, servo_id: int, address: int, data: bytes) -> Reply:
        """REG WRITE (staged until ACTION); the servo acknowledges it (S13)."""
        return self.transact(proto.encode_reg_write(servo_id, address, data), servo_id, 0)

    def action(self) -> None:
        """Broadcast ACTION: staged writes execute now."""
        self.send(proto.encode_action())

    def reset(self, servo_id: int) -> Reply:
        """RESET one servo to factory settings."""
        return self.transact(proto.encode_reset(servo_id), servo_id, 0)

    def sync_write_positions(self, targets: Sequence[Tuple[int, int, int]]) -> list:
        """SYNC WRITE (id, ticks, ms) in as few frames as fit, at the next READ boundary."""
        frames = sync_write_frames(targets)
        self.send_all(frames)
        return frames

    def scan(self, ids: Iterable[int]) -> List[int]:
        """PING each id once; return the ids that answered (cleanly, late or garbled), in order.

        The PINGs use the normal margin, so an absent id costs a few ms; late replies are
        collected by id while the sweep goes on, garbled ones make suspects, and both are
        confirmed with a long wait (`bus_scan.sweep`; docs/protocols.md, "Scan").
        """
        return sweep(self, ids)

    # -- counters -------------------------------------------------------------------------------

    @property
    def checksum_errors(self) -> int:
        """Candidate reply frames rejected by their checksum."""
        return self.decoder.checksum_errors

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
