"""The servo bus as a device: its servos, the read loop, commands and services. No ROS here.

:class:`ServoBusCore` owns the bus and what is known of each servo. Every decision of the bus
is the schedule's (``bus_schedule.BusSchedule``: the read cycles and their pace, the
online/offline judgement, the coalesced commands and their share of the bus, what goes first at
a READ boundary, an emergency stop, the services' transactions and holds, the shutdown's torque
off), the same state machine the model test searches; ``bus_runtime.BusRuntime`` steps it on the
port (``link.ServoBusLink``: the port, its counters and margins, the services' blocking
requests). This module takes what the reads bring (``ReadDone``: the values; ``CycleDone``:
publish, the duplicate-id check) and adds the start-up procedure. The services are in
``services.py``, the diagnostics in ``health.py``, the types in ``state.py``. It reports through
callbacks (``on_cycle(snapshot)``, ``on_change()``, ``on_servos()``) and takes a clock for the
read loop's pace. The node (``node.py``) only translates. Decisions: ``docs/protocols.md``,
"Driver decisions" of the servo bus.

Threads (who steps the schedule; one step at a time under the runtime's lock):

- the **link reader thread**: each reply (the next READ leaves from it at once), the port
  opening or closing; its ``ReadDone`` handler writes the servo's values (a servo's
  ``reading`` and ``telemetry`` are immutable tuples replaced in one assignment, so a snapshot
  never mixes two replies), and after the lock is let go its ``CycleDone`` handler publishes;
- the runtime's **timer**: deadlines, the next cycle, a command the budget holds back, and
  the reports while the port is away;
- **callers** (the node's executor threads): ``command()`` and the services, each a call
  answered by the schedule and waited on with a timeout; a service that needs a quiet bus
  holds the read loop (``runtime.held``);
- **start-up** (``_startup``, a thread that ends): the start-up scan and torque on, with the
  read loop held from the start.

``_servos`` is the schedule's tuple, replaced in one assignment under the step lock (start-up
scan, ``set_id``, both with the read loop held); readers take it once.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import replace
import math
import threading
import time
import traceback
from typing import Any, Callable, Dict, Iterator, Optional, Tuple

from desheng_servo_ros.bus_runtime import BusRuntime
from desheng_servo_ros.bus_schedule import CycleDone, ReadDone
from desheng_servo_ros.commands import CommandPath
from desheng_servo_ros.health import BusHealth, LOOP_FAILURE_HOLD_S  # noqa: F401 - re-exported
from desheng_servo_ros.link import LinkError, ServoBusLink
from desheng_servo_ros.schedule import (  # noqa: F401 - the rules' constants, re-exported
    COMMAND_BURST, COMMAND_CYCLE_SHARE, COMMAND_SPACING, CommandQueue, OFFLINE_AFTER_FAILURES,
    REPROBE_PERIOD_S, shutdown_frames, sync_write_frames)
from desheng_servo_ros.services import ServoServices
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
        self._configured_ids = frozenset(config.servo_ids)
        self._scan_at_start = not joints
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
        self.runtime = BusRuntime(config.port, config.baud, joints,
                                  publish_rate_hz=config.publish_rate_hz,
                                  telemetry_period_s=config.telemetry_period_s,
                                  max_retries=config.max_retries,
                                  torque_off_on_shutdown=config.torque_off_on_shutdown,
                                  clock=clock, on_read=self._on_read, on_cycle=self._cycle_done,
                                  on_log=self._on_log, on_failure=self._loop_failed,
                                  on_idle=self._idle, bus=self.bus, logger=logger)
        self._schedule = self.runtime.schedule
        self._index: Tuple[Tuple[ServoRecord, ...], Dict[int, ServoRecord]] = ((), {})
        self._latency_logged = ''
        self._running = False
        self._startup_done = False
        self._reads_hold: Any = None  # the read loop's hold from the start (start-up, tests)
        self._startup_thread: Optional[threading.Thread] = None
        self._wake = threading.Event()  # the start-up's waits end at the shutdown
        self.cycle_count = 0
        self.cycle_rate_hz = 0.0
        self.behind_logged = False
        self._rate_mark: Optional[Tuple[float, int]] = None
        self._next_check = -math.inf
        self._loop_failures = 0
        self._loop_failure = ''
        self._loop_failed_at = -math.inf
        self._loop: Optional[threading.Thread] = None  # no read-loop thread: the runtime reads

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self, read_loop: bool = True) -> None:
        """Open the port and start reading (without the read loop: tests call read_cycle).

        The read loop is held from the start: by the start-up procedure (a scan when servo_ids
        is empty, torque on), or, without the read loop, for good (read_cycle runs one cycle).
        """
        self._running = True
        self._reads_hold = self.runtime.hold_reads()
        self.runtime.start()
        if read_loop:
            self._startup_thread = threading.Thread(target=self._startup_main,
                                                    name='servo-startup', daemon=True)
            self._startup_thread.start()

    def stop(self) -> None:
        """Stop reading, broadcast torque off as the last frame (if configured), close."""
        self._running = False
        self._wake.set()
        port_open = self.bus.port_open
        frames = self.runtime.stop()
        if shutdown_frames(self.config.torque_off_on_shutdown) and not frames:
            # Said, not silently skipped: the servos may still hold their torque.
            reason = (f'{self.config.port} is not open '
                      f'({self.bus.link.last_error or "not connected"})' if not port_open
                      else 'the port closed')
            self.log_error(f'torque off on shutdown NOT sent: {reason}; servos that had '
                           'torque on still hold it')
        if self._startup_thread is not None:
            self._startup_thread.join(2.0)

    def update_config(self, changes: Dict[str, Any]) -> None:
        """Apply runtime parameter changes (the others are refused before they get here)."""
        runtime = {k: v for k, v in changes.items() if k in ServoBusConfig.RUNTIME}
        self.config = replace(self.config, **runtime)
        schedule = self._schedule
        with self.runtime.locked():
            if 'publish_rate_hz' in runtime:
                self.behind_logged = False
                schedule.rate_hz = runtime['publish_rate_hz']
                schedule.reads.period_s = 1.0 / runtime['publish_rate_hz']
            if 'telemetry_period_s' in runtime:
                schedule.telemetry_period_s = runtime['telemetry_period_s']
            if 'response_timeout_ms' in runtime:
                self.bus.response_timeout_ms = runtime['response_timeout_ms']
                schedule.margin_s = self.bus.margin_s
            if 'max_retries' in runtime:
                self.bus.max_retries = schedule.max_retries = schedule.reads.retries = \
                    runtime['max_retries']
            if 'torque_off_on_shutdown' in runtime:
                schedule.torque_off_on_shutdown = runtime['torque_off_on_shutdown']

    @property
    def _servos(self) -> Tuple[ServoRecord, ...]:
        """The servo records, the schedule's (one tuple, replaced in one assignment)."""
        return self._schedule.servos

    @property
    def _commands(self) -> CommandQueue:
        """The pending commands and their budget, the schedule's."""
        return self._schedule.commands

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

    # -- start-up and the read loop ------------------------------------------------------------

    def _wait_port_open(self) -> bool:
        while self._running:
            if self.bus.wait_port_open(0.1):
                return True
        return False

    def _startup_main(self) -> None:
        """Start-up scan and torque on, with the read loop held; then the read loop goes."""
        try:
            while self._running:
                try:
                    self._startup()
                    break
                except Exception as exc:  # noqa: BLE001 - never die, never silently
                    self._loop_failed(exc)
                    self._wake.wait(0.5)
        finally:
            hold, self._reads_hold = self._reads_hold, None
            if hold is not None:
                self.runtime.release(hold)

    def _startup(self) -> None:
        while self._scan_at_start and self._running:
            if not self._wait_port_open():
                return
            self.log_info('servo_ids is empty: scanning ids 1..250')
            try:
                found = self.bus.scan(ALL_IDS)
            except LinkError as exc:
                self.log_warning(f'scan interrupted: {exc}')
                continue
            if found:
                found = self._sweep_again(found)
                self._set_servos(tuple(ServoRecord(j, k) for k, j in enumerate(servo_list(found))))
                self._scan_at_start = False
                self.log_info(f'found servos {found}')
                break
            self.log_error(
                f'no servo answers on {self.config.port} at {self.config.baud} baud: check '
                'power, wiring and the baud parameter; scanning again in '
                f'{SCAN_RETRY_S:.0f} s')
            self._wake.wait(SCAN_RETRY_S)
        if self.config.torque_on_start and self._wait_port_open():
            for s in self._servos:
                try:
                    self.bus.write(s.id, TORQUE.address, b'\x01')
                    s.set_torque(True)
                except LinkError as exc:
                    self.log_warning(f'torque on at start: {s.name} (id {s.id}): {exc}')
        self._startup_done = True

    def _sweep_again(self, found: list) -> list:
        """Return the servos of a second sweep too: one sweep's miss would be for the whole run.

        A PING's reply lost on the line, or held by a stalled device past the sweep's listening,
        costs that servo only its first sweep; the start-up's servo list is not scanned again.
        """
        try:
            again = self.bus.scan(ALL_IDS)
        except LinkError as exc:
            self.log_warning(f'second sweep of the start-up scan interrupted: {exc}')
            return found
        missed = sorted(set(again) - set(found))
        if missed:
            self.log_warning(f'servos {missed} answered only the second sweep of the start-up '
                             'scan (a reply lost or late: check the wiring and the baud rate)')
        return sorted(set(found) | set(again))

    def read_cycle(self) -> BusSnapshot:
        """Run one read cycle now (the read loop held: start(read_loop=False)); the snapshot."""
        self.runtime.read_cycle()
        return self.snapshot()

    @contextmanager
    def _loop_paused(self) -> Iterator[None]:
        """Hold the read loop between two READs (scan, id change, reset)."""
        with self.runtime.held(PAUSE_TIMEOUT_S):
            yield

    def _set_servos(self, servos: Tuple[ServoRecord, ...]) -> None:
        with self.runtime.locked():
            self._schedule.servos = servos  # one assignment: readers see the old or the new
            self._schedule.reads.reset(self.clock())
        if self._on_servos is not None:
            try:
                self._on_servos()
            except Exception:  # noqa: BLE001
                self.log_error(f'servo list handler failed:\n{traceback.format_exc()}')
        self._changed()

    def _loop_failed(self, exc: BaseException) -> None:
        """Say and count a step of the bus (or the start-up) that raised; the bus goes on."""
        self._loop_failures += 1
        self._loop_failed_at = self.clock()
        text = f'{type(exc).__name__}: {exc}'
        detail = (':\n' + ''.join(traceback.format_exception(type(exc), exc, exc.__traceback__))
                  if text != self._loop_failure else '')
        self._loop_failure = text
        self.log_error(f'read loop failed ({text}); restarting it{detail}', every_s=5.0,
                       key='loop-failed')
        self._changed()

    # -- what the reads bring (the runtime's handlers) ------------------------------------------

    def _record(self, servo_id: int) -> Optional[ServoRecord]:
        servos = self._servos
        index = self._index
        if index[0] is not servos:
            index = self._index = (servos, {s.id: s for s in servos})
        return index[1].get(servo_id)

    def _on_read(self, done: ReadDone) -> None:
        """Take the values of one READ (the schedule judged the servo already)."""
        reply = done.reply
        s = self._record(done.servo_id)
        if reply is None or s is None:
            return
        p = reply.params
        if done.kind == READ_STATE:
            s.telemetry = s.telemetry._replace(current_ma=float((p[S_CURRENT] << 8)
                                                                | p[S_CURRENT + 1]),
                                               torque_enabled=p[0] != 0)
            return
        if done.kind == READ_WIDE:
            s.telemetry = s.telemetry._replace(temperature_c=float(p[W_TEMPERATURE]))
        self._update_position(s, (p[0] << 8) | p[1], (p[2] << 8) | p[3], reply.status, done.now)

    def _update_position(self, s: ServoRecord, ticks: int, speed: int, status: int,
                         at: float) -> None:
        old = s.reading
        if ticks != old.ticks and s.seen:
            s.direction = 1.0 if ticks > old.ticks else -1.0
        rpt = self._rad_per_tick
        # Stamped with the reply's arrival: the reader thread took it off the port then.
        s.reading = new_tuple(Reading, (ticks, (ticks - self._zero_tick) * rpt, speed,
                                        s.direction * speed * rpt if speed else 0.0, status, at))
        if status != old.status:
            self._changed()

    def _on_log(self, level: str, text: str) -> None:
        # The schedule's online judgement (offline, back online): said, and the status changed.
        self._emit(level, text)
        self._changed()

    def _cycle_done(self, done: CycleDone) -> None:
        """Take a complete cycle: the checks once per CHECK_PERIOD_S, then publish."""
        self.cycle_count += 1
        now = self.clock()
        if now >= self._next_check:
            self._next_check = now + CHECK_PERIOD_S
            self._check(now)
        self._report()
        if self.cycle_count == OFFLINE_AFTER_FAILURES + 1:
            self._report_missing()

    def _idle(self) -> Optional[float]:
        """While the port is away: servo_states (all offline) and diagnostics keep coming."""
        if not self._running or self.bus.port_open:
            return None
        self._report()
        return time.monotonic() + 1.0 / self.config.publish_rate_hz

    def _check(self, now: float) -> None:
        """Once per CHECK_PERIOD_S: the cycle rate and the duplicate-id judgement (S24)."""
        schedule = self._schedule.reads
        if self._rate_mark is not None and now > self._rate_mark[0]:
            count = self.cycle_count - self._rate_mark[1]
            self.cycle_rate_hz = count / (now - self._rate_mark[0])
            rate = self.config.publish_rate_hz
            # Behind for good: most cycles started late and the rate fell short of the goal.
            if count and 2 * schedule.late >= count and self.cycle_rate_hz < 0.9 * rate and \
                    not self.behind_logged:
                self.behind_logged = True
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
        # Reader thread, after the schedule judged the servos (the runtime's LinkUp/LinkDown).
        self._changed()
