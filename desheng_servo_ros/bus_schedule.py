"""The servo bus as one state machine without I/O, thread, lock or clock (the model's subject).

:class:`BusSchedule` composes the parts of ``schedule.py`` (the read cycles, the online
judgement, the command queue and its budget, what goes first at a READ boundary, the set_id
rule, the shutdown sequence) into a whole bus, with one entry: :meth:`BusSchedule.step` takes
one event with its time and returns the actions to carry out (issue 22 item 1), one
transaction on the half-duplex bus at a time, so ``core_runner.run_core`` can drive it.

Events (``bus_events.py``): :class:`Command` (a ``~/command``), :class:`Call` (a service call,
answered once by an :class:`Answer` with its token), :class:`Shutdown`, :class:`Late` (a frame
the host wrote after its time, told by whoever carries out ``Send`` through a :class:`Line`),
and the shared ``core_events`` ``Reply`` (a reply decoded off the wire), ``LinkUp``/``LinkDown``
(the port) and ``Tick`` (time passed). Actions: :class:`Send` (a frame, when it goes and until
when it holds the bus), :class:`Answer`, :class:`ReadDone` and :class:`CycleDone` (what the
reads brought), ``Log``, and last a shared ``SetTimer`` (when the next ``Tick`` is due; a step
without one has no deadline). ``test/test_servo_model.py`` steps it against the device model
in virtual time and checks the bus's safety invariants after every step; the driver steps the
same schedule on its port (``bus_runtime.BusRuntime``).
"""

from __future__ import annotations

from collections import deque
import math
from typing import Any, Deque, Dict, Hashable, List, Optional, Sequence, Tuple

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.bus_events import (  # noqa: F401 - the types, re-exported
    Action, Answer, Call, Command, CycleDone, Event, Late, QUIET_CALLS, ReadDone, Send,
    Shutdown)
from desheng_servo_ros.bus_services import _Service, _Tx, WAIT
from desheng_servo_ros.schedule import (CommandQueue, EMPTY, exchange_wire, IDLE_GUARD_S,
                                        judge_failure, judge_link, judge_reply, next_on_bus,
                                        NOT_DUE, OFFLINE_AFTER_FAILURES, plan_telemetry, POSTED,
                                        ReadSchedule, reply_wire, REPROBE_PERIOD_S, RETRY,
                                        set_id_refusal, shutdown_frames, sync_write_frames,
                                        Target, TORQUE_OFF_ALL, YIELD)
from desheng_servo_ros.state import READ_STATE, READ_WIDE, ServoRecord
from desheng_servo_ros.units import Joint
from uav_serial_common.core_events import LinkDown, LinkUp, Log, Reply, SetTimer, Tick
from uav_serial_common.pty_port import wire_time


TIME_EPS = 1e-9
"""Times closer than this are one (a float sum of wire times must not split a moment)."""


class Line:
    """The half-duplex line as the host really writes to it, for whoever carries out ``Send``.

    The schedule plans when each frame goes; a loaded host writes a frame late, and then the
    line is busy that much longer. :meth:`start` says when a frame may really go (its time, or
    later while the frame before it without a reply is still on the line); :meth:`wrote` takes
    when it went and returns the :class:`Late` event to step when it went late, by however
    little (a reply that came before the request had really left is not its answer). The
    driver's runtime and the model test's wire both carry out ``Send`` through one.
    """

    def __init__(self) -> None:
        self.free_at = -math.inf
        """When the last frame without a reply has left the line (and its guard)."""

    def start(self, send: Send) -> float:
        """Return when `send` may go: its time, or when the line is really free."""
        return max(send.at, self.free_at)

    def wrote(self, send: Send, began: float, ended: float, now: float) -> Optional[Late]:
        """Take that the write of `send` began by `began` and ended by `ended`.

        Returns the event to step at `now` when it went late.
        """
        lag_max = ended - send.at
        if send.reply_id is None:
            self.free_at = max(self.free_at, send.deadline + lag_max)
        if lag_max <= 0.0:
            return None
        return Late(now, send, max(0.0, began - send.at), lag_max)


class BusSchedule:
    """The servo bus as a state machine: events with their time in, actions out.

    :meth:`step` takes each event (module doc) and returns the :class:`Send` and
    :class:`Answer` actions to carry out, in order, then the ``SetTimer`` of the next
    deadline. The methods it calls (:meth:`command`, :meth:`received`, :meth:`link`,
    :meth:`shutdown`, :meth:`poll` at :meth:`wake_at`) and :meth:`call` (which numbers the
    calls) are its parts, kept public for the cases that name one moment. One transaction on the
    bus at a time: nothing is sent while a reply is awaited or a frame is on the wire.
    """

    def __init__(self, joints: Sequence[Joint], *, now: float, baud: int = 115200,
                 publish_rate_hz: float = 1000.0, telemetry_period_s: float = 1.0,
                 max_retries: int = 1, margin_s: float = 0.002,
                 torque_off_on_shutdown: bool = True,
                 pace_now: Optional[float] = None) -> None:
        self.servos: Tuple[ServoRecord, ...] = tuple(ServoRecord(j, k)
                                                     for k, j in enumerate(joints))
        self.baud = baud
        self.rate_hz = publish_rate_hz
        self.telemetry_period_s = telemetry_period_s
        self.margin_s = margin_s
        self.torque_off_on_shutdown = torque_off_on_shutdown
        self.max_retries = max_retries
        pace = now if pace_now is None else pace_now  # the read loop's clock (step)
        self.reads = ReadSchedule(1.0 / publish_rate_hz, max_retries, pace)
        self.commands = CommandQueue()
        self.port_open = True
        self.closed = False
        self.urgent: Deque[Tuple[bytes, int]] = deque()
        self.services: Deque['_Service'] = deque()
        self.service: Optional['_Service'] = None
        self._tx: Optional[_Tx] = None  # awaiting its reply until _tx_deadline
        self._tx_deadline = math.inf
        self._tx_at = now  # when the request awaiting its reply went
        self._tx_sent = now  # when the request awaiting its reply had left the line
        self._retry: Optional[_Tx] = None  # a READ to send again at the next boundary
        self._free_at = now  # a frame without a reply holds the bus until then
        self._tokens = 0
        self.held: set = set()  # tokens of the holds granted and not released
        self._notes: List[Any] = []  # ReadDone, CycleDone and Log actions of this step
        self._pace_offset = pace - now  # the read loop's clock less the events' (step)
        self._pace_at = (now, pace)  # the last step's moment on both clocks
        self.cycles_done = 0
        self.read_cycles_done = 0  # cycles that had READs in them
        # What came off the wire: bytes, frames, and replies no request took, by (id, params)
        # (a request answered by bytes and no frame at all was answered garbled: S24).
        self.bytes_in = 0
        self.frames_in = 0
        self.unsolicited: Dict[Tuple[int, int], int] = {}
        # (id, length) of a service READ whose reply may still come (left unanswered, cut off,
        # or answered, for a second servo's) -> until when; schedule.own_read keeps the next
        # READs of that servo from its length.
        self.owed: Dict[Tuple[int, int], float] = {}
        self.last_taken = False  # whether the last reply received ended its transaction
        # Per id, a margin of its own when longer than margin_s (a servo that answers late:
        # the driver's link learns it); None: margin_s for all.
        self.slow_margin: Optional[Sequence[float]] = None
        # When a list: each attempt that got no reply, (id, garbled: bytes and no frame came
        # since its first attempt; None before the last attempt), for the driver's counters.
        self.silences: Optional[List[Tuple[int, Optional[bool]]]] = None

    # -- the one entry ---------------------------------------------------------------------------

    def step(self, event: Event, pace_now: Optional[float] = None) -> List[Action]:
        """Take one event; return the actions to carry out, in order (``SetTimer`` last).

        A ``SetTimer(at)`` ends every step that leaves something due (a reply's deadline, the
        next READ, a command batch the budget holds back, a frame still on the line): step a
        ``Tick`` by then. A step without one has nothing due until the next event.

        ``pace_now``: the read loop's clock, when it is not the events' (a test's clock that
        the test moves, as the driver's ``clock``): the cycles, re-probes and telemetry are
        paced on it, while replies' deadlines and the commands' budget run on the events'
        clock. Default ``event.now``. The times of the actions are on the events' clock (but
        ``ReadDone.started``).
        """
        now = event.now
        self._pace_offset = 0.0 if pace_now is None else pace_now - now
        # The step's own moment on the read loop's clock, exactly (now + offset may round
        # below it, and a cycle due at pace_now would wait for the clock to move again).
        self._pace_at = (now, now if pace_now is None else pace_now)
        if isinstance(event, Reply):
            out = self.received(now, event.message)
        elif isinstance(event, Tick):
            out = self.poll(now)
        elif isinstance(event, Command):
            out = self.command(now, event.targets)
        elif isinstance(event, Call):
            out = self._call(now, event.token, event.name, event.args)
        elif isinstance(event, Late):
            out = self.late(now, event.send, event.lag, event.lag_max)
        elif isinstance(event, (LinkUp, LinkDown)):
            out = self.link(now, isinstance(event, LinkUp))
        elif isinstance(event, Shutdown):
            out = self.shutdown(now)
        else:
            raise TypeError(f'not an event of the servo bus: {event!r}')
        # What the reads brought come after the step's frames: the next READ leaves first.
        out.extend(self._notes)
        self._notes.clear()
        due = self.wake_at()
        if due < math.inf:
            out.append(SetTimer(due))
        return out

    # -- events ---------------------------------------------------------------------------------

    def command(self, now: float, targets: Sequence[Target]) -> List[Any]:
        """Take a ``~/command``: queue its targets (the newest wins); nothing after shutdown."""
        if not self.closed:
            self.commands.add(targets)
        return self.poll(now)

    def call(self, now: float, name: str, *args: Any) -> Tuple[int, List[Any]]:
        """Take a service call; return its token (its :class:`Answer` carries it), the actions."""
        self._tokens += 1
        return self._tokens, self._call(now, self._tokens, name, args)

    def _call(self, now: float, token: Hashable, name: str,
              args: Sequence[Any]) -> List[Any]:
        if self.closed:
            return [Answer(token, False, 'shutting down; nothing sent')]
        if name == 'release':
            # Also of a hold not granted yet (its caller gave up waiting): it never will be.
            self.held.discard(args[0])
            out = [Answer(svc.token, False, 'released before the bus was held')
                   for svc in self.services if svc.token == args[0]]
            self.services = deque(svc for svc in self.services if svc.token != args[0])
            self.reads.reset(self._pace(now))  # the servo list may have changed
            return out + [Answer(token, True, 'released')] + self.poll(now)
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
                return [Answer(token, False, 'refused: ' + refusal)]
            self.services.append(_Service(self, token, name, args))
        return self.poll(now)

    def received_bytes(self, count: int) -> None:
        """Count bytes off the wire, before the frames they make go to :meth:`received`."""
        self.bytes_in += count

    def received(self, now: float, reply: proto.Reply) -> List[Any]:
        """Take a reply decoded off the wire; the one awaited completes its transaction."""
        self.frames_in += 1
        tx = self._tx
        self.last_taken = False
        # A reply whose bytes came before the request had left the line and they had had
        # their own wire time answers an earlier one (a late reply of the attempt before a
        # retry): it ends nothing. The request left by _tx_sent at the earliest (Late), so an
        # answer is never refused.
        if tx is not None and reply.servo_id == tx.reply_id and \
                len(reply.params) == tx.nparams and now < self._tx_deadline and \
                now >= self._tx_sent + self._reply_wire(tx) - TIME_EPS:
            self._held(tx, now)
            self._tx = None
            self._tx_deadline = math.inf
            self._free_at = max(self._free_at, now)
            self.last_taken = True
            self._done(now, tx, reply)
        else:
            kind = (reply.servo_id, len(reply.params))
            self.unsolicited[kind] = self.unsolicited.get(kind, 0) + 1
            self.owed.pop(kind, None)  # the late reply it was owed: it came
        return self.poll(now)

    def link(self, now: float, up: bool) -> List[Any]:
        """Take the port opening or closing; a transaction in flight is lost with it."""
        self.port_open = up
        judge_link(self.servos, up)
        self.reads.reset(self._pace(now))
        if self._tx is not None:
            self._held(self._tx, now)
        for tx in (self._tx, self._retry):
            if tx is not None:
                self._done(now, tx, None, cut=True)
        self._tx = self._retry = None
        self._tx_deadline = math.inf
        self._free_at = max(self._free_at, now)
        return self.poll(now)

    def late(self, now: float, send: Send, lag: float, lag_max: float) -> List[Any]:
        """Take a frame written late: what it holds is held that much longer (``Late``).

        A request's reply may come `lag_max` later (a deadline kept as planned would call a
        reply on its way a silence, and the next frame would meet it on the half-duplex line),
        and is its answer from `lag` after the planned moment its request had left; a frame
        without a reply may leave the line `lag_max` later. The lag of a frame not the READs'
        is no time the commands' budget earns from (as a stop's or a service's: ``pause``).
        """
        awaited = send.reply_id is not None and self._tx is not None and \
            self._tx_deadline == send.deadline
        if send.kind != 'read':
            # The bus is held that long for it; an awaited request's hold from the moment it
            # left is booked when it ends (``_held``), so here only the time before that.
            self.commands.pause(send.at, lag if awaited else lag_max)
            if send.kind == 'command':
                self.commands.late_batch(send.deadline + lag_max)
        if send.reply_id is None:
            self._free_at = max(self._free_at, send.deadline + lag_max)
        elif awaited:
            self._tx_at += lag
            self._tx_sent += lag
            self._tx_deadline += lag_max
        return self.poll(now)

    def shutdown(self, now: float) -> List[Any]:
        """Stop: pending commands and services dropped; torque off is the last frame."""
        actions: List[Any] = []
        if self.closed:
            return actions
        self.closed = True
        self.commands.drop()
        for svc in list(self.services) + ([self.service] if self.service else []):
            left = self._tx is not None and self._tx.owner is svc
            actions.append(Answer(svc.token, False, 'shutting down' + (
                '; its request had left' if left else '')))
        stops = [token for _, token in self.urgent]
        self.urgent.clear()
        self.services.clear()
        self.service = None
        self.held.clear()
        # The transaction on the wire ends first (its reply or its deadline).
        at = max(now, self._free_at, self._tx_deadline if self._tx is not None else now)
        self._tx = self._retry = None
        self._tx_deadline = math.inf
        sent = False
        for frame in shutdown_frames(self.torque_off_on_shutdown):
            if self.port_open:
                actions.append(self._send_noreply(at, frame, 'shutdown'))
                at = self._free_at
                sent = True
        # A stop still queued (a transaction was on the wire): the shutdown's torque off is it.
        actions.extend(Answer(token, sent, 'torque off broadcast as the shutdown\'s last frame'
                              if sent else 'shutting down; torque off NOT sent')
                       for token in stops)
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
            nxt = min(nxt, self._free_at if self.reads.in_cycle
                      else self.reads.next_cycle - self._pace_offset)
        return max(self._free_at, nxt)

    def awaiting(self, now: float) -> bool:
        """Whether a reply is awaited whose deadline passed by `now` (the next poll ends it)."""
        return self._tx is not None and now >= self._tx_deadline

    @property
    def reply_deadline(self) -> float:
        """Until when the reply awaited is waited for (inf: none awaited)."""
        return self._tx_deadline

    def poll(self, now: float) -> List[Any]:
        """Let time pass to `now`: a deadline that passed, then whatever is next on the bus."""
        actions: List[Any] = []
        if self._tx is not None and now >= self._tx_deadline:
            tx, self._tx = self._tx, None
            self._held(tx, self._tx_deadline)
            self._free_at = max(self._free_at, self._tx_deadline)
            self._tx_deadline = math.inf
            if self.silences is not None:
                self.silences.append((tx.reply_id, self._garbled(tx)
                                      if tx.attempts > tx.retries else None))
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
        pace = self._pace(now)
        return reads.due(pace) and any(
            s.failures < OFFLINE_AFTER_FAILURES or pace >= s.next_probe for s in self.servos)

    def _pace(self, now: float) -> float:
        """`now` (the events' clock) on the read loop's clock (``step``'s ``pace_now``)."""
        at, pace = self._pace_at
        return pace if now == at else now + self._pace_offset

    def _reading(self) -> bool:
        """Whether the read loop runs (a scan, an id change or a hold stops it)."""
        svc = self.service
        return not (self.held or (svc is not None and svc.quiet))

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
            started = reads.start_cycle(self._pace(now), self.servos)
            if started == NOT_DUE:
                return False
            if started == EMPTY:
                self.cycles_done += 1
                self._notes.append(CycleDone(now, False))
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
                self.reads.reset(self._pace(now))
        svc = self.service
        step = svc.next(now)
        if step is None:
            actions.append(svc.answer())
            self.service = None
            if svc.name == 'hold':
                self.held.add(svc.token)
            elif svc.quiet:
                self.reads.reset(self._pace(now))  # the servo list may have changed
        elif step is WAIT:
            return False  # off the bus until its ready_at (wake_at)
        elif isinstance(step, _Tx):
            self._start(now, step, actions)
        else:
            actions.append(self._send_noreply(now, step, svc.name))
        return True

    def owed_lengths(self, servo_id: int, now: float) -> List[int]:
        """Return the lengths of `servo_id`'s READs whose late replies may still come."""
        self.owed = {k: until for k, until in self.owed.items() if until > now}
        return [size for (i, size) in self.owed if i == servo_id]

    def reply_timeout(self, frame_len: int, nparams: int, reply_id: int) -> float:
        """Return an attempt's usual wait: wire time of request + reply, and the id's margin."""
        margin = self.margin_s
        if self.slow_margin is not None and self.slow_margin[reply_id] > margin:
            margin = self.slow_margin[reply_id]
        return exchange_wire(frame_len, nparams, self.baud) + margin

    def _start(self, at: float, tx: _Tx, actions: List[Any]) -> None:
        tx.attempts += 1
        if tx.attempts == 1:
            tx.mark = (self.bytes_in, self.frames_in)
        timeout = tx.wait if tx.wait is not None else \
            self.reply_timeout(len(tx.frame), tx.nparams, tx.reply_id)
        self._tx = tx
        self._tx_at = at
        self._tx_sent = at + wire_time(len(tx.frame), self.baud)
        self._tx_deadline = at + timeout
        actions.append(Send(at, tx.frame, 'read' if tx.owner == 'read' else tx.owner.name,
                            tx.reply_id, tx.nparams, at + timeout, tx.flush))

    def _send_noreply(self, at: float, frame: bytes, kind: str) -> Send:
        self._free_at = at + wire_time(len(frame), self.baud) + IDLE_GUARD_S
        if kind != 'command':
            self.commands.pause(at, self._free_at - at)
        return Send(at, frame, kind, None, 0, self._free_at)

    def _held(self, tx: _Tx, end: float) -> None:
        """End `tx` at `end`: one not the READs' held the bus from the commands too."""
        if tx.owner != 'read':
            self.commands.pause(self._tx_at, end - self._tx_at)

    def _reply_wire(self, tx: _Tx) -> float:
        """Return the wire time of `tx`'s reply."""
        return reply_wire(tx.nparams, self.baud)

    def _garbled(self, tx: _Tx) -> bool:
        """Whether bytes and no frame came since `tx` was first sent (S24: colliding replies)."""
        return self.bytes_in > tx.mark[0] and self.frames_in == tx.mark[1]

    def _done(self, now: float, tx: _Tx, reply: Optional[proto.Reply],
              cut: bool = False) -> None:
        """End `tx` with `reply` (None: none after its retries; `cut`: by the link)."""
        if tx.owner != 'read':
            tx.owner.result(now, reply, reply is None and self._garbled(tx), cut)
            return
        s, kind, started, last = tx.tag
        if reply is None:
            if judge_failure(s, self._pace(now)):
                self._notes.append(Log('warning', (
                    f'{s.name} (id {s.id}) stopped answering: offline, probing it every '
                    f'{REPROBE_PERIOD_S:g} s (check its power and cable; ~/scan lists the bus)')))
        elif kind == READ_STATE:
            s.failures = 0
            s.set_torque(reply.params[0] != 0)
        else:
            if kind == READ_WIDE:
                plan_telemetry(s, started, self.telemetry_period_s, len(self.servos))
            if judge_reply(s):
                self._notes.append(Log('info', f'{s.name} (id {s.id}) is back online'))
        self._notes.append(ReadDone(now, s.id, kind, started, reply))
        if last:
            self.cycles_done += 1
            self.read_cycles_done += 1
            self._notes.append(CycleDone(now, True))
