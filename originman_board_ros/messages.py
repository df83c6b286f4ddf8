"""The OriginMan core's samples and snapshots as ROS messages and diagnostics: pure functions.

No node, no clock read, no I/O: each builder takes what it shows and the stamp. The node calls
them from the threads the core reports on (the IMU from the link's reader thread), so they are
kept lean: one message object, fields set in place.
"""

from __future__ import annotations

from collections import deque
import math
import struct
from typing import Deque, Dict, Iterable, List, Optional, Sequence, Tuple

from builtin_interfaces.msg import Time
from sensor_msgs.msg import BatteryState, Imu, JointState, Joy
from std_msgs.msg import Header, UInt8MultiArray
from uav_serial_drivers.msg import BusServoState, BusServoStateArray, ButtonEvent, SbusFrame

from originman_board_ros.core import (AsrSample, BatterySample, BusServoStatus, ButtonSample,
                                      GamepadSample, ImuSample, OriginManSnapshot, SbusSample)
from uav_serial_common import cdr
from uav_serial_common.diagnostics import ERROR, OK, STALE, Status, WARN

NAN = math.nan


def joint_name(servo_id: int) -> str:
    """Return the joint name of bus servo ``servo_id`` (the contract's ``bus_servo_<id>``)."""
    return f'bus_servo_{servo_id}'


# ---------------------------------------------------------------------------------------------
# Reports
# ---------------------------------------------------------------------------------------------

def imu_msg(sample: ImuSample, stamp: Time, frame_id: str) -> Imu:
    """Return ``~/imu``: m/s^2 and rad/s (O7); no orientation (covariance[0] = -1, REP-145).

    The other two covariances stay all zero: "unknown" in sensor_msgs/Imu's own words.
    """
    msg = Imu()
    msg.orientation_covariance[0] = -1.0
    fill_imu(msg, sample, stamp.sec, stamp.nanosec, frame_id)
    return msg


def fill_imu(msg: Imu, sample: ImuSample, sec: int, nanosec: int, frame_id: str) -> Imu:
    """Write one report and its stamp into an ``Imu`` made by :func:`imu_msg`."""
    header = msg.header
    header.stamp.sec = sec
    header.stamp.nanosec = nanosec
    header.frame_id = frame_id
    a = msg.linear_acceleration
    a.x, a.y, a.z = sample.linear_acceleration
    w = msg.angular_velocity
    w.x, w.y, w.z = sample.angular_velocity
    return msg


class ImuPacker(cdr.FramedPacker):
    """``~/imu`` as the serialized (CDR, little endian) bytes rclpy would make of :func:`imu_msg`.

    The IMU is the one stream that runs all the time at up to 100 Hz, and building an ``Imu``
    and converting it for the middleware cost more than the rest of its path together (bench:
    ``cpu_originman_pct``). Everything but the stamp and the six values is constant, so the
    bytes are a few joins; rclpy publishes ``bytes`` as a serialized message.
    ``test_originman_messages`` deserializes them with ``rclpy.serialization`` and compares.
    """

    _VECTOR = struct.Struct('<3d')
    _ZERO9 = struct.pack('<9d', *([0.0] * 9))
    # Orientation: the default quaternion (0, 0, 0, 1), unknown (covariance[0] = -1).
    _ORIENTATION = struct.pack('<4d', 0.0, 0.0, 0.0, 1.0) + \
        struct.pack('<9d', -1.0, *([0.0] * 8))

    def _layout(self, frame: bytes, offset: int) -> tuple:
        return (frame + bytes(-offset % 8),)  # the doubles that follow are 8-aligned

    def pack(self, sample: ImuSample, sec: int, nanosec: int) -> bytes:
        """Return the serialized ``~/imu`` of one report."""
        vector, zero9 = self._VECTOR.pack, self._ZERO9
        return b''.join((cdr.ENCAPSULATION, cdr.STAMP.pack(sec, nanosec), self._parts[0],
                         self._ORIENTATION, vector(*sample.angular_velocity), zero9,
                         vector(*sample.linear_acceleration), zero9))


def battery_msg(sample: BatterySample, stamp: Time, frame_id: str) -> BatteryState:
    """Return ``~/battery``: voltage in V (O9), NaN for everything the board does not measure."""
    return BatteryState(
        header=Header(stamp=stamp, frame_id=frame_id), voltage=float(sample.voltage_v),
        temperature=NAN, current=NAN, charge=NAN, capacity=NAN, design_capacity=NAN,
        percentage=NAN, present=True,
        power_supply_status=BatteryState.POWER_SUPPLY_STATUS_UNKNOWN,
        power_supply_health=BatteryState.POWER_SUPPLY_HEALTH_UNKNOWN,
        power_supply_technology=BatteryState.POWER_SUPPLY_TECHNOLOGY_UNKNOWN)


def button_msg(sample: ButtonSample, stamp: Time, frame_id: str) -> ButtonEvent:
    """Return ``~/button``: one raw key event with its name (O17)."""
    return ButtonEvent(header=Header(stamp=stamp, frame_id=frame_id), key_id=sample.key_id,
                       event=sample.event, event_name=sample.event_name)


def sbus_msg(sample: SbusSample, stamp: Time, frame_id: str) -> SbusFrame:
    """Return ``~/sbus``: raw channels (O16) and (raw - 992) / 820 clamped to -1..1."""
    return SbusFrame(header=Header(stamp=stamp, frame_id=frame_id),
                     channels=list(sample.channels), normalized=list(sample.normalized),
                     ch17=sample.ch17, ch18=sample.ch18, signal_loss=sample.signal_loss,
                     failsafe=sample.failsafe)


def joy_msg(sample: GamepadSample, stamp: Time, frame_id: str) -> Joy:
    """Return ``~/joy``: [lx, ly, rx, ry, hat_x, hat_y] and the 16 button bits (O15)."""
    return Joy(header=Header(stamp=stamp, frame_id=frame_id), axes=list(sample.axes),
               buttons=list(sample.buttons))


def asr_msg(sample: AsrSample) -> UInt8MultiArray:
    """Return ``~/asr``: the speech-recognition report's bytes (O2)."""
    return UInt8MultiArray(data=list(sample.data))


# ---------------------------------------------------------------------------------------------
# Bus servos
# ---------------------------------------------------------------------------------------------

def bus_servo_state(status: BusServoStatus) -> BusServoState:
    """Return one ``BusServoState`` (NaN where not read; limits 0 until ``get_state``)."""
    return BusServoState(
        id=status.id, online=status.online,
        position=max(-32768, min(32767, int(status.position))),
        position_rad=float(status.position_rad), voltage_v=float(status.voltage_v),
        temperature_c=float(status.temperature_c), torque_enabled=status.torque_enabled,
        offset=max(-128, min(127, int(status.offset))),
        min_position=max(0, min(65535, int(status.min_position))),
        max_position=max(0, min(65535, int(status.max_position))),
        min_voltage_v=float(status.min_voltage_v), max_voltage_v=float(status.max_voltage_v),
        max_temperature_c=float(status.max_temperature_c),
        failed_reads=max(0, int(status.failed_reads)), error=status.last_error)


def bus_servo_states_msg(statuses: Sequence[BusServoStatus], stamp: Time,
                         frame_id: str) -> BusServoStateArray:
    """Return ``~/bus_servo/states``: every polled servo, offline ones with ``online`` false."""
    return BusServoStateArray(header=Header(stamp=stamp, frame_id=frame_id),
                              servos=[bus_servo_state(s) for s in statuses])


def joint_states_msg(statuses: Iterable[BusServoStatus], stamp: Time,
                     frame_id: str) -> Optional[JointState]:
    """Return ``joint_states`` for the online servos (None when none is online)."""
    online = [s for s in statuses if s.online and math.isfinite(s.position_rad)]
    if not online:
        return None
    return JointState(header=Header(stamp=stamp, frame_id=frame_id),
                      name=[joint_name(s.id) for s in online],
                      position=[float(s.position_rad) for s in online])


# ---------------------------------------------------------------------------------------------
# Diagnostics
# ---------------------------------------------------------------------------------------------

class ReportRates:
    """Rates of the board's reports from their counters, over a sliding window of samples."""

    def __init__(self, window_s: float = 5.0) -> None:
        self.window_s = window_s
        self._samples: Deque[Tuple[float, Dict[str, int]]] = deque()

    def update(self, now: float, counts: Dict[str, int]) -> Dict[str, float]:
        """Add the counters read at ``now``; return reports per second of each kind (NaN: n/a)."""
        samples = self._samples
        samples.append((now, dict(counts)))
        while len(samples) > 2 and now - samples[1][0] >= self.window_s:
            samples.popleft()
        t0, first = samples[0]
        dt = now - t0
        if dt < 0.5:
            return {k: NAN for k in counts}
        return {k: (counts[k] - first.get(k, 0)) / dt for k in counts}


def _hz(value: float) -> str:
    return 'n/a' if math.isnan(value) else f'{value:.1f}'


def link_status(stat: Status, snap: OriginManSnapshot, rates: Dict[str, float], baud: int,
                send_failures: int) -> None:
    """Fill the ``link`` status: ERROR while offline; counters, report rates, refusals."""
    if not snap.online:
        stat.summary(ERROR, f'offline: {snap.status}')
    elif not snap.settings_ok:
        stat.summary(WARN, f'online; desired settings not confirmed: {snap.settings_message}')
    else:
        stat.summary(OK, 'online')
    age = snap.last_frame_age_s
    for key, value in (
            ('baud', baud), ('port open', snap.port_open), ('state', snap.status),
            ('port error', snap.port_error),
            ('last frame age [s]', 'never' if age is None else f'{age:.3f}'),
            ('frames', snap.frames_decoded), ('crc errors', snap.checksum_errors),
            ('bytes discarded', snap.bytes_discarded),
            ('unknown functions', snap.unknown_functions),
            ('unknown frames', snap.unknown_frames),
            ('unexpected replies', snap.unexpected_replies),
            ('imu rate [Hz]', _hz(rates.get('imu', NAN))),
            ('battery rate [Hz]', _hz(rates.get('battery', NAN))),
            ('reports', ', '.join(f'{k} {v}' for k, v in sorted(snap.reports.items()))),
            ('reads', snap.reads), ('read timeouts', snap.read_timeouts),
            ('read failures (success -1)', snap.read_failures),
            ('reconnects', snap.reconnects), ('motor timeout stops', snap.watchdog_stops),
            ('bus servo targets queued', snap.bus_targets_queued),
            ('bus servo targets replaced by newer', snap.bus_targets_replaced),
            ('board backlog [ms]', f'{snap.board_backlog_s * 1000:.1f}'),
            ('settings', snap.settings_message),
            ('refused commands', sum(snap.refusals.values())),
            ('commands not sent (port closed)', send_failures)):
        stat.add(key, value)
    for cause, count in sorted(snap.refusals.items()):
        stat.add(f'refused: {cause}', count)


def battery_status(stat: Status, snap: OriginManSnapshot) -> None:
    """Fill the ``battery`` status: WARN below the alarm threshold (6300 mV when -1)."""
    mv = snap.battery_mv
    if mv is None:
        stat.summary(STALE, 'no battery report yet')
    elif snap.battery_low:
        stat.summary(WARN, f'battery low: {mv / 1000:.2f} V < {snap.battery_warn_mv / 1000:.2f} V')
    else:
        stat.summary(OK, f'{mv / 1000:.2f} V')
    stat.add('voltage [V]', 'n/a' if mv is None else f'{mv / 1000:.3f}')
    stat.add('warning below [V]', f'{snap.battery_warn_mv / 1000:.3f}')
    if not snap.online and mv is not None:
        stat.add('note', 'the board is offline: this is the last value received')


def bus_servo_status(stat: Status, snap: OriginManSnapshot) -> None:
    """Fill the ``bus servos`` status: WARN when a polled servo is offline; failed reads."""
    servos = snap.bus_servos
    offline: List[int] = [s.id for s in servos if not s.online]
    if not servos:
        stat.summary(OK, 'no bus servos polled (bus_servo_ids is empty)')
    elif not snap.online:
        stat.summary(WARN, f'the board is offline: servos {offline} unknown')
    elif offline:
        stat.summary(WARN, f'offline: {offline}')
    else:
        stat.summary(OK, f'{len(servos)} online')
    for s in servos:
        text = (f'{"online" if s.online else "OFFLINE"}, position {s.position} '
                f'({s.position_rad:.3f} rad), {s.voltage_v:.2f} V, {s.temperature_c:.0f} degC, '
                f'torque {"on" if s.torque_enabled else "off"}, failed reads {s.failed_reads}')
        if s.last_error:
            text += f'; last error: {s.last_error}'
        stat.add(f'servo {s.id}', text)
