"""What goes on the servo bus next, decided without I/O, thread, lock or clock.

Every rule of the bus's scheduling lives here, once, as plain state and functions that take the
time as an argument. The threaded driver (``core.py`` with ``link.py``) calls these parts on its
threads; :class:`BusSchedule` composes the same parts into a whole bus as a state machine
(events with their time in, actions out) that ``test/test_servo_model.py`` drives against the
device model in virtual time. The parts:

- :func:`plan_cycle` and :class:`ReadSchedule`: the read loop's cycles (one READ per active
  servo, telemetry spread over its period, offline servos probed once per REPROBE_PERIOD_S),
  the cycles' pace (a cycle a period late starts afresh) and the retries of a READ;
- :func:`judge_failure`, :func:`judge_reply`, :func:`judge_link`: the online/offline judgement;
- :class:`CommandQueue`: coalesced commands (the newest target of each servo wins) and their
  bus budget (commands take at most 1 / (1 + COMMAND_SPACING) of the bus over any stretch);
- :func:`next_on_bus`: between two READs of the chain, what goes first (a caller of higher
  priority, i.e. an emergency stop or a service, then a pending command, then the READ to be
  retried, then the next READ);
- :func:`set_id_refusal` and :func:`renamed`: ``~/set_id`` never gives two joints one id;
- :func:`judge_probe`: ``~/set_id``'s probe of the bus, that never renames two servos at once;
- :func:`shutdown_frames`: the shutdown sequence, whose last frame is torque off.
"""

from __future__ import annotations

import math
from typing import Dict, List, Optional, Sequence, Tuple

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.state import (LOOP_READS, POSITION, READ_POSITION, READ_STATE,
                                     READ_WIDE, ServoRecord, TORQUE)
from desheng_servo_ros.units import Joint
from uav_serial_common.pty_port import wire_time
from uav_serial_common.text import few

# A servo is offline after this many READs in a row failed (each with its retries), and then
# probed this often (one READ, no retries), so a missing servo costs little bus time.
OFFLINE_AFTER_FAILURES = 3
REPROBE_PERIOD_S = 1.0
# Commands coming faster than the bus should take them are coalesced. Each batch of command
# frames owes the read loop COMMAND_SPACING times its wire time, so over any stretch commands
# take at most 1 / (1 + COMMAND_SPACING) of the bus; a batch that finds that budget unspent goes
# at once, up to COMMAND_BURST batches ahead of it (a token bucket kept as a time, GCRA), so a
# command at a normal rate waits only for the READ on the wire. Budget and spacing count from
# the line: a loaded host that writes a batch late moves them with it, and the batch after it
# goes at most one batch ahead (late_batch). Batches are also at least COMMAND_CYCLE_SHARE of
# a read cycle apart (at most two per cycle).
COMMAND_SPACING = 2.0
COMMAND_BURST = 2.0
COMMAND_CYCLE_SHARE = 0.5
# After a frame without a reply, the bus stays quiet this much beyond its wire time, so a servo
# still parsing it never sees the next header glued to it.
IDLE_GUARD_S = 0.0001
# Reply frame = FF F5 ID LEN STATUS params CHK.
REPLY_OVERHEAD = 6


def reply_wire(reply_params: int, baud: int) -> float:
    """Return the wire time of a reply with `reply_params` params."""
    return wire_time(reply_params + REPLY_OVERHEAD, baud)


def exchange_wire(frame_len: int, reply_params: int, baud: int) -> float:
    """Return the wire time of a request of `frame_len` bytes and its reply."""
    return wire_time(frame_len, baud) + reply_wire(reply_params, baud)


# What goes on the bus between two READs of the chain (next_on_bus).
YIELD, POSTED, RETRY, READ = range(4)


def next_on_bus(higher_waiting: bool, posted: bool, retry: bool) -> int:
    """Return what goes at a READ boundary: POSTED, YIELD, RETRY or READ.

    A pending command goes first (an emergency stop drops them before it waits), so a service
    never holds the newest targets back; then a caller of higher priority (an emergency stop, a
    service) takes the bus: the chain yields (a READ to be retried then counts as failed); else
    the READ to be retried, else the next READ. A retry follows a command.
    """
    if posted:
        return POSTED
    if higher_waiting:
        return YIELD
    return RETRY if retry else READ


# -- the read loop's cycles ----------------------------------------------------------------------

def plan_cycle(now: float, servos: Sequence[ServoRecord]) -> List[Tuple[ServoRecord, int]]:
    """Return (servo, READ_*) for each READ of a cycle starting `now`.

    Every servo that is not offline, and the offline ones due for their probe (one every
    REPROBE_PERIOD_S, whose time is set here, a plain position READ); where its telemetry period
    has come, the state READ and the wide READ after it.
    """
    plan = []
    for s in servos:
        if s.failures >= OFFLINE_AFTER_FAILURES:
            if now < s.next_probe:
                continue
            s.next_probe = now + REPROBE_PERIOD_S
            plan.append((s, READ_POSITION))
        elif now >= s.next_telemetry:
            # The state READ first: a cycle ends with a position, so it is published as soon
            # as its newest position is in.
            plan.append((s, READ_STATE))
            plan.append((s, READ_WIDE))
        else:
            plan.append((s, READ_POSITION))
    return plan


NOT_DUE, EMPTY, STARTED = 0, 1, 2


class ReadSchedule:
    """The read loop's cycles: which READ is next, and when a cycle is due. Times are passed in.

    ``period_s`` (1 / publish_rate_hz) and ``retries`` (per READ) are attributes the owner sets;
    the next cycle is due a period after the last started, and a cycle that starts a whole
    period late (the bus or a stall held the last one up) starts the pace afresh (``late``
    counts those, for the judgement that the bus cannot keep up).
    """

    __slots__ = ('period_s', 'retries', 'plan', 'pos', 'started', 'fresh', 'next_cycle', 'late')

    def __init__(self, period_s: float, retries: int, now: float) -> None:
        self.period_s = period_s
        self.retries = retries
        self.plan: List[Tuple[ServoRecord, int]] = []
        self.pos = 0
        self.started = 0.0
        self.fresh = True
        self.next_cycle = now
        self.late = 0

    @property
    def in_cycle(self) -> bool:
        """Whether a cycle has READs left to send."""
        return self.pos < len(self.plan)

    def reset(self, now: float) -> None:
        """Drop the cycle in progress (the servo list or the port changed); the next is due."""
        self.plan = []
        self.pos = 0
        self.next_cycle = now
        self.fresh = True  # the next cycle starts afresh: no backlog to catch up with

    def due(self, now: float) -> bool:
        """Whether the next cycle may start at `now`."""
        return now >= self.next_cycle

    def begin_cycle(self, now: float) -> bool:
        """Start the next cycle's pace if it is due at `now`; False if it is not."""
        if now < self.next_cycle:
            return False
        period = self.period_s
        if self.fresh or now - self.next_cycle > period:
            self.late += not self.fresh
            self.next_cycle = now
        self.next_cycle += period
        self.started = now
        self.fresh = False
        return True

    def plan_cycle(self, servos: Sequence[ServoRecord]) -> int:
        """Plan the READs of the cycle just begun: EMPTY (none) or STARTED."""
        self.plan = plan_cycle(self.started, servos)
        self.pos = 0
        return STARTED if self.plan else EMPTY

    def start_cycle(self, now: float, servos: Sequence[ServoRecord]) -> int:
        """Start the next cycle if due: NOT_DUE, EMPTY (no READ in it) or STARTED."""
        if not self.begin_cycle(now):
            return NOT_DUE
        return self.plan_cycle(servos)

    def take(self) -> Tuple[bytes, int, int, int, Tuple[ServoRecord, int, float, bool]]:
        """Return the next READ of the cycle as the link's ReadItem.

        (frame, servo id, reply params, retries, (servo, READ_*, cycle start, last of cycle)).
        """
        s, kind = self.plan[self.pos]
        self.pos += 1
        frame, nparams = s.frames[kind]
        # A servo that failed as often as it takes to be offline is probed without retries.
        return (frame, s.id, nparams, self.retries if s.failures < OFFLINE_AFTER_FAILURES else 0,
                (s, kind, self.started, self.pos == len(self.plan)))


# -- online / offline ----------------------------------------------------------------------------

def judge_failure(s: ServoRecord, now: float) -> bool:
    """Count a READ that failed after its retries; return True when `s` just went offline."""
    s.error_count += 1
    s.failures += 1
    if s.failures == OFFLINE_AFTER_FAILURES:
        s.next_probe = now + REPROBE_PERIOD_S
        if s.online:
            s.online = False
            return True
    return False


def judge_reply(s: ServoRecord) -> bool:
    """Count a READ answered with a position; return True when `s` came back online."""
    back = not s.online and s.seen
    s.online = True
    s.seen = True
    s.failures = 0
    return back


def plan_telemetry(s: ServoRecord, started: float, period: float, count: int) -> None:
    """Set when `s` is next due for telemetry after its wide READ of the cycle at `started`.

    The first time, the servos' telemetry READs are spread evenly over the period.
    """
    if s.telemetry_started or period <= 0:
        s.next_telemetry = started + period
    else:
        s.telemetry_started = True
        s.next_telemetry = started + period * (s.index + 1) / max(1, count)


def judge_link(servos: Sequence[ServoRecord], up: bool) -> None:
    """Judge the port opening (re-probe every servo at once) or closing (all offline)."""
    for s in servos:
        if up:
            # The servos were most likely fine all along.
            s.failures = min(s.failures, OFFLINE_AFTER_FAILURES - 1)
            s.next_probe = -math.inf
        else:
            s.online = False


# -- commands ------------------------------------------------------------------------------------

Target = Tuple[int, int, int]
"""(servo id, ticks, run time ms)."""


class CommandQueue:
    """Pending ``~/command`` targets, newest per servo, and the commands' share of the bus.

    ``add`` replaces a servo's older target (it goes to the end: the newest order); ``take``
    empties the queue into one batch; ``charge`` books a batch that left the line, and
    ``free_at`` says when the next batch may go (see COMMAND_SPACING).
    """

    __slots__ = ('pending', 'next_at', 'budget_at', 'tolerance', 'cost', 'received',
                 'superseded', 'frames_sent')

    def __init__(self) -> None:
        self.pending: Dict[int, Tuple[int, int]] = {}
        self.next_at = 0.0
        self.budget_at = 0.0  # when the commands' bus budget is paid (GCRA's TAT)
        self.tolerance = 0.0
        self.cost = 0.0  # the last batch's budget
        self.received = 0
        self.superseded = 0
        self.frames_sent = 0

    def add(self, targets: Sequence[Target]) -> None:
        """Queue a command's targets; each replaces the servo's pending one."""
        self.received += 1
        pending = self.pending
        for servo_id, ticks, ms in targets:
            if servo_id in pending:
                self.superseded += 1
                del pending[servo_id]  # re-inserted last: the newest order
            pending[servo_id] = (ticks, ms)

    def drop(self, ids: Optional[Sequence[int]] = None) -> None:
        """Forget pending targets (of `ids`, or all): a newer move or a stop overrides them."""
        if ids is None:
            self.pending = {}
        else:
            for servo_id in ids:
                self.pending.pop(servo_id, None)

    def free_at(self) -> float:
        """Return when the bus budget lets the next command batch go."""
        return max(self.next_at, self.budget_at - self.tolerance)

    def due(self, now: float) -> bool:
        """Whether targets are pending and the budget lets them go at `now`."""
        return bool(self.pending) and now >= self.free_at()

    def take(self) -> List[Target]:
        """Return the pending targets as one batch (oldest servo first) and empty the queue."""
        batch = [(i, t, ms) for i, (t, ms) in self.pending.items()]
        self.pending = {}
        return batch

    def pause(self, since: float, duration: float) -> None:
        """Let the budget's clock stand still for the `duration` another held the bus `since`.

        A stop or a service: the READs did not have that time either, and commands that gained
        bus credit from it would take it from the READs afterwards (a burst after a service).
        A budget already whole by then gains nothing from time anyway.
        """
        if self.budget_at > since:
            self.budget_at += duration

    def late_batch(self, ended: float) -> None:
        """Take a batch written late, whose last byte left the line by `ended`.

        Its lag is paused (no budget earned from it), but batches written late one after the
        other each found the budget within the two-batch burst again and went back to back
        while READs waited (the bus search found commands four batches ahead of READs). So the
        next batch goes one batch ahead of the budget at most, or a whole batch's budget after
        this one really ended if that is sooner: the burst granted before is not taken back
        (a target the host's lag already held waited a whole read cycle more when it was).
        """
        self.tolerance = min(self.tolerance,
                             max(self.cost, self.budget_at - ended - self.cost))

    def charge(self, ended_at: float, size: int, baud: int, rate_hz: float) -> None:
        """Book a batch of `size` bytes that left the line at `ended_at`."""
        wire = wire_time(size, baud)
        self.cost = cost = wire * (1.0 + COMMAND_SPACING)
        self.budget_at = max(self.budget_at, ended_at - wire) + cost
        self.tolerance = COMMAND_BURST * cost
        self.next_at = ended_at + COMMAND_CYCLE_SHARE / rate_hz


# A service READ left unanswered may still be answered this long after its last attempt's
# deadline (ten times a scan's listening): its length is kept from the next READs of that servo.
OWED_REPLY_S = 1.0


def own_read(address: int, length: int, taken: Sequence[int] = ()) -> Tuple[int, int, int]:
    """Return (address, length, skip): the READ a service sends for `length` bytes at `address`.

    A reply names its servo and its length, not the address it was read from. A service READ
    of the length of one of the read loop's (or of `taken`: the lengths of that servo's READs
    whose late replies may still come) would take such a late reply for its own, and the loop
    would take one of its own (register 0x10 read as a position). So it runs on past its end,
    or starts before it at the table's end, to a length of its own; its bytes are the reply's
    from `skip`.
    """
    avoid = {n for _, n in LOOP_READS} | set(taken)
    if length not in avoid:
        return address, length, 0
    for size in range(length + 1, proto.MAX_READ_LENGTH + 1):
        if size not in avoid:
            start = min(address, 256 - size)
            return start, size, address - start
    return address, length, 0  # (every longer length taken: not in practice)


def trimmed(reply: proto.Reply, skip: int, length: int) -> proto.Reply:
    """Return `reply` with the `length` params from `skip` (an :func:`own_read`'s own bytes)."""
    if skip == 0 and len(reply.params) == length:
        return reply
    return proto.Reply(reply.servo_id, reply.status, reply.params[skip:skip + length], reply.raw)


def sync_write_frames(targets: Sequence[Target]) -> List[bytes]:
    """Return the SYNC WRITE frames of (id, ticks, ms) targets (50 servos per frame, S18)."""
    step = proto.MAX_SYNC_WRITE_POSITIONS
    return [proto.encode_sync_write_positions(targets[k:k + step])
            for k in range(0, len(targets), step)]


# -- ids and shutdown ----------------------------------------------------------------------------

def set_id_refusal(servos: Sequence[ServoRecord], old: int, new: int) -> Optional[str]:
    """Return why ``~/set_id old -> new`` is refused before anything is sent, or None.

    The one rule that keeps joints apart: `new` must not be the id of a configured joint.
    """
    if not (proto.is_servo_id(old) and proto.is_servo_id(new)):
        return f'id and new_id must be 1..250, got {old} -> {new}'
    if old == new:
        return f'servo already has id {new}'
    owner = next((s for s in servos if s.id == new), None)
    if owner is not None:
        state = 'online' if owner.online else 'offline'
        return (f'id {new} belongs to joint {owner.name} (servo_ids; it is {state}): two '
                'joints would share it. Pick an id not in servo_ids; to move a servo onto a '
                'configured id, run the driver without that id in servo_ids first')
    return None


# How long a reply that ends a sweep may still come (the scan listens this long after its last
# PING), and the least a PING that decides an answer waits for its reply.
LATE_REPLY_WINDOW_S = 0.1


def patient_wait(frame_len: int, reply_params: int, baud: int, usual: float) -> float:
    """Return an attempt's wait when its silence decides an answer (`usual`: the normal one).

    A PING that finds an id free, or tells after a lost acknowledgement where a servo is, is
    not judged by the margin of the read loop, which a late device or a host that stalls for a
    few ms overruns: its silence becomes what a service answers (and a set_id onto an id whose
    servo answered late would make two servos share it).
    """
    return max(usual, exchange_wire(frame_len, reply_params, baud) + LATE_REPLY_WINDOW_S)


# ~/set_id's probe of the old id (S24): this many READs of its present position, one attempt
# each, and after each reply a wait for a second servo's reply to end (probe_quiet_s).
PROBE_READS = 5


def probe_quiet_s(baud: int) -> float:
    """Return the wait after a probe READ's reply: a second whole reply follows it at once."""
    return wire_time(2 * (POSITION.size + 6), baud) + 0.003


def judge_probe(values: Sequence[int], garbled: int, unsolicited: int,
                values_differ: bool = True) -> Tuple[str, str]:
    """Return ('none' | 'one' | 'unsure' | 'several', why) after PROBE_READS READs of an id.

    `values`: the positions of the READs answered; `garbled`: READs answered by bytes that made
    no frame; `unsolicited`: replies of that id and size no READ took, while they ran. Two
    servos at one id collide (garbled replies) or, on a bus that keeps their replies apart,
    answer twice (a READ without a reply of its own may be answered late, once: beyond those,
    more than one servo answers); their positions also rarely agree (`values_differ`: count
    that as a sign too, at the price of a moving servo looking like two). 'one' only when every
    READ was answered in its time (its patient wait, ``patient_wait``): on a bus that loses
    replies a second servo's may be among those lost (and a late reply is not told from a
    second servo's), and the PINGs that found the new id free may have missed a servo there
    ('unsure').
    """
    extra = unsolicited - (PROBE_READS - len(values))
    if garbled:
        return 'several', f'{garbled} of {PROBE_READS} replies garbled (colliding replies)'
    if extra > 0:
        return 'several', f'{extra} replies more than requests'
    if values_differ and len(set(values)) > 1:
        return 'several', (f'its present position read {few(sorted(set(values)))}: two '
                           'servos, or one that is moving (stop it first)')
    if not values:
        return 'none', ''
    if len(values) < PROBE_READS:
        # A reply that came late and a second servo's reply look alike (the search found two
        # lost READs hiding a second servo's two replies): only a READ answered in its time
        # is known to be one servo's.
        return 'unsure', (f'{PROBE_READS - len(values)} of {PROBE_READS} READs not answered in '
                          'time: the bus loses or delays replies, and a servo may go unheard')
    return 'one', ''


def renamed(servos: Sequence[ServoRecord], old: int, new: int) -> Tuple[ServoRecord, ...]:
    """Return the servo list after the servo at `old` took id `new` (a fresh record)."""
    out = []
    for s in servos:
        if s.id == old:
            name = f'servo_{new}' if s.name == f'servo_{old}' else s.name
            s = ServoRecord(Joint(new, name), s.index)
        out.append(s)
    return tuple(out)


TORQUE_OFF_ALL = proto.encode_write(proto.BROADCAST_ID, TORQUE.address, b'\x00')
"""Torque off, every servo at once: the emergency stop and the last frame of a shutdown."""


def shutdown_frames(torque_off_on_shutdown: bool) -> List[bytes]:
    """Return the frames of a shutdown, in order; torque off (if configured) is the last.

    Pending commands are dropped, never sent: a target that left after torque off would drive
    a servo again.
    """
    return [TORQUE_OFF_ALL] if torque_off_on_shutdown else []
