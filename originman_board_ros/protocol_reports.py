"""OriginMan board: the board's frames (reports and replies), built and typed.

The builders serve the device model and golden frames in tests; the decoders never raise on
board output: a frame they cannot type becomes an :class:`UnknownFrame`.
"""

from __future__ import annotations

from dataclasses import dataclass
import struct
from typing import Optional, Sequence, Tuple, Union

from originman_board_ros.protocol_wire import (
    _int, BUS_READ_FORMATS, BUS_SUCCESS, BusSub, encode_frame, Frame, Function,
    KEY_EVENT_NAMES, parse_frame, ProtocolRangeError, PwmSub, SBUS_CHANNELS, SysSub, U16_MAX,
)


# ---------------------------------------------------------------------------------------------
# Board -> host frames (the device model sends them; tests build golden frames with them)
# ---------------------------------------------------------------------------------------------

def encode_battery_report(millivolts: int) -> bytes:
    """SYS 0x04: battery voltage in mV (O9)."""
    _int('battery [mV]', millivolts, 0, U16_MAX)
    return encode_frame(Function.SYS, struct.pack('<BH', SysSub.BATTERY_REPORT, millivolts))


def encode_key_report(key_id: int, event: int) -> bytes:
    """KEY: one button event (O17)."""
    _int('key id', key_id, 0, 255)
    _int('key event', event, 0, 255)
    return encode_frame(Function.KEY, bytes((key_id, event)))


def encode_imu_report(accel_g: Sequence[float], gyro_dps: Sequence[float]) -> bytes:
    """IMU: acceleration in g and angular rate in deg/s (O7), three axes each."""
    if len(accel_g) != 3 or len(gyro_dps) != 3:
        raise ProtocolRangeError('IMU sample', (accel_g, gyro_dps), 'three axes each')
    return encode_frame(Function.IMU, struct.pack('<6f', *accel_g, *gyro_dps))


def encode_gamepad_report(buttons: int, hat: int, lx: int, ly: int, rx: int,
                          ry: int) -> bytes:
    """GAMEPAD: button mask, hat and four int8 stick axes (O15)."""
    _int('gamepad buttons', buttons, 0, U16_MAX)
    _int('gamepad hat', hat, 0, 255)
    for name, value in (('lx', lx), ('ly', ly), ('rx', rx), ('ry', ry)):
        _int(f'gamepad {name}', value, -128, 127)
    return encode_frame(Function.GAMEPAD, struct.pack('<HB4b', buttons, hat, lx, ly, rx, ry))


def encode_sbus_report(channels: Sequence[int], ch17: bool = False, ch18: bool = False,
                       signal_loss: bool = False, failsafe: bool = False) -> bytes:
    """SBUS: 16 raw channel values and four flags (O16)."""
    if len(channels) != SBUS_CHANNELS:
        raise ProtocolRangeError('SBUS channels', len(channels), '16 values')
    for value in channels:
        _int('SBUS channel', value, -32768, 32767)
    return encode_frame(Function.SBUS, struct.pack(
        '<16h4B', *channels, bool(ch17), bool(ch18), bool(signal_loss), bool(failsafe)))


def encode_asr_report(data: bytes) -> bytes:
    """ASR (FUNCTION 12, O2): a speech module result, normally ``BB CC b3 b4 b5``."""
    return encode_frame(Function.ASR, bytes(data))


def encode_pwm_pulse_reply(servo_id: int, pulse_us: int) -> bytes:
    """Reply to PWM 0x05: ``id, 0x05, pulse``."""
    _int('PWM servo id', servo_id, 0, 255)
    _int('PWM pulse [us]', pulse_us, 0, U16_MAX)
    return encode_frame(Function.PWM_SERVO,
                        struct.pack('<BBH', servo_id, PwmSub.READ_PULSE, pulse_us))


def encode_pwm_offset_reply(servo_id: int, offset_us: int) -> bytes:
    """Reply to PWM 0x09: ``id, 0x09, offset`` (O11)."""
    _int('PWM servo id', servo_id, 0, 255)
    _int('PWM offset [us]', offset_us, -128, 127)
    return encode_frame(Function.PWM_SERVO,
                        struct.pack('<BBb', servo_id, PwmSub.READ_OFFSET, offset_us))


BusValue = Union[int, bool, Tuple[int, int], None]


def encode_bus_reply(servo_id: int, sub: int, value: BusValue = None,
                     success: int = BUS_SUCCESS) -> bytes:
    """Reply to a BUS_SERVO read: ``id, sub, success, value``; a failure carries zeros (O14)."""
    _int('bus servo id', servo_id, 0, 255)
    fmt = BUS_READ_FORMATS.get(sub)
    if fmt is None:
        raise ProtocolRangeError('bus servo read sub-command', sub, 'one of the nine reads')
    _int('success', success, -128, 127)
    if success != BUS_SUCCESS or value is None:
        args = bytes(struct.calcsize(fmt))
    else:
        values = tuple(value) if isinstance(value, (tuple, list)) else (int(value),)
        args = struct.pack(fmt, *values)
    return encode_frame(Function.BUS_SERVO, struct.pack('<BBb', servo_id, sub, success) + args)


# ---------------------------------------------------------------------------------------------
# Decoded board -> host messages
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class BatteryReport:
    """SYS 0x04: battery voltage in mV (O9; the SDK's "mAh" is wrong)."""

    millivolts: int
    raw: bytes = b''


@dataclass(frozen=True, slots=True)
class KeyReport:
    """KEY: one raw button event (O17)."""

    key_id: int
    event: int
    raw: bytes = b''

    @property
    def event_name(self) -> str:
        """The event's name (``click`` ...), ``unknown_0xNN`` for a code not in the table."""
        return KEY_EVENT_NAMES.get(self.event, f'unknown_0x{self.event:02x}')


@dataclass(frozen=True, slots=True)
class ImuReport:
    """IMU: acceleration in g, angular rate in deg/s (O7), as the board sends them."""

    accel_g: Tuple[float, float, float]
    gyro_dps: Tuple[float, float, float]
    raw: bytes = b''


@dataclass(frozen=True, slots=True)
class GamepadReport:
    """GAMEPAD: a USB gamepad's state (O15)."""

    buttons: int
    hat: int
    lx: int
    ly: int
    rx: int
    ry: int
    raw: bytes = b''


@dataclass(frozen=True, slots=True)
class SbusReport:
    """SBUS: raw channel values and flags (O16)."""

    channels: Tuple[int, ...]
    ch17: bool
    ch18: bool
    signal_loss: bool
    failsafe: bool
    raw: bytes = b''


@dataclass(frozen=True, slots=True)
class AsrReport:
    """ASR (FUNCTION 12): the speech module's result bytes (O2)."""

    data: bytes
    raw: bytes = b''


@dataclass(frozen=True, slots=True)
class PwmPulseReply:
    """Reply to PWM 0x05: the servo's current pulse, offset not included."""

    servo_id: int
    pulse_us: int
    raw: bytes = b''


@dataclass(frozen=True, slots=True)
class PwmOffsetReply:
    """Reply to PWM 0x09 (O11)."""

    servo_id: int
    offset_us: int
    raw: bytes = b''


@dataclass(frozen=True, slots=True)
class BusServoReply:
    """Reply to a BUS_SERVO read.

    ``servo_id`` echoes the requested id (O13). ``success`` is the raw int8: 0 ok, anything
    else (-1) means the servo gave no valid answer, and then ``value`` is None whatever the
    frame carried (O14). ``value`` is an int (position, mV, degrees C, id, offset), a bool
    (0x0D loaded) or a ``(low, high)`` pair (0x32, 0x36).
    """

    servo_id: int
    sub: int
    success: int
    value: BusValue
    raw: bytes = b''

    @property
    def ok(self) -> bool:
        """Whether the servo answered."""
        return self.success == BUS_SUCCESS


@dataclass(frozen=True, slots=True)
class UnknownFrame:
    """A CRC-valid frame this module cannot type (unknown FUNCTION, sub-command or LENGTH)."""

    function: int
    data: bytes
    reason: str
    raw: bytes = b''


BoardMessage = Union[BatteryReport, KeyReport, ImuReport, GamepadReport, SbusReport, AsrReport,
                     PwmPulseReply, PwmOffsetReply, BusServoReply, UnknownFrame]

_BUS_REPLY_LENGTHS = {sub: 3 + struct.calcsize(fmt) for sub, fmt in BUS_READ_FORMATS.items()}


def _unknown(frame: Frame, reason: str) -> UnknownFrame:
    return UnknownFrame(frame.function, frame.data, reason, frame.raw)


def _length(frame: Frame, expected: int, what: str) -> Optional[UnknownFrame]:
    if len(frame.data) != expected:
        return _unknown(frame, f'{what} with LENGTH {len(frame.data)}, expected {expected}')
    return None


def decode_board_frame(frame: Frame) -> BoardMessage:
    """Type one board -> host frame; anything unexpected becomes an :class:`UnknownFrame`."""
    f, data, raw = frame.function, frame.data, frame.raw
    if f == Function.SYS:
        if data[:1] == bytes((SysSub.BATTERY_REPORT,)):
            return _length(frame, 3, 'battery report') or BatteryReport(
                struct.unpack_from('<H', data, 1)[0], raw)
        return _unknown(frame, 'SYS frame that is not a battery report')
    if f == Function.KEY:
        return _length(frame, 2, 'key report') or KeyReport(data[0], data[1], raw)
    if f == Function.IMU:
        bad = _length(frame, 24, 'IMU report')
        if bad:
            return bad
        values = struct.unpack('<6f', data)
        return ImuReport(values[:3], values[3:], raw)
    if f == Function.GAMEPAD:
        return _length(frame, 7, 'gamepad report') or GamepadReport(
            *struct.unpack('<HB4b', data), raw)
    if f == Function.SBUS:
        bad = _length(frame, 36, 'SBUS report')
        if bad:
            return bad
        values = struct.unpack('<16h4B', data)
        return SbusReport(values[:16], *(bool(v) for v in values[16:]), raw)
    if f == Function.ASR:
        return AsrReport(data, raw)
    if f == Function.PWM_SERVO:
        sub = data[1] if len(data) > 1 else None
        if sub == PwmSub.READ_PULSE:
            return _length(frame, 4, 'PWM pulse reply') or PwmPulseReply(
                data[0], struct.unpack_from('<H', data, 2)[0], raw)
        if sub == PwmSub.READ_OFFSET:
            return _length(frame, 3, 'PWM offset reply') or PwmOffsetReply(
                data[0], struct.unpack_from('<b', data, 2)[0], raw)
        return _unknown(frame, 'PWM_SERVO reply with an unknown sub-command')
    if f == Function.BUS_SERVO:
        sub = data[1] if len(data) > 1 else None
        fmt = BUS_READ_FORMATS.get(sub)  # type: ignore[arg-type]
        if fmt is None:
            return _unknown(frame, 'BUS_SERVO reply with an unknown sub-command')
        bad = _length(frame, _BUS_REPLY_LENGTHS[sub], f'bus servo reply 0x{sub:02X}')
        if bad:
            return bad
        success = struct.unpack_from('<b', data, 2)[0]
        value: BusValue = None
        if success == BUS_SUCCESS:
            values = struct.unpack_from(fmt, data, 3)
            if len(values) == 2:
                value = (values[0], values[1])
            elif sub == BusSub.READ_LOAD:
                value = bool(values[0])
            else:
                value = values[0]
        return BusServoReply(data[0], sub, success, value, raw)
    return _unknown(frame, f'FUNCTION {f} is not sent by the board')


def decode_board_bytes(raw: bytes) -> BoardMessage:
    """Check one complete board frame (header, LENGTH, CRC) and type it."""
    return decode_board_frame(parse_frame(raw))
