"""The OriginMan board as a device: state, rules and policies, without ROS.

:class:`OriginManCore` owns an :class:`~originman_board_ros.link.OriginManLink` and a worker
thread. It judges the board online or offline, writes the desired settings whenever the board
(re)appears, stops the motors when their commands stop coming (the board has no watchdog, §8),
polls the bus servos, validates every command before anything reaches the wire, converts to SI
units and reports through callbacks. A node is a thin adapter on top of it. Decisions O1..
refer to ``docs/protocols.md``.

The decisions that must not wait (the motor watchdog, the online judgement, the order and pace
of outgoing frames) live in :class:`~originman_board_ros.plan.BoardPlan`, which has no I/O,
thread or clock; this module feeds it events with their time and carries out what it decides.

Threads and state (who owns what):

* the link's **reader thread** decodes frames; ``_on_frames`` tells the plan a frame came (the
  board is online from that frame on, before any report of it is published), then
  :meth:`_on_report` converts each report and calls the matching ``on_*`` callback directly; it
  writes ``_battery_mv`` and the report counters under ``_lock``. ``_on_connection`` (also the
  reader thread) tells the plan the port opened or closed.
* the **timer thread** fires the motor watchdog at its deadline and releases paced bus servo
  moves; it never reads or waits for the board, so a read that is not answered cannot hold a
  stop back (issue 21 item 6).
* the **worker thread** runs :meth:`poll` when a duty may be due (:meth:`next_wake`: at
  most ``IDLE_MAX_S`` apart, every ``WORKER_PERIOD_S`` while offline): the silence judgement
  (and ``on_online_change``), desired settings, the settings check and the bus servo poll
  (blocking reads, one at a time) with ``on_bus_servo_states``. It owns the poll schedule
  (``_next_poll``, ``_telemetry_at``, ``_reprobe_at``, ``_check_at``: worker only, no lock).
* **caller threads** (a node's executor) call the command methods. They validate, queue their
  frame in the plan and write what it has ready (``_drain``: one writer at a time, stops
  first); a read goes through the link (a lock per FUNCTION keeps one read outstanding).
* shared, always under ``_lock``: ``_plan``, ``_status``, ``_settings_*``, ``_servos`` (the
  poll and the read services), ``_poll_ids`` (renamed by ``set_bus_servo_id``),
  ``_expected_offsets`` (the worker and ``set_pwm_servo_offset``), the refusal and report
  counters.

``_lock`` is never held while calling a callback or doing I/O. Callbacks must be quick and must
not call back into blocking methods of the core from the reader thread.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import logging
import math
import threading
import time
from typing import Any, Callable, Dict, Iterable, List, Optional, Sequence, Tuple

from originman_board_ros import protocol as p
from originman_board_ros.link import BusServoFailure, LinkDown, LinkError, OriginManLink
from originman_board_ros.plan import BoardPlan

__all__ = ['AsrSample', 'BatterySample', 'BusServoStatus', 'BusServoStatesResult',
           'ButtonSample', 'CommandResult', 'ConfigError', 'GamepadSample', 'ImuSample',
           'MOTOR_TYPES', 'OriginManConfig', 'OriginManCore', 'OriginManSnapshot',
           'PwmServoStatesResult', 'Refused', 'SbusSample', 'battery_volts',
           'bus_position_to_rad', 'gamepad_axes', 'gamepad_buttons', 'imu_to_si',
           'sbus_normalize']

WORKER_PERIOD_S = 0.01
"""How often the worker looks for the board's first frames while it is offline."""
IDLE_MAX_S = 0.1
"""The longest the worker sleeps while online: the state in snapshots is at most this old."""
SERVO_OFFLINE_AFTER = 3
"""Consecutive failed reads after which a polled bus servo is offline."""
SERVO_REPROBE_S = 1.0
"""An offline bus servo is read once per this period, without retries."""
SETTINGS_RETRY_S = 1.0
TIMER_IDLE_S = 0.5
"""The longest the timer thread sleeps without a deadline (commands wake it earlier)."""
DEFAULT_BATTERY_WARN_MV = 6300
"""The firmware's own alarm threshold, used for warnings when ``low_battery_mv`` is -1."""
MOTOR_TYPES = ('keep',) + tuple(t.name for t in p.MotorType)
STOP_ALL_MASK = (1 << p.MOTOR_COUNT) - 1
LED_TIME_MAX_S = 65.535
BUS_DURATION_MAX_S = 65.535
PWM_DURATION_MIN_S = 0.02
PWM_DURATION_MAX_S = 30.0


# ---------------------------------------------------------------------------------------------
# Units (O7, O9, and the contract's conversions)
# ---------------------------------------------------------------------------------------------

STANDARD_GRAVITY = 9.80665
BUS_DEG_PER_UNIT = 0.24
BUS_CENTRE = 500
SBUS_CENTRE = 992
SBUS_HALF_RANGE = 820.0
HAT_X = {9: 1.0, 13: -1.0}
HAT_Y = {11: -1.0, 15: 1.0}


Vector3 = Tuple[float, float, float]


def imu_to_si(report: p.ImuReport) -> Tuple[Vector3, Vector3]:
    """Return (acceleration in m/s^2, angular rate in rad/s) from the board's g and deg/s (O7)."""
    ax, ay, az = (v * STANDARD_GRAVITY for v in report.accel_g)
    gx, gy, gz = (math.radians(v) for v in report.gyro_dps)
    return (ax, ay, az), (gx, gy, gz)


def battery_volts(millivolts: int) -> float:
    """Battery voltage in V from the board's mV (O9)."""
    return millivolts / 1000.0


def bus_position_to_rad(raw: int) -> float:
    """Bus servo angle in rad: 0.24 degrees per unit around 500, rising with the raw value."""
    return math.radians((raw - BUS_CENTRE) * BUS_DEG_PER_UNIT)


def sbus_normalize(raw: int) -> float:
    """Scale an SBUS channel to -1..1 around 992 (O16: the wire carries raw values)."""
    return max(-1.0, min(1.0, (raw - SBUS_CENTRE) / SBUS_HALF_RANGE))


def gamepad_axes(report: p.GamepadReport) -> List[float]:
    """``[lx, ly, rx, ry]`` scaled to -1..1 (raw / 127, clamped), then ``[hat_x, hat_y]``."""
    axes = [max(-1.0, min(1.0, v / 127.0))
            for v in (report.lx, report.ly, report.rx, report.ry)]
    return axes + [HAT_X.get(report.hat, 0.0), HAT_Y.get(report.hat, 0.0)]


def gamepad_buttons(report: p.GamepadReport) -> List[int]:
    """Return the 16 bits of the button mask, bit 0 first."""
    return [(report.buttons >> i) & 1 for i in range(16)]


# ---------------------------------------------------------------------------------------------
# Configuration, events, results
# ---------------------------------------------------------------------------------------------

class ConfigError(ValueError):
    """A configuration value the core cannot work with; the message says which and why."""


@dataclass(frozen=True)
class OriginManConfig:
    """The driver's parameters (the contract's table, plus link tuning)."""

    port: str = '/dev/ttyS1'
    baud: int = p.BAUD
    offline_timeout_s: float = 2.5
    low_battery_mv: int = -1
    motor_type: str = 'keep'
    motor_timeout_s: float = 0.5
    pwm_servo_offsets_us: Tuple[int, ...] = ()
    bus_servo_ids: Tuple[int, ...] = ()
    bus_servo_poll_hz: float = 10.0
    bus_servo_telemetry_period_s: float = 2.0
    read_timeout_s: float = 0.05
    read_retries: int = 1
    settings_check_period_s: float = 5.0

    def validated(self) -> 'OriginManConfig':
        """Return a normalised copy (tuples, ints); raise ConfigError naming a bad value."""
        def number(name: str, lo: float, hi: float = math.inf, open_lo: bool = False) -> float:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or \
                    not math.isfinite(value) or value < lo or value > hi or \
                    (open_lo and value == lo):
                bound = f'> {lo:g}' if open_lo else f'>= {lo:g}'
                if hi != math.inf:
                    bound += f' and <= {hi:g}'
                raise ConfigError(f'{name} must be a finite number {bound}, got {value!r}')
            return float(value)

        def integers(name: str, lo: int, hi: int, max_len: int) -> Tuple[int, ...]:
            values = tuple(getattr(self, name))
            if len(values) > max_len or any(not _is_int(v) or not lo <= v <= hi
                                            for v in values):
                raise ConfigError(f'{name} must hold at most {max_len} integers in {lo}..{hi}, '
                                  f'got {list(values)}')
            return tuple(int(v) for v in values)

        if not isinstance(self.port, str) or not self.port:
            raise ConfigError(f'port must be a device path or URL, got {self.port!r}')
        if not _is_int(self.baud) or self.baud <= 0:
            raise ConfigError(f'baud must be a positive integer, got {self.baud!r}')
        low = self.low_battery_mv
        if not _is_int(low) or not (low == -1 or 0 <= low <= p.U16_MAX):
            raise ConfigError(f'low_battery_mv must be -1 (leave the board\'s 6300 mV) or '
                              f'0..{p.U16_MAX} mV, got {low!r}')
        if self.motor_type not in MOTOR_TYPES:
            raise ConfigError(f'motor_type must be one of {", ".join(MOTOR_TYPES)}, '
                              f'got {self.motor_type!r}')
        ids = integers('bus_servo_ids', 0, p.BUS_ID_MAX, p.BUS_ID_MAX + 1)
        if len(set(ids)) != len(ids):
            raise ConfigError(f'bus_servo_ids lists an id twice: {list(ids)}')
        if not _is_int(self.read_retries) or not 0 <= self.read_retries <= 5:
            raise ConfigError(f'read_retries must be 0..5, got {self.read_retries!r}')
        return replace(
            self,
            offline_timeout_s=number('offline_timeout_s', 0.0, open_lo=True),
            motor_timeout_s=number('motor_timeout_s', 0.0),
            pwm_servo_offsets_us=integers('pwm_servo_offsets_us', -p.PWM_OFFSET_MAX_US,
                                          p.PWM_OFFSET_MAX_US, p.PWM_SERVO_COUNT),
            bus_servo_ids=ids,
            bus_servo_poll_hz=number('bus_servo_poll_hz', 0.0, 200.0),
            bus_servo_telemetry_period_s=number('bus_servo_telemetry_period_s', 0.0,
                                                open_lo=True),
            read_timeout_s=number('read_timeout_s', 0.0, 5.0, open_lo=True),
            settings_check_period_s=number('settings_check_period_s', 0.0))


@dataclass(frozen=True)
class ImuSample:
    """One IMU report in SI units (O7); ``received_at`` is the core's clock at arrival."""

    received_at: float
    linear_acceleration: Tuple[float, float, float]
    angular_velocity: Tuple[float, float, float]
    report: p.ImuReport


@dataclass(frozen=True)
class BatterySample:
    """One battery report (O9)."""

    received_at: float
    voltage_v: float
    millivolts: int
    low: bool


@dataclass(frozen=True)
class ButtonSample:
    """One raw key event (O17)."""

    received_at: float
    key_id: int
    event: int
    event_name: str


@dataclass(frozen=True)
class SbusSample:
    """One SBUS frame: raw channels (O16) and the contract's normalisation."""

    received_at: float
    channels: Tuple[int, ...]
    normalized: Tuple[float, ...]
    ch17: bool
    ch18: bool
    signal_loss: bool
    failsafe: bool


@dataclass(frozen=True)
class GamepadSample:
    """One gamepad report as a joystick: 6 axes (sticks, hat) and 16 buttons (O15)."""

    received_at: float
    axes: Tuple[float, ...]
    buttons: Tuple[int, ...]
    report: p.GamepadReport


@dataclass(frozen=True)
class AsrSample:
    """One speech-recognition result: the report's bytes (O2)."""

    received_at: float
    data: bytes


@dataclass(frozen=True)
class BusServoStatus:
    """What is known of one bus servo (the fields of ``BusServoState``).

    The poll fills ``position``, ``voltage_v``, ``temperature_c`` and ``torque_enabled``; a
    :meth:`OriginManCore.get_bus_servo_state` call fills every field afresh. NaN = not read.
    """

    id: int
    online: bool = False
    position: int = 0
    position_rad: float = math.nan
    voltage_v: float = math.nan
    temperature_c: float = math.nan
    torque_enabled: bool = False
    offset: int = 0
    min_position: int = 0
    max_position: int = 0
    min_voltage_v: float = math.nan
    max_voltage_v: float = math.nan
    max_temperature_c: float = math.nan
    failed_reads: int = 0
    last_error: str = ''


@dataclass(frozen=True)
class CommandResult:
    """The outcome of a command: ``ok`` and a message saying what was done or what failed.

    ``cause`` is set when the core refused the command before sending anything
    (``out_of_range``, ``not_finite``, ``length_mismatch``, ``duplicate``, ``offline``,
    ``id_taken`` ...).
    """

    ok: bool
    message: str
    cause: str = ''


@dataclass(frozen=True)
class BusServoStatesResult:
    """The answer of :meth:`OriginManCore.get_bus_servo_state`."""

    ok: bool
    message: str
    servos: Tuple[BusServoStatus, ...] = ()
    cause: str = ''


@dataclass(frozen=True)
class PwmServoStatesResult:
    """The answer of :meth:`OriginManCore.get_pwm_servo_state` (0 where a read failed)."""

    ok: bool
    message: str
    pulses_us: Tuple[int, ...] = ()
    offsets_us: Tuple[int, ...] = ()
    cause: str = ''


@dataclass(frozen=True)
class OriginManSnapshot:
    """The core's state for diagnostics, taken at once under its lock."""

    connected: bool
    online: bool
    status: str
    port_error: str
    last_frame_age_s: Optional[float]
    battery_mv: Optional[int]
    battery_low: bool
    battery_warn_mv: int
    frames: int
    crc_errors: int
    bytes_discarded: int
    unknown_functions: int
    unknown_frames: int
    unexpected_replies: int
    reports: Dict[str, int]
    reads: int
    read_timeouts: int
    read_failures: int
    reconnects: int
    refusals: Dict[str, int]
    watchdog_stops: int
    settings_ok: bool
    settings_message: str
    bus_servos: Tuple[BusServoStatus, ...]
    bus_targets_queued: int = 0
    """Bus servo targets waiting for room on the servo bus (issue 21 item 7)."""
    bus_targets_replaced: int = 0
    """Queued targets a newer one of the same servo replaced before they left."""
    board_backlog_s: float = 0.0
    """The servo-bus work the board still has from frames sent, as estimated."""


class Refused(ValueError):
    """A command the core will not send; ``cause`` is a short key for counting."""

    def __init__(self, cause: str, message: str) -> None:
        self.cause = cause
        super().__init__(message)


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


# ---------------------------------------------------------------------------------------------
# Validation helpers (they raise Refused; nothing is sent before they all pass)
# ---------------------------------------------------------------------------------------------

def _ints(name: str, values: Iterable[Any], lo: int, hi: int) -> List[int]:
    out = []
    for value in values:
        if not _is_int(value):
            if isinstance(value, float) and math.isfinite(value) and value.is_integer():
                value = int(value)
            else:
                raise Refused('out_of_range', f'{name} must be integers in {lo}..{hi}, '
                                              f'got {value!r}')
        if not lo <= value <= hi:
            raise Refused('out_of_range', f'{name} {value} is out of range {lo}..{hi}')
        out.append(int(value))
    return out


def _int(name: str, value: Any, lo: int, hi: int) -> int:
    return _ints(name, [value], lo, hi)[0]


def _seconds(name: str, value: Any, lo: float, hi: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise Refused('out_of_range', f'{name} must be a number of seconds, got {value!r}')
    if not math.isfinite(value):
        raise Refused('not_finite', f'{name} {value} is not finite')
    if not lo <= value <= hi:
        raise Refused('out_of_range', f'{name} {value:g} s is out of range {lo:g}..{hi:g} s')
    return float(value)


def _to_ms(seconds: float) -> int:
    ms = int(round(seconds * 1000.0))
    # A time > 0 shorter than 1 ms is 1 ms: 0 would mean "off" to the board (§4.2).
    return 1 if seconds > 0 and ms == 0 else ms


def _pattern(on_s: Any, off_s: Any, repeat: Any) -> Tuple[int, int, int]:
    """On and off times [ms] and repeat count of an LED or buzzer pattern, checked (O31)."""
    return (_to_ms(_seconds('on_s', on_s, 0.0, LED_TIME_MAX_S)),
            _to_ms(_seconds('off_s', off_s, 0.0, LED_TIME_MAX_S)),
            _int('repeat', repeat, 0, p.U16_MAX))


def _same_length(**lists: Sequence) -> None:
    lengths = {name: len(values) for name, values in lists.items()}
    if len(set(lengths.values())) > 1:
        detail = ', '.join(f'{name} has {n}' for name, n in lengths.items())
        raise Refused('length_mismatch', f'the lists must have the same length: {detail}')


def _distinct(name: str, ids: Sequence[int]) -> None:
    seen = set()
    for i in ids:
        if i in seen:
            raise Refused('duplicate', f'{name} lists {i} twice')
        seen.add(i)


# ---------------------------------------------------------------------------------------------
# The core
# ---------------------------------------------------------------------------------------------

class OriginManCore:
    """The board, its policies and its state; reports through callbacks.

    Callbacks (each optional, called with one argument unless noted; exceptions are logged):
    ``on_imu(ImuSample)``, ``on_battery(BatterySample)``, ``on_button(ButtonSample)``,
    ``on_sbus(SbusSample)``, ``on_gamepad(GamepadSample)``, ``on_asr(AsrSample)`` from the reader
    thread at each report; ``on_bus_servo_states(list[BusServoStatus])`` from the worker after
    each poll cycle (every id of ``bus_servo_ids``, offline ones with ``online`` False);
    ``on_online_change(online: bool, reason: str)`` from the worker on every change.

    Command methods return a :class:`CommandResult` (or a ``*Result`` with data) and never
    raise for bad input, a refused command or a failed device: a refusal has ``cause`` set and
    sent nothing. Reads block for at most a few read timeouts per servo.
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
        # The decisions (watchdog, online judgement, outgoing frames): under _lock.
        self._plan = BoardPlan(self.config.motor_timeout_s, self.config.offline_timeout_s)
        # One writer at a time drains the plan's frames; a caller's own frame has left (or
        # failed: the reason) when its ticket is in _results after its drain.
        self._send_lock = threading.Lock()
        self._results: Dict[object, Optional[str]] = {}
        self._timer_wake = threading.Event()
        self._timer: Optional[threading.Thread] = None
        # Reader thread (under _lock).
        self._battery_mv: Optional[int] = None
        self._reports = {'imu': 0, 'battery': 0, 'button': 0, 'sbus': 0, 'gamepad': 0,
                         'asr': 0}
        self._status = 'port not open yet'
        self._settings_due: Optional[float] = None
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
        # The watchdog and the paced frames have a thread of their own that never waits
        # behind a read (issue 21 item 6).
        self._timer = threading.Thread(target=self._run_timer, name='originman-timer',
                                       daemon=True)
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
        if stop_motors and self.link.connected:
            self.stop_all_motors()
        self._stop.set()
        self._wake.set()
        self._timer_wake.set()
        if self._timer is not None:
            self._timer.join(3.0)
            self._timer = None
        if self._thread is not None:
            self._thread.join(3.0)
            worker_ran = True
            self._thread = None
        else:
            worker_ran = False
        if stop_motors and worker_ran and self.link.connected:
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
            self._plan.configure(new.motor_timeout_s, new.offline_timeout_s)
            if new.bus_servo_ids != old.bus_servo_ids:
                self._poll_ids = list(new.bus_servo_ids)
                self._servos = {i: self._servos.get(i, BusServoStatus(i))
                                for i in self._poll_ids}
            if any(getattr(new, k) != getattr(old, k) for k in desired):
                self._expected_offsets = {
                    i + 1: v for i, v in enumerate(new.pwm_servo_offsets_us)}
                if self._plan.online:
                    self._settings_due = self._clock()
                    self._settings_ok = False
                    self._settings_message = 'writing'
        self._wake.set()
        self._timer_wake.set()

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
        with self._lock:
            change, fired = self._plan.tick(now)
            online = self._plan.online
            if not self.link.connected:
                self._status = f'port {self.config.port} not open: ' \
                               f'{self.link.serial.last_error or "connecting"}'
            elif not online and self._plan.judge.last_frame_at is None:
                self._status = 'port open, no frame from the board yet'
            last = self._plan.watchdog.last_command_at
        if change is not None:
            self._changed(change, now)
        if fired:
            self._log.warning(f'no motor command for {now - (last or now):.2f} s '
                              f'(motor_timeout_s {self.config.motor_timeout_s:g}): '
                              'stopping every motor')
        self._drain()
        return online

    def _changed(self, change: Tuple[bool, str], now: float) -> None:
        """Carry out an online change the plan decided (from any thread, outside _lock)."""
        online, why = change
        with self._lock:
            self._status = why
            if online:
                # Written at connect and after every return (a reboot loses them, §4).
                self._settings_due = now
                self._settings_ok = False
                self._settings_message = 'writing'
                self._expected_offsets = {
                    i + 1: v for i, v in enumerate(self.config.pwm_servo_offsets_us)}
                self._next_poll = now
        if not online:
            self._mark_servos_offline(why)
        self._log.info(f'originman board {"online" if online else "offline"}: {why}')
        self._call('online', online, why)
        self._wake.set()

    # -- sending ---------------------------------------------------------------------------------

    def _drain(self) -> None:
        """Write every frame the plan has ready, in its order (stops first, paced moves)."""
        with self._send_lock:
            while True:
                with self._lock:
                    item = self._plan.take(self._pace_clock())
                if item is None:
                    return
                _, frame, ticket = item
                error: Optional[str] = None
                try:
                    self.link.send(frame)
                except LinkError as exc:
                    error = str(exc) or type(exc).__name__
                if ticket is not None:
                    with self._lock:
                        self._results[ticket] = error

    def _outcome(self, ticket: object) -> Optional[str]:
        """After a drain: None if the ticket's frame left, else why not."""
        with self._lock:
            if ticket in self._results:
                return self._results.pop(ticket)
        return 'dropped before it left (a motor stop came after it, or the board went offline)'

    def _write(self, frame: bytes, cancels: Sequence[int] = ()) -> None:
        """Send a command now, behind queued ones; raise LinkError when it did not leave.

        ``cancels``: queued bus servo targets of these ids are dropped (a stop, torque off).
        """
        ticket = object()
        with self._lock:
            queued = self._plan.command(frame, ticket, cancels)
        if not queued:
            raise LinkDown(f'the board is offline ({self._status})')
        self._drain()
        error = self._outcome(ticket)
        if error is not None:
            raise LinkDown(error)

    def _on_written(self, frame: bytes) -> None:
        """Every frame that left, reads included: the board's work to come (link thread)."""
        with self._lock:
            self._plan.scheduler.written(frame, self._pace_clock())

    def _run_timer(self) -> None:
        """Fire the watchdog and release paced frames; never read or wait on the board."""
        while not self._stop.is_set():
            try:
                now = self._clock()
                with self._lock:
                    fired = self._plan.tick_watchdog(now)
                if fired:
                    self._log.warning(f'no motor command for motor_timeout_s '
                                      f'{self.config.motor_timeout_s:g} s: stopping every motor')
                self._drain()
                now, pace_now = self._clock(), self._pace_clock()
                waits = [TIMER_IDLE_S]
                with self._lock:
                    deadline = self._plan.watchdog.deadline
                    if deadline is not None and self._plan.judge.connected:
                        waits.append(deadline - now)
                    due = self._plan.scheduler.next_time(pace_now)
                    if due is not None:
                        waits.append(due - pace_now)
            except Exception:  # noqa: BLE001 - the watchdog's thread must outlive a bug
                self._log.exception('originman core: timer failed')
                waits = [0.01]
            self._timer_wake.wait(max(0.0005, min(waits)))
            self._timer_wake.clear()

    def _apply_settings(self, now: float) -> None:
        if self._settings_due is None or now < self._settings_due:
            return
        cfg = self.config
        problems = []
        with self._lock:
            expected = dict(self._expected_offsets)
        try:
            if cfg.low_battery_mv != -1:
                self._write(p.encode_battery_limit(cfg.low_battery_mv))
            if cfg.motor_type != 'keep':
                self._write(p.encode_motor_type(p.MotorType[cfg.motor_type]))
            for servo_id, offset in sorted(expected.items()):
                self._write(p.encode_pwm_set_offset(servo_id, offset))
            for servo_id, offset in sorted(expected.items()):
                got = self.link.read_pwm_offset(servo_id)
                if got != offset:
                    problems.append(f'PWM servo {servo_id} offset reads {got} us, '
                                    f'wanted {offset} us')
        except LinkError as exc:
            problems.append(f'could not write the settings: {exc}')
        with self._lock:
            if problems:
                self._settings_ok = False
                self._settings_message = '; '.join(problems)
                self._settings_due = now + SETTINGS_RETRY_S
            else:
                self._settings_due = None
                self._settings_ok = True
                self._settings_message = self._describe_settings(expected)
        if problems:
            self._log.warning(f'originman board settings: {self._settings_message}; retrying')
            return
        period = cfg.settings_check_period_s
        self._check_at = now + period if period > 0 and expected else None

    def _describe_settings(self, offsets: Dict[int, int]) -> str:
        cfg = self.config
        parts = []
        if cfg.low_battery_mv != -1:
            parts.append(f'low battery alarm {cfg.low_battery_mv} mV')
        if cfg.motor_type != 'keep':
            parts.append(f'motor type {cfg.motor_type}')
        if offsets:
            parts.append('PWM offsets ' + ', '.join(
                f'{i}: {v} us' for i, v in sorted(offsets.items())) + ' (read back)')
        return 'written: ' + '; '.join(parts) if parts else 'no desired settings'

    def _check_settings(self, now: float) -> None:
        # O37: a reboot shorter than offline_timeout_s leaves no other trace; offsets that no
        # longer read back as expected mean the board lost its settings: write them all again.
        if self._check_at is None or now < self._check_at or self._settings_due is not None:
            return
        self._check_at = now + self.config.settings_check_period_s
        with self._lock:
            expected = dict(self._expected_offsets)
        for servo_id, offset in sorted(expected.items()):
            try:
                got = self.link.read_pwm_offset(servo_id)
            except LinkError:
                return  # silence is the offline judgement's business
            if got != offset:
                self._log.warning(f'PWM servo {servo_id} offset reads {got} us instead of '
                                  f'{offset} us: the board was reset? writing the desired '
                                  'settings again')
                with self._lock:
                    self._settings_due = now
                    self._expected_offsets = {
                        i + 1: v for i, v in enumerate(self.config.pwm_servo_offsets_us)}
                return

    # -- bus servo poll -------------------------------------------------------------------------

    def _poll_servos(self, now: float, online: bool) -> None:
        cfg = self.config
        if not self._poll_ids or cfg.bus_servo_poll_hz <= 0 or not online:
            return
        if self._next_poll is None or now < self._next_poll:
            return
        period = 1.0 / cfg.bus_servo_poll_hz
        # Catch up without bursts: a late cycle does not cause several quick ones.
        self._next_poll = max(self._next_poll + period, now)
        with self._lock:
            ids = list(self._poll_ids)
        for servo_id in ids:
            # A pass of unanswered reads takes seconds: the board's silence is judged between
            # them, not only after the pass.
            if self._stop.is_set() or not self._tick(self._clock()):
                break
            self._poll_one(servo_id, now)
        with self._lock:
            states = [self._servos[i] for i in self._poll_ids if i in self._servos]
        self._call('states', states)

    def _poll_one(self, servo_id: int, now: float) -> None:
        with self._lock:
            status = self._servos.setdefault(servo_id, BusServoStatus(servo_id))
        if not status.online and status.failed_reads >= SERVO_OFFLINE_AFTER:
            if now < self._reprobe_at.get(servo_id, 0.0):
                return
            self._reprobe_at[servo_id] = now + SERVO_REPROBE_S
            retries: Optional[int] = 0
        else:
            retries = None
        telemetry = now >= self._telemetry_at.get(servo_id, 0.0)
        reads = [p.BusSub.READ_POSITION]
        if telemetry:
            reads += [p.BusSub.READ_VOLTAGE, p.BusSub.READ_TEMPERATURE, p.BusSub.READ_LOAD]
        values: Dict[int, p.BusValue] = {}
        error = ''
        for sub in reads:
            try:
                values[sub] = self.link.bus_read(sub, servo_id, retries=retries)
            except (LinkError, p.ProtocolError) as exc:
                error = str(exc)
                break
        if telemetry and not error:
            self._telemetry_at[servo_id] = now + self.config.bus_servo_telemetry_period_s
        with self._lock:
            status = self._servos.get(servo_id, BusServoStatus(servo_id))
            if error:
                failed = status.failed_reads + 1
                if failed == SERVO_OFFLINE_AFTER:
                    self._log.warning(f'bus servo {servo_id} offline after {failed} failed '
                                      f'reads: {error}')
                    self._reprobe_at[servo_id] = now + SERVO_REPROBE_S
                status = replace(status, failed_reads=failed, last_error=error,
                                 online=status.online and failed < SERVO_OFFLINE_AFTER)
            else:
                if not status.online:
                    self._log.info(f'bus servo {servo_id} online')
                status = _with_values(replace(status, online=True, failed_reads=0,
                                              last_error=''), values)
            self._servos[servo_id] = status

    def _mark_servos_offline(self, why: str) -> None:
        with self._lock:
            for servo_id, status in self._servos.items():
                self._servos[servo_id] = replace(status, online=False, last_error=why)
            states = [self._servos[i] for i in self._poll_ids if i in self._servos]
        self._telemetry_at.clear()
        if states:
            self._call('states', states)

    # -- reader thread --------------------------------------------------------------------------

    def _on_connection(self, up: bool, reason: str) -> None:
        now = self._clock()
        with self._lock:
            # O38: after (re)opening the port the motors' state is unknown; without a motor
            # command within motor_timeout_s they are stopped (the plan arms the watchdog).
            change = self._plan.connection(up, now)
        if change is not None:
            self._changed(change, now)
        self._wake.set()
        self._timer_wake.set()

    def _on_frames(self, now: float) -> None:
        # Issue 21 item 11(a): online from the frame itself, before anyone sees it published.
        with self._lock:
            change = self._plan.frame(now)
        if change is not None:
            self._changed(change, now)

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
                connected=link.connected, online=self._plan.online, status=self._status,
                port_error=link.serial.last_error,
                last_frame_age_s=None if last is None else max(0.0, now - last),
                battery_mv=battery, battery_low=battery is not None and battery < warn,
                battery_warn_mv=warn, frames=decoder.frames_decoded,
                crc_errors=decoder.checksum_errors, bytes_discarded=decoder.bytes_discarded,
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

    # -- command plumbing -----------------------------------------------------------------------

    def _refuse(self, exc: Refused) -> CommandResult:
        with self._lock:
            self._refusals[exc.cause] = self._refusals.get(exc.cause, 0) + 1
        return CommandResult(False, str(exc), exc.cause)

    def _require_online(self) -> None:
        if not self.link.connected:
            raise Refused('offline', f'port {self.config.port} is not open: '
                                     f'{self.link.serial.last_error or "connecting"}')
        if not self._plan.online:
            raise Refused('offline', f'the board is offline ({self._status})')

    def _send_all(self, frames: Sequence[bytes], what: str,
                  cancels: Sequence[int] = ()) -> CommandResult:
        try:
            for frame in frames:
                self._write(frame, cancels)
        except LinkError as exc:
            return CommandResult(False, f'{what}: not sent: {exc}')
        # The board never acknowledges these: "sent" is all anyone can know.
        return CommandResult(True, f'{what}: sent')

    def _command(self, build: Callable[[], Tuple[List[bytes], str]]) -> CommandResult:
        try:
            frames, what = build()
            self._require_online()
        except Refused as exc:
            return self._refuse(exc)
        return self._send_all(frames, what)

    # -- topics ---------------------------------------------------------------------------------

    def set_led(self, led_id: int, on_s: float, off_s: float, repeat: int) -> CommandResult:
        """Blink LED 1 or 2 (on 0 = off, off 0 = steady, repeat 0 = forever, O31)."""
        def build() -> Tuple[List[bytes], str]:
            led = _int('led_id', led_id, p.LED_IDS[0], p.LED_IDS[-1])
            on, off, count = _pattern(on_s, off_s, repeat)
            return [p.encode_led(led, on, off, count)], \
                f'LED {led}: on {on} ms, off {off} ms, repeat {count}'
        return self._command(build)

    def set_buzzer(self, frequency_hz: int, on_s: float, off_s: float,
                   repeat: int) -> CommandResult:
        """Beep (frequency 0 or on 0 = silent, off 0 = continuous, repeat 0 = forever)."""
        def build() -> Tuple[List[bytes], str]:
            freq = _int('frequency_hz', frequency_hz, 0, p.U16_MAX)
            on, off, count = _pattern(on_s, off_s, repeat)
            return [p.encode_buzzer(freq, on, off, count)], \
                f'buzzer: {freq} Hz, on {on} ms, off {off} ms, repeat {count}'
        return self._command(build)

    def set_rgb(self, indices: Sequence[int], red: Sequence[int], green: Sequence[int],
                blue: Sequence[int]) -> CommandResult:
        """Colour RGB pixels 1..2 (1-based here, 0-based on the wire, O18)."""
        def build() -> Tuple[List[bytes], str]:
            idx = _ints('indices', list(indices), 1, p.RGB_PIXEL_COUNT)
            _same_length(indices=idx, red=list(red), green=list(green), blue=list(blue))
            if not idx:
                raise Refused('empty', 'no pixel given')
            _distinct('indices', idx)
            r, g, b = (_ints(n, list(v), 0, 255) for n, v in
                       (('red', red), ('green', green), ('blue', blue)))
            pixels = [(i - 1, r[k], g[k], b[k]) for k, i in enumerate(idx)]
            return [p.encode_rgb(pixels)], 'RGB ' + ', '.join(
                f'{i}: ({r[k]}, {g[k]}, {b[k]})' for k, i in enumerate(idx))
        return self._command(build)

    def set_oled(self, line: int, text: str) -> CommandResult:
        """Show ``text`` (at most 23 bytes of UTF-8, O19) on OLED line 1 or 2."""
        def build() -> Tuple[List[bytes], str]:
            n = _int('line', line, p.OLED_LINES[0], p.OLED_LINES[-1])
            if not isinstance(text, str):
                raise Refused('out_of_range', f'text must be a string, got {text!r}')
            size = len(text.encode('utf-8'))
            if size > p.OLED_TEXT_MAX_BYTES:
                raise Refused('too_long', f'OLED text is {size} bytes of UTF-8, at most '
                                          f'{p.OLED_TEXT_MAX_BYTES} fit: {text!r}')
            return [p.encode_oled(n, text)], f'OLED line {n}: {text!r}'
        return self._command(build)

    def set_motor_speeds(self, motor_ids: Sequence[int], rps: Sequence[float]) -> CommandResult:
        """Set motor speeds (ids 1..4, O3; finite, |rps| <= 6). Any call restarts the timeout.

        An empty call sends nothing and only restarts the motor timeout (a keep-alive).
        """
        def build() -> Tuple[List[bytes], str]:
            ids = _ints('motor_ids', list(motor_ids), 1, p.MOTOR_COUNT)
            speeds = list(rps)
            _same_length(motor_ids=ids, rps=speeds)
            _distinct('motor_ids', ids)
            for value in speeds:
                if isinstance(value, bool) or not isinstance(value, (int, float)):
                    raise Refused('out_of_range', f'rps must be numbers, got {value!r}')
                if not math.isfinite(value):
                    raise Refused('not_finite', f'rps {value} is not finite')
                if abs(value) > p.MAX_RPS:
                    raise Refused('out_of_range', f'rps {value:g} is beyond +-{p.MAX_RPS:g} '
                                                  '(the fastest motor type)')
            if not ids:
                return [], 'motor timeout restarted'
            frame = p.encode_motor_speeds([(i - 1, float(v)) for i, v in zip(ids, speeds)])
            return [frame], 'motors ' + ', '.join(
                f'{i}: {v:g} r/s' for i, v in zip(ids, speeds))
        try:
            frames, what = build()
            self._require_online()
        except Refused as exc:
            return self._refuse(exc)
        ticket = object()
        with self._lock:
            # Zeros and empty calls restart the timeout too; a refused one does not: its
            # sender is not in control of the motors (O39).
            accepted = self._plan.motor_command(frames[0] if frames else None, self._clock(),
                                                ticket)
        if not accepted:
            return self._refuse(Refused('offline', f'the board is offline ({self._status})'))
        self._timer_wake.set()  # a new motor deadline: the timer may be sleeping past it
        if not frames:
            return CommandResult(True, f'{what}: sent')
        self._drain()
        error = self._outcome(ticket)
        if error is not None:
            return CommandResult(False, f'{what}: not sent: {error}')
        return CommandResult(True, f'{what}: sent')

    def stop_all_motors(self) -> CommandResult:
        """Set every motor's speed to 0 (MOTOR 0x03, mask 0x0F), offline or not; for shutdown.

        The stop goes out ahead of every queued frame; the answer comes once it has left.
        """
        ticket = object()
        with self._lock:
            self._plan.stop_motors(ticket)
        self._drain()
        error = self._outcome(ticket)
        if error is not None:
            return CommandResult(False, f'stop all motors: not sent: {error}')
        return CommandResult(True, 'stop all motors: sent')

    def set_pwm_servos(self, ids: Sequence[int], pulses_us: Sequence[int],
                       duration_s: float) -> CommandResult:
        """Move PWM servos 1..4 to 500..2500 us in 0.02..30 s, one frame (O10)."""
        def build() -> Tuple[List[bytes], str]:
            servo_ids = _ints('ids', list(ids), 1, p.PWM_SERVO_COUNT)
            pulses = _ints('pulses_us', list(pulses_us), p.PWM_PULSE_MIN_US,
                           p.PWM_PULSE_MAX_US)
            _same_length(ids=servo_ids, pulses_us=pulses)
            if not servo_ids:
                raise Refused('empty', 'no PWM servo given')
            _distinct('ids', servo_ids)
            duration = _seconds('duration_s', duration_s, PWM_DURATION_MIN_S,
                                PWM_DURATION_MAX_S)
            ms = max(p.PWM_DURATION_MIN_MS, _to_ms(duration))
            return [p.encode_pwm_move(ms, list(zip(servo_ids, pulses)))], \
                f'PWM servos {servo_ids} to {pulses} us in {ms} ms'
        return self._command(build)

    def set_bus_servos(self, ids: Sequence[int], positions: Sequence[int],
                       duration_s: float) -> CommandResult:
        """Move bus servos (ids 0..253) to positions 0..1000 in 0..65.535 s (O23)."""
        def build() -> Tuple[List[bytes], str]:
            servo_ids = _ints('ids', list(ids), 0, p.BUS_ID_MAX)
            targets = _ints('positions', list(positions), 0, p.BUS_POSITION_MAX)
            _same_length(ids=servo_ids, positions=targets)
            if not servo_ids:
                raise Refused('empty', 'no bus servo given')
            _distinct('ids', servo_ids)
            ms = _to_ms(_seconds('duration_s', duration_s, 0.0, BUS_DURATION_MAX_S))
            return (ms, list(zip(servo_ids, targets))), \
                f'bus servos {servo_ids} to {targets} in {ms} ms'
        try:
            (ms, items), what = build()
            self._require_online()
        except Refused as exc:
            return self._refuse(exc)
        with self._lock:
            # Issue 21 item 7: the newest target of each servo waits for room on the board's
            # servo bus; a later command for the same servo replaces it.
            accepted = self._plan.move(ms, items)
        if not accepted:
            return self._refuse(Refused('offline', f'the board is offline ({self._status})'))
        self._drain()
        with self._lock:
            waiting = [i for i, _ in items if i in self._plan.scheduler.targets]
        if waiting:
            self._timer_wake.set()
            return CommandResult(True, f'{what}: queued (the servo bus is busy; a newer target '
                                       f'of the same servo replaces it)')
        return CommandResult(True, f'{what}: sent')

    # -- services -------------------------------------------------------------------------------

    def _service(self, validate: Callable[[], Any]) -> Any:
        """Run ``validate`` and the online check; return its value or raise Refused."""
        value = validate()
        self._require_online()
        return value

    def _bus_ids(self, ids: Sequence[int], allow_empty: bool = False) -> List[int]:
        servo_ids = _ints('ids', list(ids), 0, p.BUS_ID_MAX)
        if not servo_ids and not allow_empty:
            raise Refused('empty', 'no bus servo given')
        _distinct('ids', servo_ids)
        return servo_ids

    def get_bus_servo_state(self, ids: Sequence[int]) -> BusServoStatesResult:
        """Read every field of each servo afresh (empty ``ids``: every polled servo).

        A servo with a failed read has ``online`` False; the message names it (O14).
        """
        try:
            servo_ids = self._service(lambda: self._bus_ids(ids, allow_empty=True)) \
                or self.bus_servo_ids
        except Refused as exc:
            r = self._refuse(exc)
            return BusServoStatesResult(False, r.message, (), r.cause)
        states, problems = [], []
        for servo_id in servo_ids:
            values: Dict[int, p.BusValue] = {}
            error = ''
            for sub in p.BUS_READ_FORMATS:
                if sub == p.BusSub.READ_ID:
                    continue
                try:
                    values[sub] = self.link.bus_read(sub, servo_id)
                except (LinkError, p.ProtocolError) as exc:
                    error = str(exc)
                    break
            status = _with_values(BusServoStatus(servo_id, online=not error,
                                                 last_error=error), values)
            if error:
                problems.append(f'servo {servo_id}: {error}')
            states.append(status)
            with self._lock:
                if servo_id in self._servos:
                    old = self._servos[servo_id]
                    self._servos[servo_id] = replace(
                        status, failed_reads=old.failed_reads + 1 if error else 0,
                        online=old.online if error else True)
        if problems:
            return BusServoStatesResult(False, '; '.join(problems), tuple(states))
        return BusServoStatesResult(True, f'read {len(states)} servo(s)', tuple(states))

    def set_bus_servo_torque(self, ids: Sequence[int], enable: bool) -> CommandResult:
        """Torque on (0x0C) or off (0x0B) for each servo (O6), checked by reading 0x0D."""
        try:
            servo_ids = self._service(lambda: self._bus_ids(ids))
        except Refused as exc:
            return self._refuse(exc)
        done, problems = [], []
        for servo_id in servo_ids:
            try:
                self._write(p.encode_bus_torque(servo_id, bool(enable)),
                            cancels=() if enable else (servo_id,))
                loaded = self.link.bus_read(p.BusSub.READ_LOAD, servo_id)
            except LinkError as exc:
                problems.append(f'servo {servo_id}: {exc}')
                continue
            if loaded != bool(enable):
                problems.append(f'servo {servo_id}: torque reads {"on" if loaded else "off"}')
            else:
                done.append(servo_id)
        state = 'on' if enable else 'off'
        if problems:
            return CommandResult(False, f'torque {state} for {done or "none"}; failed: '
                                 + '; '.join(problems))
        return CommandResult(True, f'torque {state} for {done} (read back)')

    def stop_bus_servos(self, ids: Sequence[int]) -> CommandResult:
        """Stop servos where they are (0x03)."""
        try:
            servo_ids = self._service(lambda: self._bus_ids(ids))
        except Refused as exc:
            return self._refuse(exc)
        # Queued targets of these servos are dropped: a stop is not followed by an old move.
        return self._send_all([p.encode_bus_stop(servo_ids)], f'stop bus servos {servo_ids}',
                              cancels=servo_ids)

    def set_bus_servo_id(self, servo_id: int, new_id: int) -> CommandResult:
        """Give a servo a new id; refused if ``new_id`` answers. Renamed in the poll list too."""
        def validate() -> Tuple[int, int]:
            old = _int('id', servo_id, 0, p.BUS_ID_MAX)
            new = _int('new_id', new_id, 0, p.BUS_ID_MAX)
            if old == new:
                raise Refused('out_of_range', f'servo {old} already has id {new}')
            return old, new
        try:
            old, new = self._service(validate)
            if self._answers(new):
                raise Refused('id_taken', f'id {new} is taken: a servo answers at it')
        except Refused as exc:
            return self._refuse(exc)
        except LinkError as exc:
            return CommandResult(False, f'could not check whether id {new} is free: {exc}')
        try:
            if not self._answers(old):
                return CommandResult(False, f'servo {old} does not answer; nothing written')
            self._write(p.encode_bus_write_id(old, new), cancels=(old,))
            if not self._answers(new):
                return CommandResult(False, f'id {new} written to servo {old}, but nothing '
                                            f'answers at {new}')
        except LinkError as exc:
            return CommandResult(False, f'set id {old} -> {new}: {exc}')
        with self._lock:
            if old in self._poll_ids:
                self._poll_ids[self._poll_ids.index(old)] = new
                self._servos[new] = replace(self._servos.pop(old, BusServoStatus(new)), id=new)
        return CommandResult(True, f'servo {old} now answers at id {new}')

    def _answers(self, servo_id: int) -> bool:
        """Whether a servo answers at ``servo_id`` (raises LinkError when the board is silent)."""
        try:
            self.link.bus_read(p.BusSub.READ_POSITION, servo_id)
        except BusServoFailure:
            return False
        return True

    def set_bus_servo_offset(self, servo_id: int, offset: int, save: bool) -> CommandResult:
        """Set a servo's deviation (-125..125), optionally saved to its flash; read back."""
        def validate() -> Tuple[int, int]:
            return (_int('id', servo_id, 0, p.BUS_ID_MAX),
                    _int('offset', offset, -p.BUS_OFFSET_MAX, p.BUS_OFFSET_MAX))
        try:
            sid, value = self._service(validate)
        except Refused as exc:
            return self._refuse(exc)
        try:
            self._write(p.encode_bus_set_offset(sid, value))
            if save:
                self._write(p.encode_bus_save_offset(sid))
            got = self.link.bus_read(p.BusSub.READ_OFFSET, sid)
        except LinkError as exc:
            return CommandResult(False, f'servo {sid} offset {value}: {exc}')
        if got != value:
            return CommandResult(False, f'servo {sid} offset reads {got}, not {value}')
        return CommandResult(True, f'servo {sid} offset {value}' + (' saved' if save else '')
                             + ' (read back)')

    def set_bus_servo_limits(self, servo_id: int, min_position: int, max_position: int,
                             min_voltage_mv: int, max_voltage_mv: int,
                             max_temperature_c: int) -> CommandResult:
        """Set a servo's limits; a pair of zeros (or temperature 0) is left as it is (O24)."""
        def validate() -> Tuple[int, list]:
            sid = _int('id', servo_id, 0, p.BUS_ID_MAX)
            jobs = []
            lo, hi = (_int(n, v, 0, p.U16_MAX) for n, v in
                      (('min_position', min_position), ('max_position', max_position)))
            if (lo, hi) != (0, 0):
                if not 0 <= lo <= hi <= p.BUS_POSITION_MAX:
                    raise Refused('out_of_range', f'position limits need 0 <= min <= max <= '
                                                  f'{p.BUS_POSITION_MAX}, got {lo}..{hi}')
                jobs.append((p.encode_bus_set_angle_limits(sid, lo, hi),
                             p.BusSub.READ_ANGLE_LIMITS, (lo, hi), 'position limits'))
            vlo, vhi = (_int(n, v, 0, p.U16_MAX) for n, v in
                        (('min_voltage_mv', min_voltage_mv), ('max_voltage_mv', max_voltage_mv)))
            if (vlo, vhi) != (0, 0):
                if not p.BUS_VOLTAGE_MIN_MV <= vlo <= vhi <= p.BUS_VOLTAGE_MAX_MV:
                    raise Refused('out_of_range', f'voltage limits need {p.BUS_VOLTAGE_MIN_MV} '
                                                  f'<= min <= max <= {p.BUS_VOLTAGE_MAX_MV} '
                                                  f'mV, got {vlo}..{vhi}')
                jobs.append((p.encode_bus_set_voltage_limits(sid, vlo, vhi),
                             p.BusSub.READ_VOLTAGE_LIMITS, (vlo, vhi), 'voltage limits'))
            temp = _int('max_temperature_c', max_temperature_c, 0, 255)
            if temp:
                if temp > p.BUS_TEMPERATURE_LIMIT_MAX_C:
                    raise Refused('out_of_range', f'max_temperature_c must be 1..'
                                                  f'{p.BUS_TEMPERATURE_LIMIT_MAX_C}, got {temp}')
                jobs.append((p.encode_bus_set_temperature_limit(sid, temp),
                             p.BusSub.READ_TEMPERATURE_LIMIT, temp, 'temperature limit'))
            return sid, jobs
        try:
            sid, jobs = self._service(validate)
        except Refused as exc:
            return self._refuse(exc)
        if not jobs:
            return CommandResult(True, f'servo {sid}: nothing to change (every limit is 0)')
        done = []
        for frame, sub, wanted, what in jobs:
            try:
                self._write(frame)
                got = self.link.bus_read(sub, sid)
            except LinkError as exc:
                return CommandResult(False, f'servo {sid} {what}: {exc}'
                                     + (f' (set before: {", ".join(done)})' if done else ''))
            if got != wanted:
                return CommandResult(False, f'servo {sid} {what} read {got}, not {wanted}')
            done.append(what)
        return CommandResult(True, f'servo {sid}: {", ".join(done)} set (read back)')

    def get_pwm_servo_state(self, ids: Sequence[int]) -> PwmServoStatesResult:
        """Read pulse and offset of PWM servos 1..4 (empty ``ids``: all four)."""
        def validate() -> List[int]:
            servo_ids = _ints('ids', list(ids), 1, p.PWM_SERVO_COUNT)
            _distinct('ids', servo_ids)
            return servo_ids or list(range(1, p.PWM_SERVO_COUNT + 1))
        try:
            servo_ids = self._service(validate)
        except Refused as exc:
            r = self._refuse(exc)
            return PwmServoStatesResult(False, r.message, cause=r.cause)
        pulses, offsets, problems = [], [], []
        for servo_id in servo_ids:
            try:
                pulses.append(self.link.read_pwm_pulse(servo_id))
                offsets.append(self.link.read_pwm_offset(servo_id))
            except LinkError as exc:
                pulses += [0] * (len(offsets) + 1 - len(pulses))
                offsets.append(0)
                problems.append(f'PWM servo {servo_id}: {exc}')
        if problems:
            return PwmServoStatesResult(False, '; '.join(problems), tuple(pulses),
                                        tuple(offsets))
        return PwmServoStatesResult(True, f'read PWM servos {servo_ids}', tuple(pulses),
                                    tuple(offsets))

    def set_pwm_servo_offset(self, servo_id: int, offset_us: int) -> CommandResult:
        """Set a PWM servo's offset (-100..100 us), read back; until the next (re)connect."""
        def validate() -> Tuple[int, int]:
            return (_int('id', servo_id, 1, p.PWM_SERVO_COUNT),
                    _int('offset_us', offset_us, -p.PWM_OFFSET_MAX_US, p.PWM_OFFSET_MAX_US))
        try:
            sid, value = self._service(validate)
        except Refused as exc:
            return self._refuse(exc)
        try:
            self._write(p.encode_pwm_set_offset(sid, value))
            got = self.link.read_pwm_offset(sid)
        except LinkError as exc:
            return CommandResult(False, f'PWM servo {sid} offset {value} us: {exc}')
        with self._lock:
            # What the board should now hold; a reset is what makes it differ (O37).
            self._expected_offsets[sid] = value
        if got != value:
            return CommandResult(False, f'PWM servo {sid} offset reads {got} us, not {value}')
        return CommandResult(True, f'PWM servo {sid} offset {value} us (read back)')


def _with_values(status: BusServoStatus, values: Dict[int, p.BusValue]) -> BusServoStatus:
    """Fold read values into a status (units: V, degrees C, rad)."""
    changes: Dict[str, Any] = {}
    s = p.BusSub
    if s.READ_POSITION in values:
        raw = int(values[s.READ_POSITION])  # type: ignore[arg-type]
        changes.update(position=raw, position_rad=bus_position_to_rad(raw))
    if s.READ_VOLTAGE in values:
        changes['voltage_v'] = values[s.READ_VOLTAGE] / 1000.0  # type: ignore[operator]
    if s.READ_TEMPERATURE in values:
        changes['temperature_c'] = float(values[s.READ_TEMPERATURE])  # type: ignore[arg-type]
    if s.READ_LOAD in values:
        changes['torque_enabled'] = bool(values[s.READ_LOAD])
    if s.READ_OFFSET in values:
        changes['offset'] = int(values[s.READ_OFFSET])  # type: ignore[arg-type]
    if s.READ_ANGLE_LIMITS in values:
        lo, hi = values[s.READ_ANGLE_LIMITS]  # type: ignore[misc]
        changes.update(min_position=lo, max_position=hi)
    if s.READ_VOLTAGE_LIMITS in values:
        lo, hi = values[s.READ_VOLTAGE_LIMITS]  # type: ignore[misc]
        changes.update(min_voltage_v=lo / 1000.0, max_voltage_v=hi / 1000.0)
    if s.READ_TEMPERATURE_LIMIT in values:
        changes['max_temperature_c'] = float(values[s.READ_TEMPERATURE_LIMIT])  # type: ignore
    return replace(status, **changes)
