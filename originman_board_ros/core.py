"""The OriginMan board as a device: state, rules and policies, without ROS.

:class:`OriginManCore` owns an :class:`~originman_board_ros.link.OriginManLink` and a worker
thread. It judges the board online or offline, writes the desired settings whenever the board
(re)appears, stops the motors when their commands stop coming (the board has no watchdog, §8),
polls the bus servos, validates every command before anything reaches the wire, converts to SI
units and reports through callbacks. A node is a thin adapter on top of it. Decisions O1..
refer to ``docs/protocols.md``.

The decisions that must not wait (the motor watchdog, the online judgement, the order and pace
of outgoing frames) live in :class:`~originman_board_ros.plan.BoardPlan`, which has no I/O,
thread or clock. Every path (a caller's command, the worker's round, the timer, the reader's
connection and frame callbacks, every frame written) steps it with one event and its time
through the shared runner (``core_runner.run_core``, :meth:`_step`), and carries out what it
returns with one handler per action type: ``Send`` (write the frame; its ``SendDone`` is
stepped next), ``OnlineChanged``, ``Refuse``/``Drop`` (a caller's frame that will not leave),
``Log`` and ``SetTimer`` (the timer wakes by the plan's next deadline).

It is assembled here from one mixin class per responsibility, each in a module of its own whose
docstring says which threads run its code and which of the state below it owns:

- ``core_types``: the units, the configuration, the samples and results (re-exported here);
- ``core_commands``: the command methods (the topics) and the validation helpers;
- ``core_services``: the service methods (reads and settings of the servos);
- ``core_settings``: the desired settings written at (re)connect, and their check;
- ``core_bus_poll``: the bus servo poll.

This module holds the shared state, the life cycle, the worker's and the timer's loops, the
plan's actions (``_step`` and its handlers), the reader's callbacks and the snapshot.

Threads and state (who owns what):

* the link's **reader thread** decodes frames; ``_on_frames`` tells the plan a frame came (the
  board is online from that frame on, before any report of it is published), then
  :meth:`_on_report` converts each report and calls the matching ``on_*`` callback directly; it
  writes ``_battery_mv`` and the report counters under ``_lock``. ``_on_connection`` (also the
  reader thread) tells the plan the port opened or closed.
* the **timer thread** (a ``DeadlineTimer`` running :meth:`_timer_duty`) fires the motor
  watchdog at its deadline and releases paced bus servo moves; it never reads or waits for
  the board, so a read that is not answered cannot hold a stop back (issue 21 item 6).
* the **worker thread** runs :meth:`poll` when a duty may be due (:meth:`next_wake`: at
  most ``IDLE_MAX_S`` apart, every ``WORKER_PERIOD_S`` while offline): the silence judgement
  (and ``on_online_change``), desired settings (``core_settings``), the settings check and the
  bus servo poll (``core_bus_poll``: blocking reads, one at a time) with
  ``on_bus_servo_states``. It owns the poll schedule (``_next_poll``, ``_telemetry_at``,
  ``_reprobe_at``, ``_check_at``: worker only, no lock).
* **caller threads** (a node's executor) call the command methods (``core_commands``) and the
  services (``core_services``). They validate and step the plan with their frame and a
  :class:`~uav_serial_common.ticket.Ticket` (opaque to the plan), then wait on it (``_wait``)
  until the frame has left, was dropped or could not be written: whichever thread carries out
  the plan's ``Send``, ``Refuse`` or ``Drop`` settles it. A ticket holds its own fate, so one
  settled after its caller gave up (``SEND_WAIT_S``) is kept for nobody. A read goes through
  the link (a lock per FUNCTION keeps one read outstanding).
* **writing**: a caller, the worker or the timer, never the reader (the plan gives no ``Send``
  for the reader's and the link's events: they come from inside the link's locks). The plan
  has at most one ``Send`` out: the thread whose step got it writes it (outside ``_lock``),
  steps its ``SendDone`` and writes whatever the plan gives next, until nothing is ready; a
  thread whose step gets no ``Send`` writes nothing. So a stop (the watchdog's or
  ``stop_all_motors``) queued while another thread writes a caller's queued frames is the next
  frame on the wire, after at most the one being written (issue 22 item 3), and its caller's
  answer does not wait for the rest.
* shared, always under ``_lock``: ``_plan`` (stepped by ``_stepper``), ``_status``,
  ``_settings_*``, ``_servos`` (the poll and the read services), ``_poll_ids`` (renamed by
  ``set_bus_servo_id``), ``_expected_offsets`` (the worker and ``set_pwm_servo_offset``), the
  refusal and report counters.

``_lock`` is never held while calling a callback or doing I/O. Callbacks must be quick and must
not call back into blocking methods of the core from the reader thread.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

from originman_board_ros import protocol as p
from originman_board_ros.core_bus_poll import (BusServoPoll, SERVO_OFFLINE_AFTER,  # noqa: F401
                                               SERVO_REPROBE_S)
from originman_board_ros.core_commands import (BUS_DURATION_MAX_S, Commands,  # noqa: F401
                                               LED_TIME_MAX_S, PWM_DURATION_MAX_S,
                                               PWM_DURATION_MIN_S, STOP_ALL_MASK)
from originman_board_ros.core_services import Services
from originman_board_ros.core_settings import SETTINGS_RETRY_S, SettingsAtConnect  # noqa: F401
from originman_board_ros.core_types import (  # noqa: F401 (the names of this module's API)
    AsrSample, battery_volts, BatterySample, bus_position_to_rad, BusServoStatus, ButtonSample,
    ConfigError, gamepad_axes, gamepad_buttons, GamepadSample, imu_to_si, ImuSample,
    MOTOR_TYPES, OriginManConfig, OriginManSnapshot, PwmServoStates, Refused, sbus_normalize,
    SbusSample, STANDARD_GRAVITY)
from originman_board_ros.link import LinkDown, LinkError, LinkTimeout, OriginManLink
from originman_board_ros.plan import (Action, BoardPlan, Command, Deadline, Drop, Event,
                                      FrameIn, OnlineChanged, Reconfigure, Refuse, Send,
                                      SendDone, Written)
from uav_serial_common import core_events as ev
from uav_serial_common.core_runner import run_core
from uav_serial_common.deadline_timer import DeadlineTimer
from uav_serial_common.logs import log_at
from uav_serial_common.result import Outcome, Result  # noqa: F401 (what the core answers)
from uav_serial_common.ticket import Ticket

__all__ = ['AsrSample', 'BatterySample', 'BusServoStatus', 'ButtonSample', 'ConfigError',
           'GamepadSample', 'ImuSample', 'MOTOR_TYPES', 'OriginManConfig', 'OriginManCore',
           'OriginManSnapshot', 'Outcome', 'PwmServoStates', 'Refused', 'Result', 'SbusSample',
           'battery_volts', 'bus_position_to_rad', 'gamepad_axes', 'gamepad_buttons',
           'imu_to_si', 'sbus_normalize']

WORKER_PERIOD_S = 0.01
"""How often the worker looks for the board's first frames while it is offline."""
IDLE_MAX_S = 0.1
"""The longest the worker sleeps while online: the state in snapshots is at most this old."""
TIMER_IDLE_S = 0.5
"""The longest the timer thread sleeps without a deadline (commands wake it earlier)."""
DEFAULT_BATTERY_WARN_MV = 6300
"""The firmware's own alarm threshold, used for warnings when ``low_battery_mv`` is -1."""
SEND_WAIT_S = 5.0
"""The longest a caller waits for its frame to leave (frames ahead of it are written first)."""


class _LockedPlan:
    """The plan, stepped under the core's lock with the board's clock for its pacing."""

    def __init__(self, plan: BoardPlan, lock: threading.Lock,
                 pace_clock: Callable[[], float]) -> None:
        self.plan, self.lock, self.pace_clock = plan, lock, pace_clock

    def step(self, event: Event) -> List[Action]:
        """Step the plan with ``event`` under the lock (what it asks is carried out after)."""
        with self.lock:
            return self.plan.step(event, self.pace_clock())


class OriginManCore(Commands, Services, SettingsAtConnect, BusServoPoll):
    """The board, its policies and its state; reports through callbacks.

    Callbacks (each optional, called with one argument unless noted; exceptions are logged):
    ``on_imu(ImuSample)``, ``on_battery(BatterySample)``, ``on_button(ButtonSample)``,
    ``on_sbus(SbusSample)``, ``on_gamepad(GamepadSample)``, ``on_asr(AsrSample)`` from the reader
    thread at each report; ``on_bus_servo_states(list[BusServoStatus])`` from the worker after
    each poll cycle (every id of ``bus_servo_ids``, offline ones with ``online`` False);
    ``on_online_change(online: bool, reason: str)`` from the worker on every change.

    Command methods return a :class:`~uav_serial_common.result.Result` (``value``: what a
    read returned) and never raise for bad input, a refused command or a failed device: a
    refusal (outcome REFUSED, with its ``cause``) sent nothing; a command the board never
    acknowledges is SENT. Reads block for at most a few read timeouts per servo.
    """

    def __init__(self, config: OriginManConfig, *, clock: Callable[[], float] = time.monotonic,
                 on_imu: Optional[Callable[[ImuSample], None]] = None,
                 on_battery: Optional[Callable[[BatterySample], None]] = None,
                 on_button: Optional[Callable[[ButtonSample], None]] = None,
                 on_sbus: Optional[Callable[[SbusSample], None]] = None,
                 on_gamepad: Optional[Callable[[GamepadSample], None]] = None,
                 on_asr: Optional[Callable[[AsrSample], None]] = None,
                 on_bus_servo_states: Optional[Callable[[List[BusServoStatus]], None]] = None,
                 on_online_change: Optional[Callable[[bool, str], None]] = None,
                 logger: Optional[Any] = None,
                 pace_clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config.validated()
        self._clock = clock
        # The board's own time runs on the wall: pacing uses a real clock even when ``clock``
        # is a test's fake one.
        self._pace_clock = pace_clock
        self._log = logger or logging.getLogger('originman_core')
        self._callbacks = {'imu': on_imu, 'battery': on_battery, 'button': on_button,
                           'sbus': on_sbus, 'gamepad': on_gamepad, 'asr': on_asr,
                           'states': on_bus_servo_states, 'online': on_online_change}
        self.link = OriginManLink(self.config.port, self.config.baud,
                                  on_report=self._on_report, on_connection=self._on_connection,
                                  on_frames=self._on_frames, on_tx=self._on_written,
                                  clock=clock, timeout_s=self.config.read_timeout_s,
                                  retries=self.config.read_retries, logger=logger)
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        # The decisions (watchdog, online judgement, outgoing frames): stepped under _lock
        # by every thread (run_core), their actions carried out by that thread outside it.
        self._plan = BoardPlan(self.config.motor_timeout_s, self.config.offline_timeout_s)
        self._stepper = _LockedPlan(self._plan, self._lock, pace_clock)
        # No handler raises: a step's later action failing would lose the SendDone of its
        # Send (queued behind it), and a plan left "sending" writes nothing ever again, not
        # even the watchdog's stop.
        self._handlers = {kind: self._never_raises(handler) for kind, handler in (
            (Send, self._send), (OnlineChanged, self._online_changed), (Refuse, self._unsent),
            (Drop, self._unsent), (ev.Log, self._log_line), (ev.SetTimer, self._set_timer))}
        # The watchdog and the paced frames have a thread of their own that never waits
        # behind a read (issue 21 item 6).
        self._timer = DeadlineTimer(self._timer_duty, name='originman-timer', clock=clock,
                                    idle_s=TIMER_IDLE_S, min_sleep_s=0.0005,
                                    on_error=self._timer_failed)
        # Reader thread (under _lock).
        self._battery_mv: Optional[int] = None
        self._reports = {'imu': 0, 'battery': 0, 'button': 0, 'sbus': 0, 'gamepad': 0,
                         'asr': 0}
        self._status = 'port not open yet'
        self._settings_due: Optional[float] = None
        self._settings_asked = 0  # how many times they were asked for (_ask_settings)
        self._settings_ok = False
        self._settings_message = 'not written yet'
        self._check_at: Optional[float] = None
        self._next_poll: Optional[float] = None
        self._telemetry_at: Dict[int, float] = {}
        self._reprobe_at: Dict[int, float] = {}
        # Callers and worker (under _lock).
        self._refusals: Dict[str, int] = {}
        self._poll_ids: List[int] = list(self.config.bus_servo_ids)
        self._servos: Dict[int, BusServoStatus] = {i: BusServoStatus(i)
                                                   for i in self._poll_ids}
        # What the board's PWM offsets should be now: desired at (re)connect, then what a
        # service set. A read-back that differs means the board lost them (a reboot).
        self._expected_offsets: Dict[int, int] = {
            i + 1: v for i, v in enumerate(self.config.pwm_servo_offsets_us)}

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self, worker: bool = True) -> None:
        """Open the port (reconnecting as needed) and start the worker thread.

        With ``worker`` False nothing calls :meth:`poll`: the caller does (tests with a fake
        clock).
        """
        if self._thread is not None:
            return
        self._stop.clear()
        self.link.start()
        self._timer.start()
        if worker:
            self._thread = threading.Thread(target=self._run, name='originman-core',
                                            daemon=True)
            self._thread.start()

    def stop(self, stop_motors: bool = True) -> None:
        """Stop every motor (if the port is open and ``stop_motors``), the worker, the link.

        The motors are stopped first (at once), and once more after the worker has ended, so
        that the last motor frame on the wire is a stop whatever the worker wrote meanwhile
        (desired settings include the motor type).
        """
        if stop_motors and self.link.port_open:
            self.stop_all_motors()
        self._stop.set()
        self._wake.set()
        self._timer.stop(3.0)
        if self._thread is not None:
            self._thread.join(3.0)
            worker_ran = True
            self._thread = None
        else:
            worker_ran = False
        if stop_motors and worker_ran and self.link.port_open:
            self.stop_all_motors()
        self.link.stop()

    def reconfigure(self, config: OriginManConfig) -> None:
        """Take changed parameters at runtime; ``port`` and ``baud`` need a restart.

        Changed desired settings are written at once when the board is online (else at its
        next connect); a changed ``bus_servo_ids`` is polled from the next cycle, keeping what
        is known of the servos that stay. Raises ConfigError naming a bad value.
        """
        new = config.validated()
        old = self.config
        if (new.port, new.baud) != (old.port, old.baud):
            raise ConfigError('port and baud are read at start only; restart the node')
        desired = ('low_battery_mv', 'motor_type', 'pwm_servo_offsets_us')
        with self._lock:
            self.config = new
            if new.bus_servo_ids != old.bus_servo_ids:
                self._poll_ids = list(new.bus_servo_ids)
                self._servos = {i: self._servos.get(i, BusServoStatus(i))
                                for i in self._poll_ids}
            if any(getattr(new, k) != getattr(old, k) for k in desired):
                self._expected_offsets = {
                    i + 1: v for i, v in enumerate(new.pwm_servo_offsets_us)}
                if self._plan.online:
                    self._ask_settings(self._clock())
        self._step(Reconfigure(self._clock(), new.motor_timeout_s, new.offline_timeout_s))
        self._wake.set()
        self._timer.wake()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.poll()
            except Exception:  # noqa: BLE001 - a bug in one duty must not stop the others
                self._log.exception('originman core: poll failed')
            # Sleep until a duty may be due, not on a fixed tick: a wake-up costs a driver
            # beside others a share of a core it does not need (bench: cpu_originman_pct).
            self._wake.wait(self.next_wake())
            self._wake.clear()

    def next_wake(self, now: Optional[float] = None) -> float:
        """Seconds until one of the worker's duties may be due (0..``IDLE_MAX_S``)."""
        now = self._clock() if now is None else now
        cfg = self.config
        waits = [IDLE_MAX_S]
        with self._lock:
            # Not the motor watchdog: the timer thread keeps it (issue 21 item 6).
            online = self._plan.online
            if self._settings_due is not None:
                waits.append(self._settings_due - now)
        last = self.link.last_frame_time
        if not online or last is None:
            waits.append(WORKER_PERIOD_S)
        else:
            waits.append(last + cfg.offline_timeout_s - now)
            if self._check_at is not None:
                waits.append(self._check_at - now)
            if self._next_poll is not None and self._poll_ids and cfg.bus_servo_poll_hz > 0:
                waits.append(self._next_poll - now)
        return max(0.0, min(waits))

    # -- the worker's duties --------------------------------------------------------------------

    def poll(self, now: Optional[float] = None) -> None:
        """Run every duty that is due at ``now`` (default: the clock).

        The worker thread calls it; call it yourself only after ``start(worker=False)``.
        """
        now = self._clock() if now is None else now
        online = self._tick(now)
        if online:
            self._apply_settings(now)
            self._check_settings(now)
        self._poll_servos(now, online)

    @property
    def online(self) -> bool:
        """Whether the board sent a frame within ``offline_timeout_s`` on an open port."""
        return self._plan.online

    def _tick(self, now: float) -> bool:
        """Judge silence and run the watchdog at ``now``; send what is due. Return online."""
        self._step(ev.Tick(now))
        with self._lock:
            online = self._plan.online
            if not self.link.port_open:
                self._status = f'port {self.config.port} not open: ' \
                               f'{self.link.serial.last_error or "connecting"}'
            elif not online and self._plan.judge.last_frame_at is None:
                self._status = 'port open, no frame from the board yet'
        return online

    def _changed(self, change: Tuple[bool, str], now: float) -> None:
        """Carry out an online change the plan decided (from any thread, outside _lock)."""
        online, why = change
        with self._lock:
            self._status = why
            if online:
                # Written at connect and after every return (a reboot loses them, §4).
                self._ask_settings(now)
                self._expected_offsets = {
                    i + 1: v for i, v in enumerate(self.config.pwm_servo_offsets_us)}
                self._next_poll = now
        if not online:
            self._mark_servos_offline(why)
        self._log.info(f'originman board {"online" if online else "offline"}: {why}')
        self._call('online', online, why)
        self._wake.set()

    # -- the plan's actions -------------------------------------------------------------------

    def _step(self, *events: Event) -> List[Action]:
        """Step the plan with ``events`` and carry out what it asks, here, in its order.

        Every path goes through here (callers, the worker, the timer, the reader). The plan is
        stepped under ``_lock``; its actions are carried out outside it, by this thread. The
        plan has at most one ``Send`` out at a time and chooses the next when it is done, so
        the thread that writes goes on with what is ready then: a stop another thread queued
        meanwhile is next, whoever queued the frames before it (issue 22 item 3).
        """
        return run_core(self._stepper, events, self._handlers)

    def _never_raises(self, handler: Callable[[Any], Any]) -> Callable[[Any], Any]:
        def carry_out(action: Any) -> Any:
            try:
                return handler(action)
            except Exception:  # noqa: BLE001 - see _handlers
                done = [SendDone(self._clock(), 'the write failed')] \
                    if isinstance(action, Send) else None
                with contextlib.suppress(Exception):  # (the logger may be what failed)
                    self._log.exception(f'originman core: carrying out '
                                        f'{type(action).__name__} failed')
                return done
        return carry_out

    def _send(self, action: Send) -> List[Event]:
        """Write the plan's frame (outside ``_lock``); its ``SendDone`` frees the writer."""
        error: Optional[str] = None
        try:
            self.link.send(action.frame)
        except LinkError as exc:
            error = str(exc) or type(exc).__name__
        except Exception as exc:  # noqa: BLE001 - the writer must be freed whatever happens
            self._log.exception('originman core: a write failed')
            error = f'{type(exc).__name__}: {exc}'
        if action.ticket is not None:  # (the ticket holds its fate: nothing kept for nobody)
            action.ticket.settle('sent' if error is None else 'failed', error)
        return [SendDone(self._clock(), error)]

    def _unsent(self, action: Any) -> None:
        """Answer a caller whose frame was refused (offline) or dropped unsent."""
        if action.ticket is not None:
            action.ticket.settle('refused' if isinstance(action, Refuse) else 'dropped',
                                 action.reason)

    @staticmethod
    def _refused(ticket: Ticket) -> bool:
        """Whether the step that queued ``ticket`` refused it (the board is offline)."""
        return ticket.outcome == 'refused'

    @staticmethod
    def _wait(ticket: Ticket) -> Optional[str]:
        """Wait until ``ticket``'s frame has left: None, or why it did not.

        Raises LinkTimeout when it is still queued after ``SEND_WAIT_S``: it may leave later,
        so whether it does is not known (and its outcome, when it comes, is not kept).
        """
        if not ticket.wait(SEND_WAIT_S):
            raise LinkTimeout(f'still queued after {SEND_WAIT_S:g} s (the port wrote '
                              'nothing meanwhile): it may leave later')
        return None if ticket.outcome == 'sent' else ticket.detail

    def _write(self, frame: bytes, cancels: Sequence[int] = ()) -> None:
        """Send a command now, behind queued ones; raise LinkError when it did not leave.

        ``cancels``: queued bus servo targets of these ids are dropped (a stop, torque off).
        """
        ticket = Ticket()
        self._step(Command(self._clock(), frame, ticket, tuple(cancels)))
        if self._refused(ticket):
            raise LinkDown(f'the board is offline ({self._status})')
        error = self._wait(ticket)
        if error is not None:
            raise LinkDown(error)

    def _online_changed(self, action: OnlineChanged) -> None:
        self._changed((action.online, action.reason), action.now)

    def _log_line(self, action: ev.Log) -> None:
        log_at(self._log, action.level, action.text)

    def _set_timer(self, action: ev.SetTimer) -> None:
        self._timer.wake(by=action.at)

    def _on_written(self, frame: bytes) -> None:
        """Every frame that left, reads included: the board's work to come (link thread)."""
        self._step(Written(self._clock(), frame))

    def _timer_duty(self) -> Optional[float]:
        """Fire the watchdog, release paced frames; return when next due (on ``_clock``).

        Never reads or waits on the board.
        """
        due = None
        for action in self._step(Deadline(self._clock())):
            if isinstance(action, ev.SetTimer):
                due = action.at  # the last step's: after the frames this thread wrote
        return due

    def _timer_failed(self, exc: BaseException) -> None:
        self._log.exception('originman core: timer failed')

    # -- reader thread --------------------------------------------------------------------------

    def _on_connection(self, up: bool, reason: str) -> None:
        now = self._clock()
        # O38: after (re)opening the port the motors' state is unknown; without a motor
        # command within motor_timeout_s they are stopped (the plan arms the watchdog).
        self._step(ev.LinkUp(now) if up else ev.LinkDown(now, reason))
        self._wake.set()
        self._timer.wake()

    def _on_frames(self, now: float) -> None:
        # Issue 21 item 11(a): online from the frame itself, before anyone sees it published.
        self._step(FrameIn(now))

    def _on_report(self, msg: Any) -> None:
        now = self._clock()
        if isinstance(msg, p.ImuReport):
            accel, gyro = imu_to_si(msg)
            self._count('imu')
            self._call('imu', ImuSample(now, accel, gyro, msg))
        elif isinstance(msg, p.BatteryReport):
            with self._lock:
                self._battery_mv = msg.millivolts
                self._reports['battery'] += 1
            self._call('battery', BatterySample(now, battery_volts(msg.millivolts),
                                                msg.millivolts,
                                                msg.millivolts < self._battery_warn_mv()))
        elif isinstance(msg, p.KeyReport):
            self._count('button')
            self._call('button', ButtonSample(now, msg.key_id, msg.event, msg.event_name))
        elif isinstance(msg, p.SbusReport):
            self._count('sbus')
            self._call('sbus', SbusSample(
                now, msg.channels, tuple(sbus_normalize(c) for c in msg.channels), msg.ch17,
                msg.ch18, msg.signal_loss, msg.failsafe))
        elif isinstance(msg, p.GamepadReport):
            self._count('gamepad')
            self._call('gamepad', GamepadSample(now, tuple(gamepad_axes(msg)),
                                                tuple(gamepad_buttons(msg)), msg))
        elif isinstance(msg, p.AsrReport):
            self._count('asr')
            self._call('asr', AsrSample(now, msg.data))

    def _count(self, kind: str) -> None:
        with self._lock:
            self._reports[kind] += 1

    def _call(self, kind: str, *args: Any) -> None:
        callback = self._callbacks.get(kind)
        if callback is None:
            return
        try:
            callback(*args)
        except Exception:  # noqa: BLE001 - a user's callback must not kill our threads
            self._log.exception(f'originman core: {kind} callback failed')

    def _battery_warn_mv(self) -> int:
        low = self.config.low_battery_mv
        return DEFAULT_BATTERY_WARN_MV if low == -1 else low

    # -- state ----------------------------------------------------------------------------------

    def snapshot(self) -> OriginManSnapshot:
        """Everything diagnostics need, consistent at one instant."""
        now = self._clock()
        last = self.link.last_frame_time
        link = self.link
        decoder = link.decoder
        with self._lock:
            battery = self._battery_mv
            warn = self._battery_warn_mv()
            return OriginManSnapshot(
                port_open=link.port_open, online=self._plan.online, status=self._status,
                port_error=link.serial.last_error,
                last_frame_age_s=None if last is None else max(0.0, now - last),
                battery_mv=battery, battery_low=battery is not None and battery < warn,
                battery_warn_mv=warn, frames_decoded=decoder.frames_decoded,
                checksum_errors=decoder.checksum_errors, bytes_discarded=decoder.bytes_discarded,
                unknown_functions=decoder.unknown_functions, unknown_frames=link.unknown_frames,
                unexpected_replies=link.unexpected_replies, reports=dict(self._reports),
                reads=link.reads, read_timeouts=link.read_timeouts,
                read_failures=link.read_failures, reconnects=link.serial.stats.reconnects,
                refusals=dict(self._refusals), watchdog_stops=self._plan.watchdog.fired,
                settings_ok=self._settings_ok, settings_message=self._settings_message,
                bus_servos=tuple(self._servos[i] for i in self._poll_ids if i in self._servos),
                bus_targets_queued=len(self._plan.scheduler.targets),
                bus_targets_replaced=self._plan.scheduler.coalesced,
                board_backlog_s=self._plan.scheduler.backlog(self._pace_clock()))

    @property
    def bus_servo_ids(self) -> List[int]:
        """The ids polled now (``bus_servo_ids``, renamed by :meth:`set_bus_servo_id`)."""
        with self._lock:
            return list(self._poll_ids)
