"""The servo bus as a device: its servos, the read loop, commands and services. No ROS here.

:class:`ServoBusCore` owns the bus (:class:`~desheng_servo_ros.link.ServoBusLink`), the servo list
and what is known of each servo, and the rules: read cycles (one READ per servo, telemetry spread
over the period, offline after failures and re-probed), duplicate ids, the coalesced command hot
path and every service as a call that returns a :class:`Result`. It reports through callbacks
(``on_cycle(snapshot)``, ``on_change()``, ``on_servos()``) and takes a clock for everything that
is planned in time. The node (``node.py``) only translates. Decisions: ``docs/protocols.md``,
"Driver decisions" of the servo bus.

Threads and state (who writes what, and what guards it):

- **read loop** (``_loop_main``): start-up scan, torque on at start, then read cycles as one
  chain of READs (``ServoBusLink.read_chain``); it restarts itself after any failure. It owns
  ``_cycles`` and the loop-failure fields.
- **link reader thread**: while a chain runs, it sends each next READ and handles each reply
  (``_on_read``, ``ReadCycles``), and runs ``_on_connection``. A chain's results are handed out
  one at a time (the chain's lock), so each servo's fields have a single writer at a time, with
  no lock: a servo's ``reading`` and ``telemetry`` are immutable tuples replaced in one
  assignment, so a snapshot never mixes two replies.
- **reporter** (``_reporter_main``): calls ``on_cycle(snapshot)`` after each cycle, off the wire.
- **commander** (``_commander_main``): sends the newest pending command; ``_pending`` and
  the command budget (``_next_command_at``, ``_command_budget_at``) are guarded by
  ``_cmd_cond``.
- **callers** (the node's executor threads): services and ``command()``. A service that needs
  a quiet bus or changes the servo list pauses the read loop first (``_pause`` and
  ``_loop_idle``, guarded by ``_pause_cond``).
- ``_servos`` is a tuple replaced in one assignment (start-up scan, ``set_id``, both with the
  loop paused); readers take it once. The duplicate-id bookkeeping is written by the reader
  thread at cycle starts only.
- The bus itself: one transaction at a time under the link's priority lock (emergency stop >
  commands and services > read loop).
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, field, fields, replace
import functools
import math
import threading
import time
import traceback
from typing import Any, Callable, Dict, Iterator, List, NamedTuple, Optional, Sequence, Tuple

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.link import (BusBusy, LinkDown, LinkError, LinkTimeout, PRIORITY_LOOP,
                                    Posted, PRIORITY_SERVICE, PRIORITY_URGENT, ReadItem,
                                    ServoBusLink, sync_write_frames)
from desheng_servo_ros.registers import (by_address, by_name, decode_block, decode_value,
                                         encode_value, RegisterError)
from desheng_servo_ros.units import (Joint, resolve_targets, select, servo_list, Target,
                                     Units)
from uav_serial_common.logs import log_at, Throttle
from uav_serial_common.pty_port import wire_time
from uav_serial_common.text import clip, few
from uav_serial_common.usb_latency import LatencyReport

# Registers, by name from the table (registers.py).
TORQUE = by_name('torque_enable')
ID = by_name('id')
FIRMWARE = by_name('firmware_version')
POSITION = by_name('present_position')
SPEED = by_name('present_speed')
CURRENT = by_name('current')
TEMPERATURE = by_name('temperature')
RUN_PRESETS = tuple(by_name(f'run_preset_{k}') for k in (1, 2, 3))
FACTORY_ID = ID.default  # S23: RESET gives every servo the table's default id
# The read loop's READs. Each cycle reads position + speed of every servo; where a servo's
# telemetry is due, that READ runs on to the temperature (0x38..0x3F) and a second one takes
# 0x28..0x2F (torque switch, current). Two 8-byte blocks rather than one of 24 (0x28..0x3F):
# no READ holds the bus longer than 1.9 ms at 115200 baud (the block of 24 held it 3.3 ms), and
# a command waits for the READ in flight.
assert SPEED.address == POSITION.end
POSITION_READ = (POSITION.address, POSITION.size + SPEED.size)
WIDE_READ = (POSITION.address, TEMPERATURE.end - POSITION.address)
STATE_READ = (TORQUE.address, CURRENT.end - TORQUE.address)
_W_TEMPERATURE = TEMPERATURE.address - POSITION.address
_S_CURRENT = CURRENT.address - TORQUE.address
# What a READ of the loop is for (the plan's entries, the tags of its replies).
READ_POSITION, READ_WIDE, READ_STATE = 0, 1, 2

# A servo is offline after this many READs in a row failed (each with its retries), and then
# probed this often (one READ, no retries), so a missing servo costs little bus time.
OFFLINE_AFTER_FAILURES = 3
REPROBE_PERIOD_S = 1.0
SCAN_RETRY_S = 5.0
PAUSE_TIMEOUT_S = 2.0
# Duplicate ids (S24), judged once per CHECK_PERIOD_S: replies beyond the requests of an id
# (clean replies, on a bus that keeps them apart), or an id whose replies come garbled more often
# than not (colliding replies: the link's garble_level). Reported for DUPLICATE_HOLD_S after the
# last sign.
CHECK_PERIOD_S = 1.0
DUPLICATE_SURPLUS = 2
DUPLICATE_GARBLE_LEVEL = 0.5
DUPLICATE_HOLD_S = 5.0
GARBLE_HINT_LEVEL = 0.2
# READs of the present position that tell one servo at an id from several (set_id, scan).
PROBE_READS = 5
# An id change or RESET whose frame left without an acknowledgement (lost, or the link dropped)
# is settled by asking the bus; a link that went down gets this long to come back for that.
SETTLE_WAIT_S = 2.0
# A failed read loop is reported for this long after its last failure, and restarts after a
# pause that grows up to LOOP_BACKOFF_MAX_S.
LOOP_FAILURE_HOLD_S = 10.0
LOOP_BACKOFF_MAX_S = 1.0
# Commands coming faster than the bus should take them are coalesced. Each batch of command
# frames owes the read loop COMMAND_SPACING times its wire time, so over any stretch commands
# take at most 1 / (1 + COMMAND_SPACING) of the bus; a batch that finds that budget unspent goes
# at once, up to COMMAND_BURST batches ahead of it (a token bucket kept as a time, GCRA), so a
# command at a normal rate waits only for the READ on the wire. Budget and spacing count from
# the line: a loaded host that writes a batch late moves them with it. Batches are also at
# least COMMAND_CYCLE_SHARE of a read cycle apart (at most two per cycle).
COMMAND_SPACING = 2.0
COMMAND_BURST = 2.0
COMMAND_CYCLE_SHARE = 0.5
ALL_IDS = range(proto.MIN_ID, proto.MAX_ID + 1)

OK, WARN, ERROR, STALE = 0, 1, 2, 3
"""Diagnostic levels (diagnostic_msgs' values)."""


@dataclass
class ServoBusConfig:
    """What the driver is told at start (the node's parameters)."""

    port: str = '/dev/ttyUSB1'
    baud: int = 115200
    servo_ids: Sequence[int] = ()
    joint_names: Sequence[str] = ()
    ticks_per_revolution: int = 4096
    zero_tick: int = 2048
    publish_rate_hz: float = 50.0
    telemetry_period_s: float = 1.0
    default_move_time_ms: int = 0
    response_timeout_ms: float = 0.0
    max_retries: int = 1
    torque_on_start: bool = False
    torque_off_on_shutdown: bool = True
    adjust_latency_timer: bool = True

    RUNTIME = ('publish_rate_hz', 'telemetry_period_s', 'default_move_time_ms',
               'response_timeout_ms', 'max_retries', 'torque_off_on_shutdown')
    """What may change while running; everything else shapes the driver and is read once."""

    @classmethod
    def from_values(cls, values: Dict[str, Any]) -> 'ServoBusConfig':
        """Build a config from a dict with (at least) the field names; others are ignored."""
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in values.items() if k in names})


class Result(NamedTuple):
    """A service's answer: whether it did what was asked, what happened, response fields."""

    ok: bool
    message: str
    data: Optional[Dict[str, Any]] = None


class Health(NamedTuple):
    """A diagnostic status: level (OK..STALE), message, key/value pairs."""

    level: int
    message: str
    values: List[Tuple[str, Any]]


class Reading(NamedTuple):
    """What one reply tells of a servo's position (replaced whole on every reply)."""

    ticks: int
    rad: float
    speed_raw: int
    velocity: float
    status: int
    at: float
    """When the reply arrived (the reader thread took it off the port), monotonic [s]."""


class Telemetry(NamedTuple):
    """What the slow READ tells (replaced whole)."""

    current_ma: float
    temperature_c: float
    torque_enabled: bool


class ServoSnapshot(NamedTuple):
    """One servo as of the last cycle."""

    id: int
    name: str
    online: bool
    seen: bool
    position_ticks: int
    position_rad: float
    speed_raw: int
    velocity: float
    current_ma: float
    temperature_c: float
    status: int
    torque_enabled: bool
    error_count: int
    duplicate: bool
    read_at: float = math.nan
    """When the position arrived off the wire (monotonic clock) [s]; NaN before the first."""

    @property
    def faults(self) -> List[str]:
        """Names of the documented fault bits set in the last status byte (S4)."""
        return fault_names(self.status)


def fault_names(status: int) -> List[str]:
    """Return the names of the documented fault bits set in a status byte (S4)."""
    return [name for bit, name in _FAULT_BITS if status & bit]


_FAULT_BITS = ((proto.STATUS_OVERLOAD, 'overload'),
               (proto.STATUS_OVER_TEMPERATURE, 'over-temperature'),
               (proto.STATUS_VOLTAGE_FAULT, 'voltage fault'))
# Immutable tuples on the hot path are built without NamedTuple's keyword handling.
_new = tuple.__new__


@dataclass(frozen=True)
class BusSnapshot:
    """Every configured servo, and whether the port is open."""

    connected: bool
    servos: Tuple[ServoSnapshot, ...] = field(default_factory=tuple)
    read_at: Optional[float] = None
    """When the oldest position of an online servo arrived off the wire (monotonic) [s]: the
    time the messages are stamped with; None when no servo is online."""


class _Servo:
    """What the driver knows of one servo (see the module docstring for who writes it)."""

    __slots__ = ('id', 'name', 'index', 'frames', 'online', 'seen',
                 'failures', 'error_count', 'reading', 'telemetry', 'next_telemetry',
                 'next_probe', 'direction', 'telemetry_started', 'surplus_mark',
                 'duplicate_until')

    def __init__(self, joint: Joint, index: int) -> None:
        self.id = joint.id
        self.name = joint.name
        self.index = index
        # By READ_POSITION, READ_WIDE, READ_STATE: (frame, reply params).
        self.frames = tuple((proto.encode_read(joint.id, *block), block[1])
                            for block in (POSITION_READ, WIDE_READ, STATE_READ))
        self.online = False
        self.seen = False
        self.failures = 0
        self.error_count = 0
        self.reading = Reading(0, math.nan, 0, 0.0, 0, math.nan)
        self.telemetry = Telemetry(math.nan, math.nan, False)
        self.next_telemetry = 0.0
        self.next_probe = 0.0
        self.direction = 1.0
        self.telemetry_started = False
        self.surplus_mark: Optional[int] = None
        self.duplicate_until = -math.inf

    @property
    def joint(self) -> Joint:
        return Joint(self.id, self.name)

    def set_torque(self, enabled: bool) -> None:
        self.telemetry = self.telemetry._replace(torque_enabled=enabled)


def plan_cycle(now: float, servos: Sequence[_Servo]) -> List[Tuple[_Servo, int]]:
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


class ReadCycles:
    """The read loop's cycles (one READ per active servo) as a plan for a chain of READs.

    The link asks for each next READ the moment the previous reply is in, so consecutive cycles
    follow each other on the wire without a gap when ``publish_rate_hz`` asks for more than the
    bus carries; otherwise the chain ends after a cycle and the read loop waits for the next
    one. Runs on the link's reader thread (replies) and the read loop (timeouts). It knows the
    rest of the driver only through what it is given: the clock, the servos, the period, where
    results and cycle starts/ends go, and two attributes its owner sets: ``enabled`` (READs may
    go out) and ``retries`` (per READ). Attributes, not calls: they are read for every READ.
    """

    def __init__(self, *, clock: Callable[[], float], servos: Callable[[], Sequence[_Servo]],
                 period_s: Callable[[], float],
                 on_read: Callable[[_Servo, int, float, Optional[proto.Reply]], None],
                 on_cycle_start: Callable[[float], None],
                 on_cycle_done: Callable[[], None], retries: int = 1) -> None:
        self._clock = clock
        self._servos = servos
        self._period_s = period_s
        self.enabled = False
        self.retries = retries
        self._on_read = on_read
        self._on_cycle_start = on_cycle_start
        self._on_cycle_done = on_cycle_done
        self.plan: List[Tuple[_Servo, bool]] = []
        self.pos = 0
        self.started = 0.0
        self.fresh = True
        self.next_cycle = self._clock()
        self.late = 0  # cycles that started a period late (read and reset by _check)
        self.behind_logged = False

    @property
    def in_cycle(self) -> bool:
        """Whether a cycle has READs left to send."""
        return self.pos < len(self.plan)

    def reset(self) -> None:
        """Drop the cycle in progress (the servo list or the port changed); the next is due."""
        self.plan = []
        self.pos = 0
        self.next_cycle = self._clock()
        self.fresh = True  # the next cycle starts afresh: no backlog to catch up with

    def next_read(self) -> Optional[ReadItem]:
        """Return the next READ of this cycle, or of the next one when it is due, else None."""
        if not self.enabled:
            return None
        if self.pos >= len(self.plan) and not self._start_cycle():
            return None
        s, kind = self.plan[self.pos]
        self.pos += 1
        tag = (s, kind, self.started, self.pos == len(self.plan))
        # A servo that failed as often as it takes to be offline is probed without retries.
        retries = self.retries if s.failures < OFFLINE_AFTER_FAILURES else 0
        frame, nparams = s.frames[kind]
        return frame, s.id, nparams, retries, tag

    def on_read(self, tag: Tuple[_Servo, int, float, bool],
                reply: Optional[proto.Reply]) -> None:
        """Take the result of one READ; the last one of a cycle completes it."""
        s, kind, started, last = tag
        self._on_read(s, kind, started, reply)
        if last:
            self._on_cycle_done()

    def start(self) -> bool:
        """Plan a cycle now if one is due (for read_cycle); returns whether it has READs."""
        self.plan, self.pos = [], 0
        return self._start_cycle()

    def _start_cycle(self) -> bool:
        now = self._clock()
        if now < self.next_cycle:
            return False
        period = self._period_s()
        if self.fresh or now - self.next_cycle > period:
            # A whole period late: the bus (or a stall of this process) held the last cycle up.
            # Whether the bus cannot keep up at all is judged over a second (_check).
            self.late += not self.fresh
            self.next_cycle = now
        self.next_cycle += period
        self.started = now
        self.fresh = False
        self._on_cycle_start(now)
        self.plan = plan_cycle(now, self._servos())
        self.pos = 0
        if not self.plan:
            # Every servo is offline and none is due for a probe: publish that all the same.
            self._on_cycle_done()
            return False
        return True


# Services that change nothing on a servo: a request of theirs that went unanswered leaves no
# outcome to find out.
_READS_ONLY = frozenset({'read_register', 'scan'})


def _service(method: Callable[..., Result]) -> Callable[..., Result]:
    """One error path for every service: refusals, link errors and bugs become a Result."""
    @functools.wraps(method)
    def call(self: 'ServoBusCore', *args: Any, **kwargs: Any) -> Result:
        try:
            result = method(self, *args, **kwargs)
        except (ValueError, RegisterError) as exc:
            result = Result(False, f'refused: {exc}')
        except LinkError as exc:
            if not exc.sent and isinstance(exc, LinkDown):
                result = Result(False, f'port not open: {exc}; nothing sent')
            elif exc.sent and method.__name__ not in _READS_ONLY:
                # The servo may have acted on a frame whose answer never came.
                result = Result(False, f'bus error: {exc}; the request had left, so whether the '
                                       'servo acted on it is UNKNOWN (read it back)')
            else:
                result = Result(False, f'bus error: {exc}')
        except Exception as exc:  # noqa: BLE001 - a bug must not cost the node
            self.log_error(f'{method.__name__} failed:\n{traceback.format_exc()}')
            result = Result(False, f'internal error: {exc!r}')
        return Result(result.ok, clip(result.message), result.data)
    return call


def _unknown(what: str, error: LinkError, then: str) -> Result:
    """Answer an outcome the bus did not tell: never a success or refusal not seen."""
    return Result(False, f'UNKNOWN whether {what}: its frame left, then {error}; {then}')


class ServoBusCore:
    """One bus of Desheng servos: read loop, commands, services, health. See the module doc."""

    def __init__(self, config: ServoBusConfig, *, clock: Callable[[], float] = time.monotonic,
                 logger: Optional[Any] = None,
                 on_cycle: Optional[Callable[[BusSnapshot], None]] = None,
                 on_change: Optional[Callable[[], None]] = None,
                 on_servos: Optional[Callable[[], None]] = None,
                 backoff_max_s: float = 1.0) -> None:
        self.config = config
        self.clock = clock
        self.units = Units(config.ticks_per_revolution, config.zero_tick)
        self._rad_per_tick = self.units.rad_per_tick
        self._zero_tick = self.units.zero_tick
        joints = servo_list(config.servo_ids, config.joint_names)  # ValueError: bad config
        self._servos: Tuple[_Servo, ...] = tuple(_Servo(j, k) for k, j in enumerate(joints))
        self._configured_ids = frozenset(config.servo_ids)
        self._scan_at_start = not self._servos
        self._log = logger
        self._on_cycle = on_cycle
        self._on_change = on_change
        self._on_servos = on_servos
        self._throttle = Throttle()
        self.bus = ServoBusLink(config.port, config.baud,
                                response_timeout_ms=config.response_timeout_ms,
                                max_retries=config.max_retries,
                                on_connection=self._on_connection, logger=logger,
                                backoff_max_s=backoff_max_s,
                                adjust_latency_timer=config.adjust_latency_timer,
                                on_latency=self._on_latency)
        self._link = self.bus.link
        self._latency_logged = ''
        self._cycles = ReadCycles(
            clock=clock, servos=lambda: self._servos,
            period_s=lambda: 1.0 / self.config.publish_rate_hz,
            on_read=self._on_read, on_cycle_start=self._cycle_started,
            on_cycle_done=self._cycle_done, retries=config.max_retries)
        self._running = False
        self._pause = 0
        self._loop_idle = False
        self._pause_cond = threading.Condition()
        self._startup_done = False
        self.cycle_count = 0
        self.cycle_rate_hz = 0.0
        self._rate_mark: Optional[Tuple[float, int]] = None
        self._next_check = -math.inf
        self._offline_report_at = -math.inf
        self._loop_failures = 0
        self._loop_failure = ''
        self._loop_failed_at = -math.inf
        self._report_cond = threading.Condition()
        self._report_due = False
        self._cmd_cond = threading.Condition()
        self._pending: Dict[int, Tuple[int, int]] = {}
        self._next_command_at = 0.0
        self._command_budget_at = 0.0  # when the commands' bus budget is paid (GCRA's TAT)
        self._command_tolerance = 0.0
        self._last_post: Optional[Posted] = None
        self.commands_received = 0
        self.commands_superseded = 0
        self.command_frames_sent = 0
        self._threads: List[threading.Thread] = []
        self._loop: Optional[threading.Thread] = None

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self, read_loop: bool = True) -> None:
        """Open the port and start the threads (without the read loop: tests call read_cycle)."""
        self._running = True
        self._allow_reading()
        self.bus.start()
        for target, name in ((self._reporter_main, 'servo-reporter'),
                             (self._commander_main, 'servo-commands')):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)
        if read_loop:
            self._loop = threading.Thread(target=self._loop_main, name='servo-read-loop',
                                          daemon=True)
            self._loop.start()

    def stop(self) -> None:
        """Stop the threads, broadcast torque off as the last frame (if configured), close."""
        self._running = False
        self._allow_reading()
        for cond in (self._pause_cond, self._report_cond, self._cmd_cond):
            with cond:
                cond.notify_all()
        if self._loop is not None:
            self._loop.join(2.0)
        for thread in self._threads:
            thread.join(1.0)
        try:
            if self.config.torque_off_on_shutdown:
                if not self.bus.connected:
                    # Said, not silently skipped: the servos may still hold their torque.
                    raise LinkDown(f'{self.config.port} is not open '
                                   f'({self.bus.link.last_error or "not connected"})')
                self.bus.write(proto.BROADCAST_ID, TORQUE.address, b'\x00', PRIORITY_URGENT)
                self.bus.drain()
        except LinkError as exc:
            self.log_error(f'torque off on shutdown NOT sent: {exc}; servos that had torque on '
                           'still hold it')
        finally:
            self.bus.stop()

    def update_config(self, changes: Dict[str, Any]) -> None:
        """Apply runtime parameter changes (the others are refused before they get here)."""
        runtime = {k: v for k, v in changes.items() if k in ServoBusConfig.RUNTIME}
        self.config = replace(self.config, **runtime)
        if 'publish_rate_hz' in runtime:
            self._cycles.behind_logged = False
        if 'response_timeout_ms' in runtime:
            self.bus.response_timeout_ms = runtime['response_timeout_ms']
        if 'max_retries' in runtime:
            self.bus.max_retries = self._cycles.retries = runtime['max_retries']

    # -- what others read -----------------------------------------------------------------------

    @property
    def servos(self) -> Tuple[Joint, ...]:
        """Return each servo's id and joint name, in the order of servo_ids."""
        return tuple(s.joint for s in self._servos)

    def snapshot(self) -> BusSnapshot:
        """Return every servo as last read (callable from any thread)."""
        now = self.clock()
        out = []
        oldest = math.inf
        for s in self._servos:
            r, t = s.reading, s.telemetry
            if s.online and r.at < oldest:
                oldest = r.at
            # The fields of ServoSnapshot, in order.
            out.append(_new(ServoSnapshot, (
                s.id, s.name, s.online, s.seen, r.ticks, r.rad, r.speed_raw, r.velocity,
                t.current_ma, t.temperature_c, r.status, t.torque_enabled, s.error_count,
                now < s.duplicate_until, r.at)))
        return BusSnapshot(self.bus.connected, tuple(out),
                           oldest if oldest < math.inf else None)

    # -- logging --------------------------------------------------------------------------------

    def _emit(self, level: str, text: str, every_s: float = 0.0, key: str = '') -> None:
        if self._log is None:
            return
        if every_s > 0:
            note = self._throttle.admit(key or text, time.monotonic(), every_s)
            if note is None:
                return
            text = clip(text) + note
        else:
            text = clip(text)
        try:
            log_at(self._log, level, text)
        except Exception:  # noqa: BLE001 - logging must never cost the bus (context gone)
            pass

    def log_info(self, text: str) -> None:
        """Log an information line (bounded)."""
        self._emit('info', text)

    def log_warning(self, text: str, every_s: float = 0.0, key: str = '') -> None:
        """Log a warning (bounded; at most once per `every_s` per key when given)."""
        self._emit('warning', text, every_s, key)

    def log_error(self, text: str, every_s: float = 0.0, key: str = '') -> None:
        """Log an error (bounded; throttled like log_warning)."""
        self._emit('error', text, every_s, key)

    def _changed(self) -> None:
        if self._on_change is not None:
            try:
                self._on_change()
            except Exception:  # noqa: BLE001 - a reporting problem never stops reading
                pass

    # -- read loop ------------------------------------------------------------------------------

    def _allow_reading(self) -> None:
        # The read cycles check this flag before every READ (running and not paused).
        self._cycles.enabled = self._running and not self._pause

    def _loop_main(self) -> None:
        backoff = 0.05
        while self._running:
            try:
                if not self._startup_done:
                    self._startup()
                self._run_cycles()
            except Exception as exc:  # noqa: BLE001 - never die, never silently
                self._loop_failures += 1
                self._loop_failed_at = self.clock()
                text = f'{type(exc).__name__}: {exc}'
                detail = f':\n{traceback.format_exc()}' if text != self._loop_failure else ''
                self._loop_failure = text
                self.log_error(f'read loop failed ({text}); restarting it{detail}', every_s=5.0,
                               key='loop-failed')
                self._changed()
                self._cycles.reset()
                with self._pause_cond:  # real time: a stopped test clock must not hold it
                    self._pause_cond.wait(backoff)
                backoff = min(backoff * 2, LOOP_BACKOFF_MAX_S)

    def _sleep(self, seconds: float, until_pause: bool = True) -> None:
        # In short steps of real time against the clock, so a pause or shutdown never waits for
        # a slow rate, and a test's clock can move time on.
        deadline = self.clock() + seconds
        with self._pause_cond:
            while self._running and not (until_pause and self._pause):
                remaining = deadline - self.clock()
                if remaining <= 0:
                    return
                self._pause_cond.wait(min(0.05, remaining))

    def _wait_connected(self) -> bool:
        while self._running:
            if self.bus.wait_connected(0.1):
                return True
        return False

    def _startup(self) -> None:
        while self._scan_at_start and self._running:
            if not self._wait_connected():
                return
            self.log_info('servo_ids is empty: scanning ids 1..250')
            try:
                found = self.bus.scan(ALL_IDS, priority=PRIORITY_LOOP)
            except LinkError as exc:
                self.log_warning(f'scan interrupted: {exc}')
                continue
            if found:
                self._set_servos(tuple(_Servo(j, k) for k, j in enumerate(servo_list(found))))
                self._scan_at_start = False
                self.log_info(f'found servos {found}')
                break
            self.log_error(
                f'no servo answers on {self.config.port} at {self.config.baud} baud: check '
                'power, wiring and the baud parameter; scanning again in '
                f'{SCAN_RETRY_S:.0f} s')
            self._sleep(SCAN_RETRY_S, until_pause=False)
        if self.config.torque_on_start and self._wait_connected():
            for s in self._servos:
                try:
                    self.bus.write(s.id, TORQUE.address, b'\x01', PRIORITY_LOOP)
                    s.set_torque(True)
                except LinkError as exc:
                    self.log_warning(f'torque on at start: {s.name} (id {s.id}): {exc}')
        self._startup_done = True

    def _run_cycles(self) -> None:
        cycles = self._cycles
        while self._running:
            if self._pause:
                self._idle_while_paused()
                cycles.reset()
                continue
            if not self.bus.connected:
                # Keep servo_states (all offline) and diagnostics coming while the port is away,
                # at the publish rate, and look at the port often enough for a prompt shutdown.
                now = self.clock()
                if now >= self._offline_report_at:
                    self._report()
                    self._offline_report_at = now + 1.0 / self.config.publish_rate_hz
                self.bus.wait_connected(min(0.1, 1.0 / self.config.publish_rate_hz))
                cycles.reset()
                continue
            if not cycles.in_cycle:
                delay = cycles.next_cycle - self.clock()
                if delay > 0:
                    self._sleep(delay)
                    continue
            try:
                # Returns between cycles when the next one is not due yet, or early when a
                # command, a service or a pause wants the bus.
                self.bus.read_chain(cycles, PRIORITY_LOOP)
            except (LinkDown, BusBusy):
                continue

    def read_cycle(self) -> BusSnapshot:
        """Run one read cycle now, on the calling thread, and return the snapshot (tests)."""
        cycles = self._cycles
        cycles.next_cycle = min(cycles.next_cycle, self.clock())
        if cycles.start():
            self.bus.read_chain(_OneCycle(cycles), PRIORITY_LOOP)
        return self.snapshot()

    def _idle_while_paused(self) -> None:
        with self._pause_cond:
            while self._pause and self._running:
                self._loop_idle = True
                self._pause_cond.notify_all()
                self._pause_cond.wait(0.1)
            self._loop_idle = False

    @contextmanager
    def _loop_paused(self) -> Iterator[None]:
        """Hold the read loop between two READs (scan, id change, reset)."""
        with self._pause_cond:
            self._pause += 1
            self._allow_reading()
            self._pause_cond.notify_all()
            loop = self._loop
            self._pause_cond.wait_for(
                lambda: self._loop_idle or loop is None or not loop.is_alive(), PAUSE_TIMEOUT_S)
        try:
            yield
        finally:
            with self._pause_cond:
                self._pause -= 1
                self._allow_reading()
                self._pause_cond.notify_all()

    def _set_servos(self, servos: Tuple[_Servo, ...]) -> None:
        self._servos = servos  # one assignment: readers see the old or the new tuple
        self._cycles.reset()
        if self._on_servos is not None:
            try:
                self._on_servos()
            except Exception:  # noqa: BLE001
                self.log_error(f'servo list handler failed:\n{traceback.format_exc()}')
        self._changed()

    # -- the hot path (link reader thread) ------------------------------------------------------

    def _on_read(self, s: _Servo, kind: int, started: float,
                 reply: Optional[proto.Reply]) -> None:
        """Take the result of one READ of the cycle that started at `started`."""
        if reply is None:
            self._failed(s, started)
            return
        p = reply.params
        if kind == READ_STATE:
            s.telemetry = s.telemetry._replace(current_ma=float((p[_S_CURRENT] << 8)
                                                                | p[_S_CURRENT + 1]),
                                               torque_enabled=p[0] != 0)
            if s.failures:
                s.failures = 0
            return
        if kind == READ_WIDE:
            period = self.config.telemetry_period_s
            if s.telemetry_started or period <= 0:
                s.next_telemetry = started + period
            else:
                # Spread the telemetry reads of the servos evenly over the period.
                s.telemetry_started = True
                s.next_telemetry = started + period * (s.index + 1) / max(1, len(self._servos))
            s.telemetry = s.telemetry._replace(temperature_c=float(p[_W_TEMPERATURE]))
        self._update_position(s, (p[0] << 8) | p[1], (p[2] << 8) | p[3], reply.status)

    def _update_position(self, s: _Servo, ticks: int, speed: int, status: int) -> None:
        old = s.reading
        if ticks != old.ticks and s.seen:
            s.direction = 1.0 if ticks > old.ticks else -1.0
        rpt = self._rad_per_tick
        # Stamped with the reply's arrival: the reader thread took it off the port just now.
        s.reading = _new(Reading, (ticks, (ticks - self._zero_tick) * rpt, speed,
                                   s.direction * speed * rpt if speed else 0.0, status,
                                   self._link.last_rx_time))
        changed = status != old.status or not s.online
        if not s.online and s.seen:
            self.log_info(f'{s.name} (id {s.id}) is back online')
        s.online = True
        s.seen = True
        s.failures = 0
        if changed:
            self._changed()

    def _failed(self, s: _Servo, now: float) -> None:
        s.error_count += 1
        s.failures += 1
        if s.failures == OFFLINE_AFTER_FAILURES:
            s.next_probe = now + REPROBE_PERIOD_S
        if s.failures == OFFLINE_AFTER_FAILURES and s.online:
            s.online = False
            self._changed()
            self.log_warning(
                f'{s.name} (id {s.id}) stopped answering: offline, probing it every '
                f'{REPROBE_PERIOD_S:g} s (check its power and cable; ~/scan lists the bus)')

    def _cycle_started(self, now: float) -> None:
        if now >= self._next_check:
            self._next_check = now + CHECK_PERIOD_S
            self._check(now)

    def _cycle_done(self) -> None:
        self.cycle_count += 1
        # Messages are built and published by the reporter, while the next cycle's bytes are
        # on the wire, instead of adding to every cycle.
        with self._report_cond:
            self._report_due = True
            self._report_cond.notify()
        if self.cycle_count == OFFLINE_AFTER_FAILURES + 1:
            self._report_missing()

    def _check(self, now: float) -> None:
        """Once per CHECK_PERIOD_S: the cycle rate and the duplicate-id judgement (S24)."""
        cycles = self._cycles
        if self._rate_mark is not None and now > self._rate_mark[0]:
            count = self.cycle_count - self._rate_mark[1]
            self.cycle_rate_hz = count / (now - self._rate_mark[0])
            rate = self.config.publish_rate_hz
            # Behind for good: most cycles started late and the rate fell short of the goal.
            if count and 2 * cycles.late >= count and self.cycle_rate_hz < 0.9 * rate and \
                    not cycles.behind_logged:
                cycles.behind_logged = True
                self.log_warning(
                    f'the bus cannot keep up with publish_rate_hz {rate:g} ({len(self._servos)} '
                    f'servos at {self.config.baud} baud): publishing as fast as it reads '
                    f'({self.cycle_rate_hz:.0f} Hz)')
        cycles.late = 0
        self._rate_mark = (now, self.cycle_count)
        bus = self.bus
        for s in self._servos:
            mark, s.surplus_mark = s.surplus_mark, bus.surplus_replies(s.id)
            surplus = 0 if mark is None else s.surplus_mark - mark
            garble = bus.garble_level[s.id]
            if surplus < DUPLICATE_SURPLUS and garble < DUPLICATE_GARBLE_LEVEL:
                continue
            if now >= s.duplicate_until:
                sign = (f'{surplus} replies more than requests' if surplus >= DUPLICATE_SURPLUS
                        else f'{garble:.0%} of its replies garbled')
                self.log_error(
                    f'{s.name} (id {s.id}): {sign}: two servos answer to id {s.id}; their '
                    'replies collide and its readings cannot be trusted. Connect them one at a '
                    'time and give each its own id with ~/set_id')
                self._changed()
            s.duplicate_until = now + DUPLICATE_HOLD_S

    def _report_missing(self) -> None:
        missing = [s for s in self._servos if not s.seen]
        if not missing or not self.bus.connected:
            return
        listed = few(f'{s.name} (id {s.id})' for s in missing)
        if len(missing) == len(self._servos):
            self.log_warning(f'no servo answers on {self.config.port}: {self._silence_hint()}')
        else:
            self.log_warning(
                f'servo(s) {listed} do not answer on {self.config.port}: check their ids with '
                'the ~/scan service, their power and wiring')

    def _silence_hint(self) -> str:
        stats = self.bus.link.stats
        baud = self.config.baud
        if stats.bytes_in and not self.bus.decoder.frames_decoded:
            return (f'{stats.bytes_in} bytes received but not one valid reply (wrong baud '
                    f'rate?): check the baud parameter ({baud}) against the servos\' baud rate')
        return ('no reply at all: check power and wiring, the servo ids (try ~/scan) and the '
                f'baud parameter ({baud}): at a wrong baud rate servos stay silent')

    # -- reporting ------------------------------------------------------------------------------

    def _report(self) -> None:
        if self._on_cycle is None:
            return
        try:
            self._on_cycle(self.snapshot())
        except Exception as exc:  # noqa: BLE001 - e.g. the context is shutting down
            if self._running:
                self.log_warning(f'publishing failed: {exc!r}', every_s=5.0, key='report')

    def _reporter_main(self) -> None:
        while self._running:
            with self._report_cond:
                if not self._report_due:
                    self._report_cond.wait(0.5)
                due, self._report_due = self._report_due, False
            if due and self._running:
                self._report()

    def _on_latency(self, report: LatencyReport) -> None:
        # Reader thread, on every (re)open: say what was found and done once, and again only
        # when it changes (another adapter after a replug).
        text = report.summary()
        if text != self._latency_logged:
            self._latency_logged = text
            if report.kind == 'ftdi' and not report.ok:
                self.log_warning(f'serial port latency: {text}')
            else:
                self.log_info(f'serial port latency: {text}')
        self._changed()

    def _on_connection(self, up: bool, reason: str) -> None:
        # Reader thread: only flags here, never a transaction.
        for s in self._servos:
            if up:
                # Re-probe at full rate at once: the servos were most likely fine all along.
                s.failures = min(s.failures, OFFLINE_AFTER_FAILURES - 1)
                s.next_probe = -math.inf
            else:
                s.online = False
        self._changed()

    # -- commands (the hot path of ~/command) ---------------------------------------------------

    def command(self, names: Sequence[str], ids: Sequence[int], positions: Sequence[float],
                move_time_ms: int) -> Result:
        """Queue a move; the newest target of each servo wins. Refusals send nothing."""
        try:
            targets = self._resolve(names, ids, positions, move_time_ms)
        except ValueError as exc:
            return Result(False, clip(str(exc)))
        except Exception as exc:  # noqa: BLE001 - no input may cost the node
            self.log_error(f'command failed:\n{traceback.format_exc()}')
            return Result(False, f'internal error: {exc!r}')
        with self._cmd_cond:
            self.commands_received += 1
            for servo_id, ticks, ms in targets:
                if servo_id in self._pending:
                    self.commands_superseded += 1
                    del self._pending[servo_id]  # re-inserted last: the newest order
                self._pending[servo_id] = (ticks, ms)
            # While the read chain runs, a due command is handed to it on this thread and goes
            # out at the next READ boundary; otherwise the command thread sends it.
            if not (self._command_due() and self._post_pending()):
                self._cmd_cond.notify()
        return Result(True, f'{len(targets)} target(s) queued')

    def _command_due(self) -> bool:
        """Whether the next command frame may go now (``_cmd_cond`` held).

        Not before the last one handed to the read chain has left the line; then as the bus
        budget allows (see COMMAND_SPACING).
        """
        last = self._last_post
        if last is not None:
            if not last.done:
                return False
            self._last_post = None
            self._charge(last.written_at, last.size)
        return time.monotonic() >= self._command_free_at()

    def _command_free_at(self) -> float:
        """Return when the bus budget lets the next command batch go (``_cmd_cond`` held)."""
        return max(self._next_command_at, self._command_budget_at - self._command_tolerance)

    def _charge(self, ended_at: float, size: int) -> None:
        """Charge a batch of `size` bytes that left the line at `ended_at` (``_cmd_cond`` held)."""
        wire = wire_time(size, self.config.baud)
        cost = wire * (1.0 + COMMAND_SPACING)
        self._command_budget_at = max(self._command_budget_at, ended_at - wire) + cost
        self._command_tolerance = COMMAND_BURST * cost
        self._next_command_at = ended_at + COMMAND_CYCLE_SHARE / self.config.publish_rate_hz

    def _post_pending(self) -> bool:
        """Hand the pending targets to the running read chain (``_cmd_cond`` held)."""
        frames = sync_write_frames([(i, t, ms) for i, (t, ms) in self._pending.items()])
        posted = self.bus.post(frames)
        if posted is None:
            return False
        self._last_post = posted
        self._pending = {}
        self._commands_sent(frames)
        return True

    def _commands_sent(self, frames: Sequence[bytes]) -> None:
        """Count command frames (``_cmd_cond`` held)."""
        self.command_frames_sent += len(frames)

    def _resolve(self, names: Sequence[str], ids: Sequence[int], positions: Sequence[float],
                 move_time_ms: int) -> List[Target]:
        return resolve_targets(self.servos, self.units, names, ids, positions, move_time_ms,
                               self.config.default_move_time_ms)

    def _commander_main(self) -> None:
        while self._running:
            in_flight = None
            with self._cmd_cond:
                while self._running and not (self._pending and self._command_due()):
                    if self._pending and self._last_post is not None:
                        in_flight = self._last_post
                        break
                    wait = (0.5 if not self._pending
                            else self._command_free_at() - time.monotonic())
                    self._cmd_cond.wait(max(0.0005, min(0.5, wait)))
                if not self._running:
                    return
                if in_flight is None:
                    if self._post_pending():
                        continue
                    targets = [(i, t, ms) for i, (t, ms) in self._pending.items()]
                    self._pending = {}
            if in_flight is not None:
                # The frames handed to the read chain are not out yet; the reader thread
                # settles them. Waited for outside the lock: it takes the post lock meanwhile.
                in_flight.event.wait(0.1)
                continue
            try:
                frames = self.bus.sync_write_positions(targets, PRIORITY_SERVICE, wait=False)
                with self._cmd_cond:
                    self._commands_sent(frames)
                    self._charge(time.monotonic(), sum(map(len, frames)))
            except LinkError as exc:
                self.log_warning(f'~/command not sent: {exc}', every_s=5.0, key='cmd-link')
            except Exception:  # noqa: BLE001 - the command thread must not die
                self.log_error(f'~/command failed:\n{traceback.format_exc()}', every_s=5.0,
                               key='cmd-bug')

    def _drop_pending(self, ids: Optional[Sequence[int]] = None) -> None:
        with self._cmd_cond:
            if ids is None:
                self._pending = {}
            else:
                for servo_id in ids:
                    self._pending.pop(servo_id, None)

    # -- services -------------------------------------------------------------------------------

    @_service
    def write_positions(self, names: Sequence[str], ids: Sequence[int],
                        positions: Sequence[float], move_time_ms: int,
                        staged: bool) -> Result:
        """Move servos now: one SYNC WRITE, or REG WRITE each then ACTION (staged)."""
        targets = self._resolve(names, ids, positions, move_time_ms)
        # A queued ~/command for these servos is older than this call: it must not follow it.
        self._drop_pending([t[0] for t in targets])
        if not staged:
            self.bus.sync_write_positions(targets)
            return Result(True, f'SYNC WRITE sent to {len(targets)} servo(s)')
        for servo_id, ticks, ms in targets:
            try:
                self.bus.reg_write(servo_id, proto.TARGET_POSITION_ADDRESS,
                                   proto.encode_position_payload(ticks, ms))
            except LinkTimeout:
                return Result(False, f'servo {servo_id} did not acknowledge its REG WRITE; '
                                     'ACTION not sent, nothing moved')
        self.bus.action()
        return Result(True, f'REG WRITE to {len(targets)} servo(s), then ACTION')

    @_service
    def set_torque(self, ids: Sequence[int], enable: bool) -> Result:
        """Switch torque of `ids` (empty = all), each verified by reading it back."""
        chosen = select(self.servos, ids)
        by_id = {s.id: s for s in self._servos}
        value = b'\x01' if enable else b'\x00'
        failed = []
        for joint in chosen:
            who = f'{joint.name} (id {joint.id})'
            try:
                self.bus.write(joint.id, TORQUE.address, value)
                back = self.bus.read(joint.id, TORQUE.address, TORQUE.size).params[0] != 0
            except LinkTimeout:
                failed.append(f'{who} did not answer')
                continue
            if joint.id in by_id:
                by_id[joint.id].set_torque(back)
            if back != enable:
                failed.append(f'{who} reads back torque {"on" if back else "off"}')
        state = 'on' if enable else 'off'
        if failed:
            return Result(False, f'torque {state}: ' + few(failed, 3))
        return Result(True, f'torque {state} for {len(chosen)} servo(s), verified by read-back')

    @_service
    def emergency_stop(self) -> Result:
        """Torque off, every servo at once (one broadcast); queued commands are dropped."""
        self._drop_pending()
        self.bus.discard_posted()
        self.bus.write(proto.BROADCAST_ID, TORQUE.address, b'\x00', PRIORITY_URGENT)
        for s in self._servos:
            s.set_torque(False)
        self.log_warning('emergency stop: torque off broadcast to every servo')
        return Result(True, 'torque off broadcast to every servo (id 254)')

    @_service
    def read_register(self, servo_id: int, register_name: str, address: int,
                      length: int) -> Result:
        """Read a register by name, or `length` bytes at `address`."""
        if not proto.is_servo_id(servo_id):
            raise ValueError(f'id must be 1..250 (READ cannot be broadcast), got {servo_id}')
        if register_name:
            reg = by_name(register_name)
            if not reg.readable:
                raise ValueError(f'{reg.name} is a command register (write only); '
                                 'nothing to read')
            address, length = reg.address, reg.size
        else:
            if not 1 <= length <= proto.MAX_READ_LENGTH or address + length > 256:
                raise ValueError(f'length must be 1..{proto.MAX_READ_LENGTH} and address + '
                                 f'length <= 256, got address 0x{address:02X} length {length}')
            try:
                reg = by_address(address)
                if reg.size != length or not reg.readable:
                    reg = None
            except RegisterError:
                reg = None
        reply = self.bus.read(servo_id, address, length)
        data = bytes(reply.params)
        if reg is not None:
            value = decode_value(reg, data)
            number = int.from_bytes(data, 'big', signed=reg.signed)
            text = value if isinstance(value, str) else f'{value} {reg.unit}'.strip()
            label = reg.name
        else:
            number = int.from_bytes(data, 'big') if length <= 8 else 0
            block = decode_block(address, data)
            text = ', '.join(f'{k}={v}' for k, v in block.items()) or data.hex(' ')
            label = f'{length} byte(s) at 0x{address:02X}'
        faults = proto.describe_status(reply.status)
        message = f'servo {servo_id} {label}: {text}' + (
            f' (status: {", ".join(faults)})' if faults else '')
        return Result(True, message, {'value': number, 'text': text, 'data': list(data),
                                      'status': reply.status})

    @_service
    def write_register(self, servo_id: int, register_name: str, value: int) -> Result:
        """Write a register by name (typed, range-checked); a unicast write is read back."""
        if not (proto.is_servo_id(servo_id) or servo_id == proto.BROADCAST_ID):
            raise ValueError(f'id must be 1..250 or 254 (broadcast), got {servo_id}')
        reg = by_name(register_name)
        if reg.name == ID.name:
            raise ValueError('change ids with ~/set_id (it checks the new id is free)')
        data = encode_value(reg, None if reg.address_only else int(value))
        self.bus.write(servo_id, reg.address, data)
        if servo_id == proto.BROADCAST_ID:
            return Result(True, f'{reg.name} written to every servo (broadcast, no reply)')
        if reg.address_only or not reg.readable:
            return Result(True, f'servo {servo_id} acknowledged {reg.name}')
        back = decode_value(reg, bytes(self.bus.read(servo_id, reg.address, reg.size).params))
        if reg is TORQUE:
            for s in self._servos:
                if s.id == servo_id:
                    s.set_torque(bool(back))
        ok = back == value
        return Result(ok, f'servo {servo_id} {reg.name} = {back} {reg.unit}'.strip() + (
            '' if ok else f' after writing {value} (the servo did not take it)'))

    @_service
    def scan(self, first_id: int, last_id: int) -> Result:
        """PING ids `first_id`..`last_id`; report who answers, firmware, and shared ids."""
        if not (proto.is_servo_id(first_id) and proto.is_servo_id(last_id)
                and first_id <= last_id):
            raise ValueError(f'need 1 <= first_id <= last_id <= 250, got {first_id}..{last_id}')
        with self._loop_paused():
            found = self.bus.scan(range(first_id, last_id + 1))
            shared = [i for i in found
                      if self._how_many_answer(i, values_differ=False)[0] == 'several']
            versions = []
            for servo_id in found:
                try:
                    data = bytes(self.bus.read(servo_id, FIRMWARE.address, FIRMWARE.size,
                                               retries=0 if servo_id in shared else None).params)
                    versions.append(str(decode_value(FIRMWARE, data)))
                except LinkTimeout:
                    versions.append('')
        message = (f'found {len(found)} servo(s) in {first_id}..{last_id}: '
                   + few((f'{i} ({v or "?"})' for i, v in zip(found, versions)), 20))
        if shared:
            message += (f'; more than one servo answers to id(s) {few(shared)}: connect them '
                        'one at a time and give each its own id')
        slow = [i for i in found if self.bus.margin_for(i) > self.bus.margin_s]
        if slow:
            message += (f'; id(s) {few(slow)} answer late: the driver waits up to '
                        f'{max(self.bus.margin_for(i) for i in slow) * 1000:.0f} ms for them')
        return Result(True, message, {'ids': found, 'firmware_versions': versions})

    @_service
    def go_to_preset(self, ids: Sequence[int], preset: int) -> Result:
        """Run servos to their stored preset position 1..3 (address-only WRITE)."""
        if not 1 <= preset <= len(RUN_PRESETS):
            raise ValueError(f'preset must be 1..3, got {preset}')
        chosen = select(self.servos, ids)
        failed = []
        for joint in chosen:
            try:
                self.bus.write(joint.id, RUN_PRESETS[preset - 1].address)
            except LinkTimeout:
                failed.append(f'{joint.name} (id {joint.id})')
        if failed:
            return Result(False, f'no acknowledgement from {few(failed)}')
        return Result(True, f'{len(chosen)} servo(s) running to preset {preset}')

    def _answers(self, servo_id: int) -> str:
        """PING up to twice: 'yes', 'garbled' (something answers, not cleanly) or 'no'."""
        garbled = False
        for _ in range(2):
            reply, mangled = self.bus.probe(proto.encode_ping(servo_id), servo_id, 0)
            if reply is not None:
                return 'yes'
            garbled = garbled or mangled
        return 'garbled' if garbled else 'no'

    def _how_many_answer(self, servo_id: int, values_differ: bool = True) -> Tuple[str, str]:
        """Return ('none' | 'one' | 'several', why): READs the present position a few times.

        Two servos at one id either collide (garbled replies, S24) or, on a bus that keeps their
        replies apart, answer twice; their positions also rarely agree (`values_differ`: count
        that as a sign too, at the price of a moving servo looking like two).
        """
        surplus = self.bus.surplus_replies(servo_id)
        frame = proto.encode_read(servo_id, POSITION.address, POSITION.size)
        # A second whole reply follows the first at once; give it time to arrive before the
        # next request flushes the input.
        quiet = wire_time(2 * (POSITION.size + 6), self.config.baud) + 0.003
        values, garbled = [], 0
        for _ in range(PROBE_READS):
            reply, mangled = self.bus.probe(frame, servo_id, POSITION.size)
            if reply is not None:
                values.append(int.from_bytes(reply.params, 'big'))
                time.sleep(quiet)
            elif mangled:
                garbled += 1
        extra = self.bus.surplus_replies(servo_id) - surplus
        if garbled:
            return 'several', f'{garbled} of {PROBE_READS} replies garbled (colliding replies)'
        if extra > 0:
            return 'several', f'{extra} replies more than requests'
        if values_differ and len(set(values)) > 1:
            return 'several', (f'its present position read {few(sorted(set(values)))}: two '
                               'servos, or one that is moving (stop it first)')
        return ('one', '') if values else ('none', '')

    @_service
    def set_id(self, old: int, new: int) -> Result:
        """Give the servo at `old` the id `new`, if exactly one servo answers at `old`."""
        if not (proto.is_servo_id(old) and proto.is_servo_id(new)):
            raise ValueError(f'id and new_id must be 1..250, got {old} -> {new}')
        if old == new:
            raise ValueError(f'servo already has id {new}')
        owner = next((s for s in self._servos if s.id == new), None)
        if owner is not None:
            state = 'online' if owner.online else 'offline'
            raise ValueError(
                f'id {new} belongs to joint {owner.name} (servo_ids; it is {state}): two '
                'joints would share it. Pick an id not in servo_ids; to move a servo onto a '
                'configured id, run the driver without that id in servo_ids first')
        with self._loop_paused():
            taken = self._answers(new)
            if taken != 'no':
                how = '' if taken == 'yes' else ' (with a garbled reply: more than one servo?)'
                raise ValueError(f'id {new} already answers on the bus{how}; pick a free id '
                                 '(~/scan)')
            count, why = self._how_many_answer(old)
            if count == 'none':
                return Result(False, f'servo {old} does not answer; nothing changed')
            if count == 'several':
                return Result(False, (
                    f'more than one servo answers at id {old} ({why}): a new id would go to '
                    'all of them. Disconnect or power off all but one, then try again; nothing '
                    'changed'))
            what = f'servo {old} now has id {new}'
            lost = self._send_unacknowledged(
                lambda: self.bus.write(old, ID.address, encode_value(ID, new)))
            try:
                if lost is not None and not self.bus.wait_connected(SETTLE_WAIT_S):
                    return _unknown(what, lost, f'~/scan tells (id {new} answers if it did)')
                if self._answers(new) != 'yes':
                    if lost is None:
                        return Result(False, f'servo {old} acknowledged but does not answer at '
                                             f'id {new}; check with ~/scan')
                    if self._answers(old) == 'yes':
                        return Result(False, f'servo {old} did not take id {new} ({lost}): it '
                                             f'still answers at id {old}; nothing changed')
                    return _unknown(what, lost, f'neither id {old} nor {new} answers now; '
                                                'check with ~/scan')
            except LinkError as exc:
                return _unknown(what, exc, f'~/scan tells (id {new} answers if it did)')
            self._rename(old, new)
        message = f'servo {old} now answers at id {new}' + (
            '' if lost is None else f' (its acknowledgement was lost: {lost})')
        self.log_info(message)
        return Result(True, message)

    def _send_unacknowledged(self, send: Callable[[], Any]) -> Optional[LinkError]:
        """Run `send`; return None if acknowledged, the error if its frame left without one.

        An error before the frame left (the port not open) is raised: nothing was sent.
        """
        try:
            send()
        except LinkError as exc:
            if not exc.sent:
                raise
            return exc
        return None

    def _rename(self, old: int, new: int) -> None:
        servos = []
        for s in self._servos:
            if s.id == old:
                name = f'servo_{new}' if s.name == f'servo_{old}' else s.name
                s = _Servo(Joint(new, name), s.index)
            servos.append(s)
        self._set_servos(tuple(servos))

    @_service
    def factory_reset(self, servo_id: int, confirm: str) -> Result:
        """RESET one servo to its factory registers (`confirm` must be ``RESET``)."""
        if confirm != 'RESET':
            raise ValueError('confirm must be exactly "RESET"; nothing sent')
        if not proto.is_servo_id(servo_id):
            raise ValueError(f'id must be 1..250 (RESET is never broadcast), got {servo_id}')
        what = f'servo {servo_id} reset to factory settings'
        with self._loop_paused():
            taken = servo_id != FACTORY_ID and self._answers(FACTORY_ID) != 'no'
            lost = self._send_unacknowledged(lambda: self.bus.reset(servo_id))
            try:
                if lost is not None and not self.bus.wait_connected(SETTLE_WAIT_S):
                    return _unknown(what, lost, f'~/scan tells (a reset servo answers at the '
                                                f'factory id {FACTORY_ID})')
                at_own = self._answers(servo_id) == 'yes'
                at_factory = 'no' if at_own else self._how_many_answer(FACTORY_ID)[0]
            except LinkError as exc:
                return _unknown(what, exc, '~/scan tells')
        if lost is not None:
            if at_own:
                # A servo that keeps its id on RESET (S23) or one that never got it: the bus
                # cannot tell them apart.
                return _unknown(what, lost, f'it still answers at id {servo_id}; read its '
                                            'registers with ~/read_register')
            if at_factory == 'none':
                return _unknown(what, lost, f'neither id {servo_id} nor the factory id '
                                            f'{FACTORY_ID} answers now; check with ~/scan')
            note = f' (its acknowledgement was lost: {lost})'
        else:
            note = ''
        if at_own:
            return Result(True, f'servo {servo_id} reset to factory settings (torque off)')
        give_back = (f'give it its id back with ~/set_id {FACTORY_ID} -> {servo_id}'
                     + (f' (this driver refuses that while servo_ids lists {servo_id}: run it '
                        f'without {servo_id} for the change)'
                        if servo_id in self._configured_ids else ''))
        if taken:
            owner = next((s.name for s in self._servos if s.id == FACTORY_ID), 'another servo')
            message = (f'servo {servo_id} reset to factory settings. WARNING: it now has the '
                       f'factory id {FACTORY_ID}, which {owner} already had: '
                       + ('more than one servo answers there' if at_factory == 'several' else
                          'check with ~/scan')
                       + f', and ~/set_id refuses an id more than one servo answers to. '
                       f'Disconnect {owner} (or power it off), then {give_back}')
            self.log_warning(message)
            return Result(True, message + note)
        if at_factory != 'none':
            return Result(True, f'servo {servo_id} reset to factory settings and now answers at '
                                f'the factory id {FACTORY_ID}; {give_back}{note}')
        return Result(True, f'servo {servo_id} acknowledged RESET but no longer answers')

    # -- health (diagnostics) -------------------------------------------------------------------

    def bus_health(self) -> Health:
        """Return the bus's diagnostic status: level, message, values."""
        now = self.clock()
        servos = self._servos
        online = sum(1 for s in servos if s.online)
        stats = self.bus.link.stats
        bus = self.bus
        values = [
            ('port', self.config.port), ('baud', self.config.baud),
            ('link', 'open' if bus.connected else (bus.link.last_error or 'not open')),
            ('online servos', f'{online}/{len(servos)}'),
            ('cycle rate [Hz]', f'{self.cycle_rate_hz:.1f}'),
            ('publish_rate_hz', f'{self.config.publish_rate_hz:g}'),
            ('transactions', bus.transactions), ('failed transactions', bus.failed_transactions),
            ('timeouts', stats.timeouts), ('retries', stats.retries),
            ('checksum errors', bus.checksum_errors),
            ('unexpected frames', bus.unexpected_frames),
            ('garbled replies', sum(bus.garbled_by_id)),
            ('reconnects', stats.reconnects),
            ('bytes in', stats.bytes_in), ('bytes out', stats.bytes_out),
            ('commands', self.commands_received),
            ('commands superseded', self.commands_superseded),
            ('read loop restarts', self._loop_failures)] + self._latency_values()
        level, message = self._bus_problem(now)
        if level == OK:
            duplicates = [s for s in servos if now < s.duplicate_until]
            offline = [s for s in servos if not s.online]
            if duplicates:
                level, message = ERROR, (f'more than one servo answers to id(s) '
                                         f'{few(s.id for s in duplicates)}: give each servo its '
                                         'own id (~/set_id)')
            elif offline:
                level, message = WARN, (f'{online}/{len(servos)} servos online; offline: '
                                        + few(f'{s.name} (id {s.id})' for s in offline))
            else:
                message = f'{online}/{len(servos)} servos online'
        return Health(level, message, values)

    def _latency_values(self) -> List[Tuple[str, Any]]:
        """Return the port's latency timer and the reply margin as diagnostic values."""
        bus = self.bus
        report = bus.latency
        margin = f'{bus.margin_s * 1000:.1f}'
        if self.config.response_timeout_ms > 0:
            margin += ' (response_timeout_ms)'
        if report is None:
            return [('latency timer', 'port not opened yet'), ('reply margin [ms]', margin)]

        def ms(value: Optional[int]) -> str:
            return 'none' if value is None else str(value)
        return [('latency timer before [ms]', ms(report.before_ms)),
                ('latency timer after [ms]', ms(report.after_ms)),
                ('latency timer action', report.action),
                ('reply margin [ms]', margin),
                ('udev rule', report.udev_rule() or 'not needed')]

    def _bus_problem(self, now: float) -> Tuple[int, str]:
        loop = self._loop
        if self._running and loop is not None and not loop.is_alive():
            return ERROR, f'read loop stopped: {self._loop_failure or "unknown reason"}'
        if now - self._loop_failed_at < LOOP_FAILURE_HOLD_S:
            return ERROR, (f'read loop failed ({self._loop_failure}); restarted '
                           f'{self._loop_failures} time(s)')
        link = self.bus.link
        if link.reader_error and not link.reader_alive and self._running:
            return ERROR, f'serial reader stopped: {link.reader_error}'
        if not self.bus.connected:
            if link.last_error:
                return ERROR, link.last_error
            if not link.stats.open_failures and not link.stats.reconnects:
                return WARN, f'opening {self.config.port}'
            return ERROR, f'{self.config.port} is not open'
        if not self._startup_done and self._scan_at_start:
            return WARN, 'scanning the bus for servos'
        servos = self._servos
        if servos and not any(s.online for s in servos) and \
                self.cycle_count > OFFLINE_AFTER_FAILURES:
            return ERROR, f'no servo answers: {self._silence_hint()}'
        return OK, ''

    def servo_health(self, servo_id: int) -> Health:
        """Return one servo's diagnostic status (STALE if it is no longer configured)."""
        s = next((x for x in self._servos if x.id == servo_id), None)
        if s is None:
            return Health(STALE, f'no servo {servo_id} configured any more', [])
        r, t = s.reading, s.telemetry
        values = [('id', s.id), ('online', s.online), ('position [ticks]', r.ticks),
                  ('position [rad]', f'{r.rad:.4f}'), ('current [mA]', t.current_ma),
                  ('temperature [degC]', t.temperature_c), ('status', f'0x{r.status:02X}'),
                  ('torque', t.torque_enabled), ('error count', s.error_count),
                  ('reply margin [ms]', f'{self.bus.margin_for(s.id) * 1000:.1f}')]
        who = f'{s.name} (id {s.id})'
        if self.clock() < s.duplicate_until:
            return Health(ERROR, f'{who}: duplicate id, more than one servo answers; give '
                                 'each its own id (~/set_id)', values)
        if not s.online:
            if self.bus.garble_level[s.id] >= GARBLE_HINT_LEVEL:
                return Health(ERROR, f'{who} offline: its replies come garbled, as when more '
                                     'than one servo answers to one id (or on a noisy line)',
                              values)
            return Health(ERROR, f'{who} offline: no reply ({s.error_count} failed '
                                 'transactions); check its power, cable and id (~/scan)', values)
        faults = fault_names(r.status)
        if faults:
            return Health(WARN, f'{who}: ' + ', '.join(faults), values)
        return Health(OK, 'ok', values)


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
