"""The OriginMan core's values: unit conversions, its configuration, its samples and results.

No state, no threads: frozen dataclasses and pure functions. :mod:`originman_board_ros.core`
re-exports every name (import them from there). What a command or service answers is the
drivers' one :class:`~uav_serial_common.result.Result`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import math
from typing import Dict, List, Optional, Tuple

from originman_board_ros import protocol as p
from originman_board_ros.link import READ_TIMEOUT_S

MOTOR_TYPES = ('keep',) + tuple(t.name for t in p.MotorType)


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
    read_timeout_s: float = READ_TIMEOUT_S
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
class PwmServoStates:
    """The value of :meth:`OriginManCore.get_pwm_servo_state`'s result (0 where a read failed)."""

    pulses_us: Tuple[int, ...] = ()
    offsets_us: Tuple[int, ...] = ()


@dataclass(frozen=True)
class OriginManSnapshot:
    """The core's state for diagnostics, taken at once under its lock."""

    port_open: bool
    online: bool
    status: str
    port_error: str
    last_frame_age_s: Optional[float]
    battery_mv: Optional[int]
    battery_low: bool
    battery_warn_mv: int
    frames_decoded: int
    checksum_errors: int
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
    """A command the core will not send; ``cause`` is a short key for counting.

    Raised inside the core only: a caller receives ``Result.refused(cause, message)``
    (``out_of_range``, ``not_finite``, ``length_mismatch``, ``duplicate``, ``empty``,
    ``too_long``, ``offline``, ``id_taken``).
    """

    def __init__(self, cause: str, message: str) -> None:
        self.cause = cause
        super().__init__(message)


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)
