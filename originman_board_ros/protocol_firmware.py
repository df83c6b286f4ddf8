"""OriginMan board: host frames as the firmware reads them, for the device model.

:class:`BoardParser` is the firmware's own parser with its quirks (O21, O22);
:func:`decode_host_command` types a frame as the firmware's handlers read it.
"""

from __future__ import annotations

from dataclasses import dataclass
import struct
from typing import Optional, Tuple, Union

from originman_board_ros.protocol_wire import (
    BOARD_FUNCTION_LIMIT, BUS_READ_FORMATS, BusSub, crc8, Function, MOTOR_COUNT, MotorSub,
    PwmSub, SysSub,
)


# ---------------------------------------------------------------------------------------------
# Host -> board frames as the firmware reads them (for the device model)
# ---------------------------------------------------------------------------------------------

BOARD_BUFFER = 257
"""The firmware's ``data_and_checksum`` buffer: 255 data bytes, the CRC, one spare."""


@dataclass(frozen=True, slots=True)
class HostFrame:
    """A frame the firmware's parser accepted: FUNCTION, LENGTH and its frame buffer.

    ``buffer`` is what the handlers read (O21/O33): the DATA bytes, then the CRC byte (the
    firmware stores it right behind DATA), then zeros (the buffer is cleared after each frame).
    """

    function: int
    length: int
    buffer: bytes
    raw: bytes

    @property
    def data(self) -> bytes:
        """The DATA bytes as sent."""
        return self.buffer[:self.length]

    def unpack(self, fmt: str, offset: int) -> tuple:
        """Read a field the way a handler's packed struct does; past the buffer reads 0."""
        size = struct.calcsize(fmt)
        chunk = self.buffer[offset:offset + size]
        return struct.unpack(fmt, chunk + bytes(size - len(chunk)))


class BoardParser:
    """The firmware's byte-wise receiver (``packet_recv``) with its quirks (O21, O22).

    * After a 0xAA, a byte other than 0x55 sends it back to waiting for 0xAA *without*
      looking at that byte again, so ``AA AA 55 ...`` loses the frame.
    * FUNCTION >= 12 drops the frame the same way, byte not re-examined.
    * No inter-byte timeout: a truncated frame swallows what follows until LENGTH is met.
    * A CRC mismatch discards the frame silently (no NAK).
    """

    _START1, _START2, _FUNCTION, _LENGTH, _DATA, _CRC = range(6)

    def __init__(self) -> None:
        self._state = self._START1
        self._function = 0
        self._length = 0
        self._data = bytearray()
        self._raw = bytearray()
        self.frames_decoded = 0
        self.checksum_errors = 0
        self.functions_dropped = 0
        self.bytes_discarded = 0

    @property
    def idle(self) -> bool:
        """Whether the parser waits for the start of a frame."""
        return self._state == self._START1

    def reset(self) -> None:
        """Back to waiting for 0xAA (a reboot); counters are kept."""
        self._state = self._START1
        self._data.clear()
        self._raw.clear()

    def feed(self, data: Union[bytes, bytearray]) -> list:
        """Run the bytes through the state machine; return the frames whose CRC matched."""
        out = []
        for byte in data:
            state = self._state
            self._raw.append(byte)
            if state == self._START1:
                if byte == 0xAA:
                    self._state = self._START2
                    self._raw[:] = b'\xaa'
                else:
                    self.bytes_discarded += 1
                    self._raw.clear()
            elif state == self._START2:
                if byte == 0x55:
                    self._state = self._FUNCTION
                else:
                    self._lose()
            elif state == self._FUNCTION:
                if byte < BOARD_FUNCTION_LIMIT:
                    self._function = byte
                    self._state = self._LENGTH
                else:
                    self.functions_dropped += 1
                    self._lose()
            elif state == self._LENGTH:
                self._length = byte
                self._data.clear()
                self._state = self._DATA if byte else self._CRC
            elif state == self._DATA:
                self._data.append(byte)
                if len(self._data) >= self._length:
                    self._state = self._CRC
            else:
                body = bytes((self._function, self._length)) + self._data
                if crc8(body) == byte:
                    buffer = bytes(self._data) + bytes((byte,))
                    buffer += bytes(BOARD_BUFFER - len(buffer))
                    out.append(HostFrame(self._function, self._length, buffer,
                                         bytes(self._raw)))
                    self.frames_decoded += 1
                else:
                    self.checksum_errors += 1
                self._state = self._START1
                self._raw.clear()
        return out

    def _lose(self) -> None:
        self.bytes_discarded += len(self._raw)
        self._raw.clear()
        self._state = self._START1


# Typed host commands, as the firmware's handlers read them.

@dataclass(frozen=True, slots=True)
class SetBatteryLimit:
    """SYS 0x01."""

    limit_mv: int


@dataclass(frozen=True, slots=True)
class SetLed:
    """LED pattern (any led_id; the board serves 1 and 2 only, O25)."""

    led_id: int
    on_ms: int
    off_ms: int
    repeat: int


@dataclass(frozen=True, slots=True)
class SetBuzzer:
    """BUZZER pattern."""

    frequency_hz: int
    on_ms: int
    off_ms: int
    repeat: int


@dataclass(frozen=True, slots=True)
class SetMotorSpeeds:
    """MOTOR 0x00 (one item) or 0x01: ``((wire_id, rps), ...)`` as read, ids unchecked."""

    sub: int
    items: Tuple[Tuple[int, float], ...]


@dataclass(frozen=True, slots=True)
class StopMotors:
    """MOTOR 0x02 (one wire id) or 0x03 (mask bits 0..3, O4): the wire ids set to 0."""

    sub: int
    wire_ids: Tuple[int, ...]


@dataclass(frozen=True, slots=True)
class SetMotorType:
    """MOTOR 0x05 with the raw type byte (the board takes anything but 0..3 as 0, O5)."""

    type_code: int


@dataclass(frozen=True, slots=True)
class PwmMove:
    """PWM_SERVO 0x01 or 0x03: ``((id, pulse_us), ...)`` in ``duration_ms`` (unclamped)."""

    sub: int
    duration_ms: int
    items: Tuple[Tuple[int, int], ...]


@dataclass(frozen=True, slots=True)
class PwmRead:
    """PWM_SERVO 0x05 or 0x09."""

    sub: int
    servo_id: int


@dataclass(frozen=True, slots=True)
class PwmSetOffset:
    """PWM_SERVO 0x07."""

    servo_id: int
    offset_us: int


@dataclass(frozen=True, slots=True)
class BusMove:
    """BUS_SERVO 0x01."""

    duration_ms: int
    items: Tuple[Tuple[int, int], ...]


@dataclass(frozen=True, slots=True)
class BusStop:
    """BUS_SERVO 0x03."""

    ids: Tuple[int, ...]


@dataclass(frozen=True, slots=True)
class BusRead:
    """Any of the nine BUS_SERVO reads."""

    sub: int
    servo_id: int


@dataclass(frozen=True, slots=True)
class BusTorque:
    """BUS_SERVO 0x0C (enable) or 0x0B (disable), O6."""

    servo_id: int
    enable: bool


@dataclass(frozen=True, slots=True)
class BusWriteId:
    """BUS_SERVO 0x10."""

    servo_id: int
    new_id: int


@dataclass(frozen=True, slots=True)
class BusSetOffset:
    """BUS_SERVO 0x20 (the raw int8)."""

    servo_id: int
    offset: int


@dataclass(frozen=True, slots=True)
class BusSaveOffset:
    """BUS_SERVO 0x24."""

    servo_id: int


@dataclass(frozen=True, slots=True)
class BusSetLimits:
    """BUS_SERVO 0x30 (position) or 0x34 (voltage, mV), values as sent (O24)."""

    sub: int
    servo_id: int
    low: int
    high: int


@dataclass(frozen=True, slots=True)
class BusSetTemperatureLimit:
    """BUS_SERVO 0x38 (value as sent)."""

    servo_id: int
    max_c: int


@dataclass(frozen=True, slots=True)
class SetOledText:
    """OLED: line and text bytes as the board copies them (``n`` bytes, even beyond 23)."""

    line: int
    text: bytes


@dataclass(frozen=True, slots=True)
class SetRgb:
    """RGB: ``((index, r, g, b), ...)`` with 0-based indices as sent (O18)."""

    pixels: Tuple[Tuple[int, int, int, int], ...]


@dataclass(frozen=True, slots=True)
class IgnoredCommand:
    """A frame the firmware has no handler for (FUNCTION 6..9, unknown sub-commands)."""

    function: int
    sub: Optional[int]
    reason: str


HostCommand = Union[SetBatteryLimit, SetLed, SetBuzzer, SetMotorSpeeds, StopMotors,
                    SetMotorType, PwmMove, PwmRead, PwmSetOffset, BusMove, BusStop, BusRead,
                    BusTorque, BusWriteId, BusSetOffset, BusSaveOffset, BusSetLimits,
                    BusSetTemperatureLimit, SetOledText, SetRgb, IgnoredCommand]


def _items(frame: HostFrame, count: int, start: int, fmt: str) -> tuple:
    size = struct.calcsize(fmt)
    return tuple(frame.unpack(fmt, start + k * size) for k in range(count))


def decode_host_command(frame: HostFrame) -> HostCommand:
    """Read a host frame the way the firmware's handler for its FUNCTION does (O21, O33).

    Fields come from the frame buffer (missing bytes: the CRC, then zeros; extra bytes are
    never looked at); counts are taken as sent, however many items the frame really holds.
    """
    f = frame.function
    sub = frame.buffer[0]
    if f == Function.SYS:
        if sub == SysSub.BATTERY_LIMIT:
            return SetBatteryLimit(frame.unpack('<H', 1)[0])
        return IgnoredCommand(f, sub, 'unknown SYS sub-command (O26)')
    if f == Function.LED:
        return SetLed(*frame.unpack('<BHHH', 0))
    if f == Function.BUZZER:
        return SetBuzzer(*frame.unpack('<HHHH', 0))
    if f == Function.MOTOR:
        return _decode_motor(frame, sub)
    if f == Function.PWM_SERVO:
        return _decode_pwm(frame, sub)
    if f == Function.BUS_SERVO:
        return _decode_bus(frame, sub)
    if f == Function.OLED:
        n = frame.buffer[1]
        return SetOledText(sub, frame.buffer[2:2 + n] + bytes(max(0, n + 2 - BOARD_BUFFER)))
    if f == Function.RGB:
        n = frame.buffer[1]
        return SetRgb(_items(frame, n, 2, '<BBBB'))
    return IgnoredCommand(f, None, f'no handler for FUNCTION {f}')


def _decode_motor(frame: HostFrame, sub: int) -> HostCommand:
    if sub == MotorSub.SET_ONE:
        wire_id, speed = frame.unpack('<Bf', 1)
        return SetMotorSpeeds(sub, ((wire_id, speed),))
    if sub == MotorSub.SET_MANY:
        return SetMotorSpeeds(sub, _items(frame, frame.buffer[1], 2, '<Bf'))
    if sub == MotorSub.STOP_ONE:
        return StopMotors(sub, (frame.buffer[1],))
    if sub == MotorSub.STOP_MASK:
        mask = frame.buffer[1]
        # The firmware looks at bits 0..3 only.
        return StopMotors(sub, tuple(i for i in range(MOTOR_COUNT) if mask & (1 << i)))
    if sub == MotorSub.SET_TYPE:
        return SetMotorType(frame.buffer[1])
    return IgnoredCommand(Function.MOTOR, sub, 'unknown MOTOR sub-command')


def _decode_pwm(frame: HostFrame, sub: int) -> HostCommand:
    if sub == PwmSub.MOVE_MANY:
        duration, n = frame.unpack('<HB', 1)
        return PwmMove(sub, duration, _items(frame, n, 4, '<BH'))
    if sub == PwmSub.MOVE_ONE:
        duration, servo_id, pulse = frame.unpack('<HBH', 1)
        return PwmMove(sub, duration, ((servo_id, pulse),))
    if sub in (PwmSub.READ_PULSE, PwmSub.READ_OFFSET):
        return PwmRead(sub, frame.buffer[1])
    if sub == PwmSub.SET_OFFSET:
        return PwmSetOffset(*frame.unpack('<Bb', 1))
    return IgnoredCommand(Function.PWM_SERVO, sub, 'unknown PWM_SERVO sub-command')


def _decode_bus(frame: HostFrame, sub: int) -> HostCommand:
    servo_id = frame.buffer[1]
    if sub == BusSub.MOVE:
        duration, n = frame.unpack('<HB', 1)
        return BusMove(duration, _items(frame, n, 4, '<BH'))
    if sub == BusSub.STOP:
        n = frame.buffer[1]
        return BusStop(tuple(v[0] for v in _items(frame, n, 2, '<B')))
    if sub in BUS_READ_FORMATS:
        return BusRead(sub, servo_id)
    if sub in (BusSub.LOAD, BusSub.UNLOAD):
        return BusTorque(servo_id, sub == BusSub.LOAD)
    if sub == BusSub.WRITE_ID:
        return BusWriteId(servo_id, frame.buffer[2])
    if sub == BusSub.SET_OFFSET:
        return BusSetOffset(servo_id, frame.unpack('<b', 2)[0])
    if sub == BusSub.SAVE_OFFSET:
        return BusSaveOffset(servo_id)
    if sub in (BusSub.SET_ANGLE_LIMITS, BusSub.SET_VOLTAGE_LIMITS):
        low, high = frame.unpack('<HH', 2)
        return BusSetLimits(sub, servo_id, low, high)
    if sub == BusSub.SET_TEMPERATURE_LIMIT:
        return BusSetTemperatureLimit(servo_id, frame.buffer[2])
    return IgnoredCommand(Function.BUS_SERVO, sub, 'unknown BUS_SERVO sub-command (O29)')
