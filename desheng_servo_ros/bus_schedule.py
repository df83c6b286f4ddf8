"""The servo bus as one state machine without I/O, thread, lock or clock (the model's subject).

:class:`BusSchedule` composes the parts of ``schedule.py`` (the read cycles, the online
judgement, the command queue and its budget, what goes first at a READ boundary, the set_id
rule, the shutdown sequence) into a whole bus: events with their time in, actions out, one
transaction on the half-duplex bus at a time. ``test/test_servo_model.py`` drives it against the
device model in virtual time and checks the bus's safety invariants after every step; the
threaded driver calls the same parts on its threads.
"""

from __future__ import annotations

from collections import deque
import math
from typing import Any, Deque, Dict, List, NamedTuple, Optional, Sequence, Tuple

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.schedule import (CommandQueue, EMPTY, IDLE_GUARD_S, judge_failure,
                                        judge_link, judge_probe, judge_reply, next_on_bus,
                                        NOT_DUE, OFFLINE_AFTER_FAILURES,
                                        plan_telemetry, POSTED, PROBE_READS, probe_quiet_s,
                                        ReadSchedule, renamed, REPLY_OVERHEAD, RETRY,
                                        set_id_refusal, shutdown_frames, sync_write_frames,
                                        Target, TORQUE_OFF_ALL, YIELD)
from desheng_servo_ros.state import (ID, POSITION, READ_STATE, READ_WIDE, ServoRecord, TORQUE)
from desheng_servo_ros.units import Joint
from uav_serial_common.pty_port import wire_time


class Send(NamedTuple):
    """Put `frame` on the bus at `at`; the bus is taken until `deadline`.

    A reply of `reply_id` with `nparams` params is awaited until `deadline`; `reply_id` None:
    no reply, the bus is free again at `deadline` (the frame's wire time and a guard).
    """

    at: float
    frame: bytes
    kind: str
    reply_id: Optional[int]
    nparams: int
    deadline: float


class Answer(NamedTuple):
    """A service call's answer."""

    token: int
    ok: bool
    text: str


class _Tx:
    """One transaction of a service or of the read loop that waits for a reply."""

    __slots__ = ('frame', 'reply_id', 'nparams', 'retries', 'owner', 'tag', 'attempts', 'mark')

    def __init__(self, frame: bytes, reply_id: int, nparams: int, retries: int, owner: Any,
                 tag: Any = None) -> None:
        self.frame = frame
        self.reply_id = reply_id
        self.nparams = nparams
        self.retries = retries
        self.owner = owner
        self.tag = tag
        self.attempts = 0
        self.mark = (0, 0)  # (bytes, frames) received when it was first sent


class BusSchedule:
    """The servo bus as a state machine: events with their time in, actions out.

    Events: :meth:`command` (a ``~/command``), :meth:`call` (a service: ``emergency_stop``,
    ``write_positions``, ``read_register``, ``set_torque``, ``scan``, ``set_id``),
    :meth:`received` (a reply decoded off the wire), :meth:`link` (port up/down),
    :meth:`shutdown`; :meth:`poll` at :meth:`wake_at` (or any time) lets time pass. Each returns
    the :class:`Send` and :class:`Answer` actions to carry out, in order. One transaction on the
    bus at a time: nothing is sent while a reply is awaited or a frame is on the wire.
    """

    def __init__(self, joints: Sequence[Joint], *, now: float, baud: int = 115200,
                 publish_rate_hz: float = 1000.0, telemetry_period_s: float = 1.0,
                 max_retries: int = 1, margin_s: float = 0.002,
                 torque_off_on_shutdown: bool = True) -> None:
        self.servos: Tuple[ServoRecord, ...] = tuple(ServoRecord(j, k)
                                                     for k, j in enumerate(joints))
        self.baud = baud
        self.rate_hz = publish_rate_hz
        self.telemetry_period_s = telemetry_period_s
        self.margin_s = margin_s
        self.torque_off_on_shutdown = torque_off_on_shutdown
        self.max_retries = max_retries
        self.reads = ReadSchedule(1.0 / publish_rate_hz, max_retries, now)
        self.commands = CommandQueue()
        self.port_open = True
        self.closed = False
        self.urgent: Deque[Tuple[bytes, int]] = deque()
        self.services: Deque['_Service'] = deque()
        self.service: Optional['_Service'] = None
        self._tx: Optional[_Tx] = None  # awaiting its reply until _tx_deadline
        self._tx_deadline = math.inf
        self._tx_sent = now  # when the request awaiting its reply had left the line
        self._retry: Optional[_Tx] = None  # a READ to send again at the next boundary
        self._free_at = now  # a frame without a reply holds the bus until then
        self._tokens = 0
        self.cycles_done = 0
        self.read_cycles_done = 0  # cycles that had READs in them
        # What came off the wire: bytes, frames, and replies no request took, by (id, params)
        # (a request answered by bytes and no frame at all was answered garbled: S24).
        self.bytes_in = 0
        self.frames_in = 0
        self.unsolicited: Dict[Tuple[int, int], int] = {}

    # -- events ---------------------------------------------------------------------------------

    def command(self, now: float, targets: Sequence[Target]) -> List[Any]:
        """Take a ``~/command``: queue its targets (the newest wins); nothing after shutdown."""
        if not self.closed:
            self.commands.add(targets)
        return self.poll(now)

    def call(self, now: float, name: str, *args: Any) -> Tuple[int, List[Any]]:
        """Take a service call; return its token (its :class:`Answer` carries it), the actions."""
        self._tokens += 1
        token = self._tokens
        if self.closed:
            return token, [Answer(token, False, 'shutting down; nothing sent')]
        if name == 'emergency_stop':
            # Ahead of everything queued; queued commands must not follow it.
            self.commands.drop()
            self.urgent.append((TORQUE_OFF_ALL, token))
        else:
            if name == 'write_positions':
                # A queued ~/command for these servos is older than this call.
                self.commands.drop([t[0] for t in args[0]])
            refusal = set_id_refusal(self.servos, *args) if name == 'set_id' else None
            if refusal is not None:
                return token, [Answer(token, False, 'refused: ' + refusal)]
            self.services.append(_Service(self, token, name, args))
        return token, self.poll(now)

    def received_bytes(self, count: int) -> None:
        """Count bytes off the wire, before the frames they make go to :meth:`received`."""
        self.bytes_in += count

    def received(self, now: float, reply: proto.Reply) -> List[Any]:
        """Take a reply decoded off the wire; the one awaited completes its transaction."""
        self.frames_in += 1
        tx = self._tx
        # A reply that came before the request had left the line answers an earlier one (a
        # late reply of the attempt before a retry): it ends nothing.
        if tx is not None and self._tx_sent < now < self._tx_deadline and \
                reply.servo_id == tx.reply_id and len(reply.params) == tx.nparams:
            self._tx = None
            self._tx_deadline = math.inf
            self._free_at = max(self._free_at, now)
            self._done(now, tx, reply)
        else:
            kind = (reply.servo_id, len(reply.params))
            self.unsolicited[kind] = self.unsolicited.get(kind, 0) + 1
        return self.poll(now)

    def link(self, now: float, up: bool) -> List[Any]:
        """Take the port opening or closing; a transaction in flight is lost with it."""
        self.port_open = up
        judge_link(self.servos, up)
        self.reads.reset(now)
        for tx in (self._tx, self._retry):
            if tx is not None:
                self._done(now, tx, None)
        self._tx = self._retry = None
        self._tx_deadline = math.inf
        self._free_at = max(self._free_at, now)
        return self.poll(now)

    def shutdown(self, now: float) -> List[Any]:
        """Stop: pending commands and services dropped; torque off is the last frame."""
        actions: List[Any] = []
        if self.closed:
            return actions
        self.closed = True
        self.commands.drop()
        for svc in list(self.services) + ([self.service] if self.service else []):
            actions.append(Answer(svc.token, False, 'shutting down'))
        self.services.clear()
        self.service = None
        # The transaction on the wire ends first (its reply or its deadline).
        at = max(now, self._free_at, self._tx_deadline if self._tx is not None else now)
        self._tx = self._retry = None
        self._tx_deadline = math.inf
        for frame in shutdown_frames(self.torque_off_on_shutdown):
            if self.port_open:
                actions.append(self._send_noreply(at, frame, 'shutdown'))
                at = self._free_at
        return actions

    # -- time -----------------------------------------------------------------------------------

    def wake_at(self) -> float:
        """Return when :meth:`poll` has something to do (a deadline, a cycle, a batch)."""
        if self.closed or not self.port_open:
            return math.inf
        if self._tx is not None:
            return self._tx_deadline
        svc = self.service
        if svc is not None and svc.ready_at > self._free_at and not self.urgent and \
                svc.retry is None and self._retry is None:
            # The service waits (set_id's probe, for a second reply); commands may go.
            nxt = svc.ready_at
            if self.commands.pending:
                nxt = min(nxt, self.commands.free_at())
            return max(self._free_at, nxt)
        if self.urgent or self.services or svc is not None or self._retry:
            return self._free_at
        nxt = math.inf
        if self.commands.pending:
            nxt = self.commands.free_at()
        if self._reading():
            nxt = min(nxt, self._free_at if self.reads.in_cycle else self.reads.next_cycle)
        return max(self._free_at, nxt)

    def poll(self, now: float) -> List[Any]:
        """Let time pass to `now`: a deadline that passed, then whatever is next on the bus."""
        actions: List[Any] = []
        if self._tx is not None and now >= self._tx_deadline:
            tx, self._tx = self._tx, None
            self._free_at = max(self._free_at, self._tx_deadline)
            self._tx_deadline = math.inf
            if tx.attempts > tx.retries:
                self._done(now, tx, None)
            elif tx.owner == 'read':
                self._retry = tx  # decided at the boundary, like the next READ (next_on_bus)
            else:
                tx.owner.retry = tx  # after an emergency stop that waits (_serve)
        while not self.closed and self.port_open and self._tx is None and now >= self._free_at:
            if not self._next(now, actions):
                break
        return actions

    # -- decisions ------------------------------------------------------------------------------

    def read_wanted(self, now: float) -> bool:
        """Whether a READ would take the bus at `now` if no command were pending.

        The read loop has a READ to send and no caller of higher priority (an emergency stop, a
        service) waits: a command batch that goes then takes the bus from a READ; one that goes
        ahead of a service takes it from the service (next_on_bus).
        """
        reads = self.reads
        if not (self._reading() and self.port_open) or self.closed:
            return False
        if self.urgent or self.services or self.service is not None:
            return False
        if reads.in_cycle or self._retry is not None:
            return True
        return reads.due(now) and any(
            s.failures < OFFLINE_AFTER_FAILURES or now >= s.next_probe for s in self.servos)

    def _reading(self) -> bool:
        """Whether the read loop runs (a scan or an id change holds it)."""
        svc = self.service
        return not (svc is not None and svc.quiet)

    def _next(self, now: float, actions: List[Any]) -> bool:
        """Put the next thing on the bus at `now`; False when nothing is due."""
        svc = self.service
        if self.urgent or (svc is not None and svc.retry is not None):
            # An emergency stop goes first (it dropped the queued commands), and a service's
            # retry follows its attempt; a READ to retry then has failed.
            retry, self._retry = self._retry, None
            if retry is not None:
                self._done(now, retry, None)
            return self._serve(now, actions)
        higher = bool(self.services or svc is not None)
        step = next_on_bus(higher, self.commands.due(now), self._retry is not None)
        retry, self._retry = self._retry, None
        if step == YIELD:
            if retry is not None:
                self._done(now, retry, None)  # a retry that cannot go out has failed
            return self._serve(now, actions)
        if step == POSTED:
            self._retry = retry  # follows the command
            batch = self.commands.take()
            frames = sync_write_frames(batch)
            at = now
            for frame in frames:
                actions.append(self._send_noreply(at, frame, 'command'))
                at = self._free_at
            self.commands.frames_sent += len(frames)
            self.commands.charge(at - IDLE_GUARD_S, sum(map(len, frames)), self.baud,
                                 self.rate_hz)
            return True
        if step == RETRY:
            self._start(now, retry, actions)
            return True
        if not self._reading():
            return False
        reads = self.reads
        if not reads.in_cycle:
            started = reads.start_cycle(now, self.servos)
            if started == NOT_DUE:
                return False
            if started == EMPTY:
                self.cycles_done += 1
                return False
        frame, servo_id, nparams, retries, tag = reads.take()
        self._start(now, _Tx(frame, servo_id, nparams, retries, 'read', tag), actions)
        return True

    def _serve(self, now: float, actions: List[Any]) -> bool:
        """Serve an emergency stop first, then the service in progress or the next one."""
        if self.urgent:
            frame, token = self.urgent.popleft()
            actions.append(self._send_noreply(now, frame, 'emergency_stop'))
            for s in self.servos:
                s.set_torque(False)
            actions.append(Answer(token, True, 'torque off broadcast to every servo'))
            return True
        svc = self.service
        if svc is not None and svc.retry is not None:
            self._start(now, svc.retry, actions)
            svc.retry = None
            return True
        if svc is not None and svc.ready_at > now:
            return False  # it waits (wake_at); a command may go meanwhile
        if self.service is None:
            self.service = self.services.popleft()
            if self.service.quiet:
                self.reads.reset(now)
        svc = self.service
        step = svc.next()
        if step is None:
            actions.append(svc.answer())
            self.service = None
            if svc.quiet:
                self.reads.reset(now)  # the servo list may have changed
        elif isinstance(step, _Tx):
            self._start(now, step, actions)
        else:
            actions.append(self._send_noreply(now, step, svc.name))
        return True

    def _start(self, at: float, tx: _Tx, actions: List[Any]) -> None:
        tx.attempts += 1
        if tx.attempts == 1:
            tx.mark = (self.bytes_in, self.frames_in)
        timeout = wire_time(len(tx.frame) + tx.nparams + REPLY_OVERHEAD, self.baud) + \
            self.margin_s
        self._tx = tx
        self._tx_sent = at + wire_time(len(tx.frame), self.baud)
        self._tx_deadline = at + timeout
        actions.append(Send(at, tx.frame, 'read' if tx.owner == 'read' else tx.owner.name,
                            tx.reply_id, tx.nparams, at + timeout))

    def _send_noreply(self, at: float, frame: bytes, kind: str) -> Send:
        self._free_at = at + wire_time(len(frame), self.baud) + IDLE_GUARD_S
        return Send(at, frame, kind, None, 0, self._free_at)

    def _done(self, now: float, tx: _Tx, reply: Optional[proto.Reply]) -> None:
        if tx.owner != 'read':
            garbled = reply is None and self.bytes_in > tx.mark[0] and \
                self.frames_in == tx.mark[1]
            tx.owner.result(now, reply, garbled)
            return
        s, kind, started, last = tx.tag
        if reply is None:
            judge_failure(s, now)
        elif kind == READ_STATE:
            s.failures = 0
            s.set_torque(reply.params[0] != 0)
        else:
            if kind == READ_WIDE:
                plan_telemetry(s, started, self.telemetry_period_s, len(self.servos))
            judge_reply(s)
        if last:
            self.cycles_done += 1
            self.read_cycles_done += 1


class _Service:
    """A service call as a sequence of transactions (the model's version of the core's)."""

    def __init__(self, bus: BusSchedule, token: int, name: str, args: Tuple[Any, ...]) -> None:
        self.bus = bus
        self.token = token
        self.name = name
        self.args = args
        # A scan and an id change hold the read loop: they need a quiet bus.
        self.quiet = name in ('scan', 'set_id')
        self.ok = True
        self.text = ''
        self.retry: Optional[_Tx] = None  # its transaction to send again
        self._steps = self._run()
        self._reply: Optional[proto.Reply] = None
        self._garbled = False
        self._at = 0.0
        self.ready_at = 0.0  # its next step waits until then

    def next(self) -> Any:
        """Return the next step: a transaction, a frame without a reply, or None (done)."""
        try:
            return next(self._steps)
        except StopIteration:
            return None

    def result(self, now: float, reply: Optional[proto.Reply], garbled: bool = False) -> None:
        """Take the reply of the step's transaction (None: none after its retries).

        `garbled`: bytes and no frame came while it was awaited.
        """
        self._reply = reply
        self._garbled = garbled
        self._at = now

    def answer(self) -> Answer:
        """Return the call's answer."""
        return Answer(self.token, self.ok, self.text)

    def _tx(self, frame: bytes, servo_id: int, nparams: int, retries: int) -> _Tx:
        return _Tx(frame, servo_id, nparams, retries, self)

    def _run(self) -> Any:
        name, args, bus = self.name, self.args, self.bus
        if name == 'write_positions':
            for frame in sync_write_frames(args[0]):
                yield frame
            self.text = 'SYNC WRITE sent'
        elif name == 'read_register':
            servo_id, address, length = args
            yield self._tx(proto.encode_read(servo_id, address, length), servo_id, length,
                           bus.max_retries)
            self.ok = self._reply is not None
            self.text = 'read' if self.ok else 'no reply'
        elif name == 'set_torque':
            ids, enable = args
            for servo_id in ids:
                yield self._tx(proto.encode_write(servo_id, TORQUE.address,
                                                  b'\x01' if enable else b'\x00'),
                               servo_id, 0, bus.max_retries)
                yield self._tx(proto.encode_read(servo_id, TORQUE.address, 1), servo_id, 1,
                               bus.max_retries)
                back = self._reply is not None and self._reply.params[0] != 0
                for s in bus.servos:
                    if s.id == servo_id and self._reply is not None:
                        s.set_torque(back)
                if back != enable:
                    self.ok = False
            self.text = 'torque'
        elif name == 'scan':
            first, last = args
            found = []
            for servo_id in range(first, last + 1):
                yield self._tx(proto.encode_ping(servo_id), servo_id, 0, 0)
                if self._reply is not None:
                    found.append(servo_id)
            self.text = f'found {found}'
        elif name == 'set_id':
            yield from self._set_id(*args)

    def _answers(self, servo_id: int) -> Any:
        """PING up to twice: 'yes', 'garbled' (something answers, not cleanly) or 'no'."""
        garbled = False
        for _ in range(2):
            yield self._tx(proto.encode_ping(servo_id), servo_id, 0, 0)
            if self._reply is not None:
                return 'yes'
            garbled = garbled or self._garbled
        return 'garbled' if garbled else 'no'

    def _how_many_answer(self, servo_id: int) -> Any:
        """Probe as the live driver does (ServoServices._how_many_answer), with judge_probe."""
        bus = self.bus
        kind = (servo_id, POSITION.size)
        unsolicited = bus.unsolicited.get(kind, 0)
        values, garbled = [], 0
        for _ in range(PROBE_READS):
            yield self._tx(proto.encode_read(servo_id, POSITION.address, POSITION.size),
                           servo_id, POSITION.size, 0)
            if self._reply is not None:
                values.append(int.from_bytes(self._reply.params, 'big'))
                # As the driver: a second servo's whole reply ends before the next READ (it
                # sleeps off the bus lock: commands may go meanwhile, the read loop is paused).
                self.ready_at = self._at + probe_quiet_s(bus.baud)
            elif self._garbled:
                garbled += 1
        return judge_probe(values, garbled, bus.unsolicited.get(kind, 0) - unsolicited)

    def _set_id(self, old: int, new: int) -> Any:
        bus = self.bus
        taken = yield from self._answers(new)
        if taken != 'no':
            self.ok, self.text = False, f'id {new} already answers ({taken})'
            return
        count, why = yield from self._how_many_answer(old)
        if count != 'one':
            self.ok, self.text = False, (f'servo {old} does not answer' if count == 'none'
                                         else f'more than one servo answers at id {old} ({why})')
            return
        # A refusal checked again where the list could have changed meanwhile.
        refusal = set_id_refusal(bus.servos, old, new)
        if refusal is not None:
            self.ok, self.text = False, refusal
            return
        yield self._tx(proto.encode_write(old, ID.address, bytes([new])), old, 0,
                       bus.max_retries)
        now_at_new = yield from self._answers(new)
        if now_at_new != 'yes':
            self.ok, self.text = False, f'UNKNOWN whether servo {old} now has id {new}'
            return
        # Done only if it is alone there (a servo at the new id whose PINGs were lost).
        after, why = yield from self._how_many_answer(new)
        bus.servos = renamed(bus.servos, old, new)
        if after != 'one':
            self.ok, self.text = False, f'servo {old} took id {new}, not alone there? ({why})'
            return
        self.text = f'servo {old} now answers at id {new}'
