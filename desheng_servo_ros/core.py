"""The servo bus as a device: its servos, the read loop, commands and services. No ROS here.

:class:`ServoBusCore` owns the bus (:class:`~desheng_servo_ros.link.ServoBusLink`), the servo list
and what is known of each servo, and runs the rules on its threads. The rules of scheduling live
in ``schedule.py``, without I/O, thread, lock or clock (the read cycles and their pace, the
online/offline judgement, the coalesced commands and their share of the bus, what goes first at
a READ boundary, the set_id rule, the shutdown sequence): this module, ``read_cycles.py``,
``commands.py`` and ``link.py`` call them, and ``bus_schedule.py`` composes them into the state
machine the model test drives. The services are in ``services.py``, the diagnostics in
``health.py``, the types in ``state.py``. It reports through callbacks (``on_cycle(snapshot)``,
``on_change()``, ``on_servos()``) and takes a clock for everything that is planned in time. The
node (``node.py``) only translates. Decisions: ``docs/protocols.md``, "Driver decisions" of the
servo bus.

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
- **commander** (``_commander_main``, ``commands.py``): sends the newest pending command; the
  pending targets and the command budget (``_commands``, a ``schedule.CommandQueue``) are
  guarded by ``_cmd_cond``.
- **callers** (the node's executor threads): services and ``command()``. A service that needs
  a quiet bus or changes the servo list pauses the read loop first (``_pause`` and
  ``_loop_idle``, guarded by ``_pause_cond``).
- ``_servos`` is a tuple replaced in one assignment (start-up scan, ``set_id``, both with the
  loop paused); readers take it once. The duplicate-id bookkeeping is written by the reader
  thread at cycle starts only.
- The bus itself: one transaction at a time under the link's priority lock (emergency stop >
  commands and services > read loop), also between two attempts of a request; after the
  shutdown's torque off the link takes no transaction any more (``ServoBusLink.send_last``).
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import replace
import math
import threading
import time
import traceback
from typing import Any, Callable, Dict, Iterator, List, Optional, Tuple

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.commands import CommandPath
from desheng_servo_ros.health import BusHealth, LOOP_FAILURE_HOLD_S  # noqa: F401 - re-exported
from desheng_servo_ros.link import (BusBusy, LinkDown, LinkError, PRIORITY_LOOP, Posted,
                                    ServoBusLink)
from desheng_servo_ros.schedule import (  # noqa: F401 - the rules' constants, re-exported
    COMMAND_BURST, COMMAND_CYCLE_SHARE, COMMAND_SPACING, CommandQueue, EMPTY, judge_failure,
    judge_link, judge_reply, NOT_DUE, OFFLINE_AFTER_FAILURES, plan_cycle, plan_telemetry,
    ReadSchedule,    REPROBE_PERIOD_S, shutdown_frames, sync_write_frames)
from desheng_servo_ros.read_cycles import _OneCycle, ReadCycles
from desheng_servo_ros.services import PROBE_READS, ServoServices  # noqa: F401
from desheng_servo_ros.state import (  # noqa: F401 - the driver's types, re-exported
    ALL_IDS, BusSnapshot, ERROR, Health, new_tuple, OK, READ_STATE, READ_WIDE, Reading, Result,
    S_CURRENT, ServoBusConfig, ServoRecord, ServoSnapshot, STALE, Telemetry, TORQUE,
    W_TEMPERATURE, WARN, fault_names)
from desheng_servo_ros.units import Joint, servo_list, Units
from uav_serial_common.logs import log_at, Throttle
from uav_serial_common.text import clip, few
from uav_serial_common.usb_latency import LatencyReport

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
# A failed read loop restarts after a pause that grows up to LOOP_BACKOFF_MAX_S.
LOOP_BACKOFF_MAX_S = 1.0


class ServoBusCore(CommandPath, ServoServices, BusHealth):
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
        self._servos: Tuple[ServoRecord, ...] = tuple(ServoRecord(j, k)
                                                      for k, j in enumerate(joints))
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
            period_s=1.0 / config.publish_rate_hz,
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
        self._commands = CommandQueue()  # guarded by _cmd_cond
        self._last_post: Optional[Posted] = None
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
        self._drop_pending()
        self.bus.discard_posted()
        try:
            frames = shutdown_frames(self.config.torque_off_on_shutdown)
            if frames:
                if not self.bus.port_open:
                    # Said, not silently skipped: the servos may still hold their torque.
                    raise LinkDown(f'{self.config.port} is not open '
                                   f'({self.bus.link.last_error or "not connected"})')
                # The last frames: the bus takes none after them (a service still running
                # gets LinkDown), so torque off is the last frame of a shutdown.
                self.bus.send_last(frames)
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
            self._cycles.schedule.period_s = 1.0 / runtime['publish_rate_hz']
        if 'response_timeout_ms' in runtime:
            self.bus.response_timeout_ms = runtime['response_timeout_ms']
        if 'max_retries' in runtime:
            self.bus.max_retries = self._cycles.schedule.retries = runtime['max_retries']

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
            out.append(new_tuple(ServoSnapshot, (
                s.id, s.name, s.online, s.seen, r.ticks, r.rad, r.speed_raw, r.velocity,
                t.current_ma, t.temperature_c, r.status, t.torque_enabled, s.error_count,
                now < s.duplicate_until, r.at)))
        return BusSnapshot(self.bus.port_open, tuple(out),
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

    def _wait_port_open(self) -> bool:
        while self._running:
            if self.bus.wait_port_open(0.1):
                return True
        return False

    def _startup(self) -> None:
        while self._scan_at_start and self._running:
            if not self._wait_port_open():
                return
            self.log_info('servo_ids is empty: scanning ids 1..250')
            try:
                found = self.bus.scan(ALL_IDS, priority=PRIORITY_LOOP)
            except LinkError as exc:
                self.log_warning(f'scan interrupted: {exc}')
                continue
            if found:
                self._set_servos(tuple(ServoRecord(j, k) for k, j in enumerate(servo_list(found))))
                self._scan_at_start = False
                self.log_info(f'found servos {found}')
                break
            self.log_error(
                f'no servo answers on {self.config.port} at {self.config.baud} baud: check '
                'power, wiring and the baud parameter; scanning again in '
                f'{SCAN_RETRY_S:.0f} s')
            self._sleep(SCAN_RETRY_S, until_pause=False)
        if self.config.torque_on_start and self._wait_port_open():
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
            if not self.bus.port_open:
                # Keep servo_states (all offline) and diagnostics coming while the port is away,
                # at the publish rate, and look at the port often enough for a prompt shutdown.
                now = self.clock()
                if now >= self._offline_report_at:
                    self._report()
                    self._offline_report_at = now + 1.0 / self.config.publish_rate_hz
                self.bus.wait_port_open(min(0.1, 1.0 / self.config.publish_rate_hz))
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
        cycles.schedule.next_cycle = min(cycles.next_cycle, self.clock())
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

    def _set_servos(self, servos: Tuple[ServoRecord, ...]) -> None:
        self._servos = servos  # one assignment: readers see the old or the new tuple
        self._cycles.reset()
        if self._on_servos is not None:
            try:
                self._on_servos()
            except Exception:  # noqa: BLE001
                self.log_error(f'servo list handler failed:\n{traceback.format_exc()}')
        self._changed()

    # -- the hot path (link reader thread) ------------------------------------------------------

    def _on_read(self, s: ServoRecord, kind: int, started: float,
                 reply: Optional[proto.Reply]) -> None:
        """Take the result of one READ of the cycle that started at `started`."""
        if reply is None:
            self._failed(s, started)
            return
        p = reply.params
        if kind == READ_STATE:
            s.telemetry = s.telemetry._replace(current_ma=float((p[S_CURRENT] << 8)
                                                                | p[S_CURRENT + 1]),
                                               torque_enabled=p[0] != 0)
            if s.failures:
                s.failures = 0
            return
        if kind == READ_WIDE:
            plan_telemetry(s, started, self.config.telemetry_period_s, len(self._servos))
            s.telemetry = s.telemetry._replace(temperature_c=float(p[W_TEMPERATURE]))
        self._update_position(s, (p[0] << 8) | p[1], (p[2] << 8) | p[3], reply.status)

    def _update_position(self, s: ServoRecord, ticks: int, speed: int, status: int) -> None:
        old = s.reading
        if ticks != old.ticks and s.seen:
            s.direction = 1.0 if ticks > old.ticks else -1.0
        rpt = self._rad_per_tick
        # Stamped with the reply's arrival: the reader thread took it off the port just now.
        s.reading = new_tuple(Reading, (ticks, (ticks - self._zero_tick) * rpt, speed,
                                        s.direction * speed * rpt if speed else 0.0, status,
                                        self._link.last_rx_time))
        changed = status != old.status or not s.online
        if judge_reply(s):
            self.log_info(f'{s.name} (id {s.id}) is back online')
        if changed:
            self._changed()

    def _failed(self, s: ServoRecord, now: float) -> None:
        if judge_failure(s, now):
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
        schedule = cycles.schedule
        if self._rate_mark is not None and now > self._rate_mark[0]:
            count = self.cycle_count - self._rate_mark[1]
            self.cycle_rate_hz = count / (now - self._rate_mark[0])
            rate = self.config.publish_rate_hz
            # Behind for good: most cycles started late and the rate fell short of the goal.
            if count and 2 * schedule.late >= count and self.cycle_rate_hz < 0.9 * rate and \
                    not cycles.behind_logged:
                cycles.behind_logged = True
                self.log_warning(
                    f'the bus cannot keep up with publish_rate_hz {rate:g} ({len(self._servos)} '
                    f'servos at {self.config.baud} baud): publishing as fast as it reads '
                    f'({self.cycle_rate_hz:.0f} Hz)')
        schedule.late = 0
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
        if not missing or not self.bus.port_open:
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
        judge_link(self._servos, up)
        self._changed()
