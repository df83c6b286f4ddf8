"""OriginMan board wire format: codes and limits, range checks, CRC-8, frames, the decoder.

Every frame, in both directions, is ``AA 55 FUNCTION LENGTH DATA[LENGTH] CRC`` with
``CRC = crc8(FUNCTION, LENGTH, DATA...)`` (CRC-8/MAXIM-DOW, init 0, O1). Pure, like every
``protocol_*`` module; :mod:`originman_board_ros.protocol` is the public face that gathers
them. Decision numbers (O1..) refer to ``docs/protocols.md``.
"""

from __future__ import annotations

from dataclasses import dataclass
import enum
import math
from typing import Iterable, Optional, Sequence, Union

from uav_serial_common.stream_decoder import BAD_CHECKSUM, DROP, WAIT
from uav_serial_common.stream_decoder import StreamDecoder as BaseStreamDecoder


HEADER = b'\xaa\x55'
FRAME_OVERHEAD = 5
"""Header (2), FUNCTION, LENGTH and CRC: a frame is LENGTH + 5 bytes long."""
MAX_DATA = 255
BAUD = 1_000_000
"""The board's UART rate (8N1, O20)."""


class Function(enum.IntEnum):
    """FUNCTION codes (O2: 12 is NONE in the firmware and ASR on the OriginMan)."""

    SYS = 0
    LED = 1
    BUZZER = 2
    MOTOR = 3
    PWM_SERVO = 4
    BUS_SERVO = 5
    KEY = 6
    IMU = 7
    GAMEPAD = 8
    SBUS = 9
    OLED = 10
    RGB = 11
    ASR = 12


BOARD_FUNCTION_LIMIT = 12
"""The board's parser drops frames whose FUNCTION is this or more (O2, O22)."""
HOST_FUNCTION_MAX = 12
"""The host accepts FUNCTION 0..12 from the board (12 = ASR, O2)."""
MAX_BOARD_LENGTH = 64
"""O34: the longest board frame is SBUS (36 data bytes); a candidate LENGTH above this bound
is a false header and is abandoned at once instead of holding the decoder for 255 bytes."""


class SysSub(enum.IntEnum):
    """SYS sub-commands: 0x01 host -> board, 0x04 board -> host."""

    BATTERY_LIMIT = 0x01
    BATTERY_REPORT = 0x04


class MotorSub(enum.IntEnum):
    """MOTOR sub-commands (O5: 0x05 selects the motor type)."""

    SET_ONE = 0x00
    SET_MANY = 0x01
    STOP_ONE = 0x02
    STOP_MASK = 0x03
    SET_TYPE = 0x05


class MotorType(enum.IntEnum):
    """Encoder motor models of MOTOR 0x05; anything else is taken as JGB520 by the board."""

    JGB520 = 0
    JGB37 = 1
    JGA27 = 2
    JGB528 = 3


MOTOR_TYPE_MAX_RPS = {MotorType.JGB520: 1.5, MotorType.JGB37: 3.0, MotorType.JGA27: 6.0,
                      MotorType.JGB528: 1.1}
"""The firmware's speed clamp of each motor type, in revolutions per second."""
MAX_RPS = 6.0
"""The fastest motor type's limit: no speed beyond it is ever encoded."""
MOTOR_COUNT = 4
"""Wire ids 0..3 are motors 1..4 (O3)."""


class PwmSub(enum.IntEnum):
    """PWM_SERVO sub-commands (O10, O11)."""

    MOVE_MANY = 0x01
    MOVE_ONE = 0x03
    READ_PULSE = 0x05
    SET_OFFSET = 0x07
    READ_OFFSET = 0x09


PWM_SERVO_COUNT = 4
"""PWM servo ids 1..4 (O30: 0 passes the firmware's check and indexes out of bounds)."""
PWM_PULSE_MIN_US = 500
PWM_PULSE_MAX_US = 2500
PWM_DURATION_MIN_MS = 20
PWM_DURATION_MAX_MS = 30000
PWM_OFFSET_MAX_US = 100


class BusSub(enum.IntEnum):
    """BUS_SERVO sub-commands (O6: 0x0B unloads, 0x0C loads; O29: no HX extensions)."""

    MOVE = 0x01
    STOP = 0x03
    READ_POSITION = 0x05
    READ_VOLTAGE = 0x07
    READ_TEMPERATURE = 0x09
    UNLOAD = 0x0B
    LOAD = 0x0C
    READ_LOAD = 0x0D
    WRITE_ID = 0x10
    READ_ID = 0x12
    SET_OFFSET = 0x20
    READ_OFFSET = 0x22
    SAVE_OFFSET = 0x24
    SET_ANGLE_LIMITS = 0x30
    READ_ANGLE_LIMITS = 0x32
    SET_VOLTAGE_LIMITS = 0x34
    READ_VOLTAGE_LIMITS = 0x36
    SET_TEMPERATURE_LIMIT = 0x38
    READ_TEMPERATURE_LIMIT = 0x3A


BUS_READ_FORMATS = {
    BusSub.READ_POSITION: '<h',
    BusSub.READ_VOLTAGE: '<H',
    BusSub.READ_TEMPERATURE: '<B',
    BusSub.READ_LOAD: '<B',
    BusSub.READ_ID: '<B',
    BusSub.READ_OFFSET: '<b',
    BusSub.READ_ANGLE_LIMITS: '<HH',
    BusSub.READ_VOLTAGE_LIMITS: '<HH',
    BusSub.READ_TEMPERATURE_LIMIT: '<B',
}
"""The nine read sub-commands and the struct format of the value in their reply (§5.1)."""
BUS_BROADCAST_ID = 0xFE
BUS_ID_MAX = 253
BUS_POSITION_MAX = 1000
BUS_DURATION_MAX_MS = 0xFFFF
BUS_OFFSET_MAX = 125
BUS_VOLTAGE_MIN_MV = 4500
BUS_VOLTAGE_MAX_MV = 14000
BUS_TEMPERATURE_LIMIT_MAX_C = 100
BUS_SUCCESS = 0
BUS_FAILURE = -1
"""The success byte of a bus-servo read reply: 0 ok, -1 (0xFF) no valid answer (O14)."""


class KeyEvent(enum.IntEnum):
    """KEY report events (O17): one per report, never OR-ed."""

    PRESSED = 0x01
    LONG_PRESS = 0x02
    LONG_PRESS_REPEAT = 0x04
    RELEASE_FROM_LONG_PRESS = 0x08
    RELEASE_FROM_SHORT_PRESS = 0x10
    CLICK = 0x20
    DOUBLE_CLICK = 0x40
    TRIPLE_CLICK = 0x80


KEY_EVENT_NAMES = {e.value: e.name.lower() for e in KeyEvent}
"""Raw event code to the contract's ``event_name`` (``pressed``, ``long_press`` ...)."""
KEY_IDS = (1, 2)
LED_IDS = (1, 2)
OLED_LINES = (1, 2)
OLED_TEXT_MAX_BYTES = 23
"""The board copies the text into a 24-byte buffer and terminates it itself (O19)."""
RGB_PIXEL_COUNT = 2
RGB_COMMAND = 0x01
"""The cmd byte of RGB frames; the firmware ignores it, the SDK sends 0x01 (O18)."""
SBUS_CHANNELS = 16
ASR_MARKER = b'\xbb\xcc'
"""First two bytes of an ASR result (O2)."""

U16_MAX = 0xFFFF


# ---------------------------------------------------------------------------------------------
# Errors and checks
# ---------------------------------------------------------------------------------------------

class ProtocolError(ValueError):
    """Base class of the errors of this module."""


class ProtocolRangeError(ProtocolError):
    """A value an encoder was given is outside what the board can take; names field and range."""

    def __init__(self, field: str, value: object, allowed: str) -> None:
        self.field = field
        self.value = value
        self.allowed = allowed
        super().__init__(f'{field} must be {allowed}, got {value!r}')


def _is_int(value: object) -> bool:
    # bool is an int, but True as an id is a bug, not a 1.
    return isinstance(value, int) and not isinstance(value, bool)


def _int(field: str, value: object, lo: int, hi: int, allowed: Optional[str] = None) -> int:
    if not _is_int(value) or not lo <= value <= hi:  # type: ignore[operator]
        raise ProtocolRangeError(field, value, allowed or f'an integer in {lo}..{hi}')
    return int(value)  # type: ignore[arg-type]


def _float(field: str, value: object, limit: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or \
            not math.isfinite(value) or abs(value) > limit:
        raise ProtocolRangeError(field, value, f'a finite number in -{limit:g}..{limit:g}')
    return float(value)


def _bus_id(field: str, value: object) -> int:
    return _int(field, value, 0, BUS_BROADCAST_ID,
                f'a servo id 0..{BUS_ID_MAX} or {BUS_BROADCAST_ID} (broadcast)')


def _distinct(field: str, ids: Sequence[int]) -> None:
    seen = set()
    for i in ids:
        if i in seen:
            raise ProtocolRangeError(field, list(ids), 'a list without repeated ids')
        seen.add(i)


def _count(field: str, items: Sequence, lo: int, hi: int) -> None:
    if not isinstance(items, (list, tuple)) or not lo <= len(items) <= hi:
        n = len(items) if isinstance(items, (list, tuple)) else items
        raise ProtocolRangeError(field, n, f'a list of {lo}..{hi} entries')


# ---------------------------------------------------------------------------------------------
# CRC-8 (O1)
# ---------------------------------------------------------------------------------------------

def _crc_table() -> bytes:
    table = bytearray(256)
    for i in range(256):
        c = i
        for _ in range(8):
            c = (c >> 1) ^ 0x8C if c & 1 else c >> 1
        table[i] = c
    return bytes(table)


CRC8_TABLE = _crc_table()
"""O1: the firmware's and SDK's table (reflected polynomial 0x8C, init 0, no final XOR)."""


def crc8(data: Union[bytes, bytearray, memoryview, Iterable[int]]) -> int:
    """Return the frame CRC of ``data`` (FUNCTION, LENGTH and DATA of a frame)."""
    table = CRC8_TABLE
    c = 0
    for b in data:
        c = table[c ^ b]
    return c


def encode_frame(function: int, data: Union[bytes, bytearray] = b'') -> bytes:
    """Build one frame: header, FUNCTION, LENGTH, DATA and CRC."""
    _int('FUNCTION', function, 0, 255)
    data = bytes(data)
    if len(data) > MAX_DATA:
        raise ProtocolRangeError('DATA length', len(data), f'at most {MAX_DATA} bytes')
    body = bytes((function, len(data))) + data
    return HEADER + body + bytes((crc8(body),))


@dataclass(frozen=True, slots=True)
class Frame:
    """One CRC-checked frame as the host's decoder found it."""

    function: int
    data: bytes
    raw: bytes


def parse_frame(raw: Union[bytes, bytearray]) -> Frame:
    """Check one complete frame; raise :class:`ProtocolError` on any defect."""
    raw = bytes(raw)
    if len(raw) < FRAME_OVERHEAD or raw[:2] != HEADER:
        raise ProtocolError(f'not a frame: {raw.hex(" ")}')
    if len(raw) != raw[3] + FRAME_OVERHEAD:
        raise ProtocolError(f'LENGTH {raw[3]} does not match a frame of {len(raw)} bytes')
    expected = crc8(raw[2:-1])
    if raw[-1] != expected:
        raise ProtocolError(f'CRC is 0x{raw[-1]:02X}, expected 0x{expected:02X}')
    return Frame(raw[2], raw[4:-1], raw)


class StreamDecoder(BaseStreamDecoder):
    """The host's decoder of the board's byte stream (§2.4); never raises.

    It hunts for ``AA 55``, takes FUNCTION and LENGTH, waits for the rest and checks the CRC.
    A CRC failure (counted in ``checksum_errors``), or a LENGTH beyond ``max_length`` (O34),
    abandons the candidate one byte after its start, so a real frame beginning inside a false
    one is still found. CRC-valid frames with FUNCTION 0..12 are returned (12 = ASR, O2); one
    with a higher FUNCTION is counted in ``unknown_functions`` and abandoned like a CRC failure
    (O50). A trailing 0xAA is kept for the next chunk. The other counters are the base's.
    """

    headers = (HEADER,)

    def __init__(self, max_length: int = MAX_BOARD_LENGTH) -> None:
        super().__init__()
        self.max_length = max_length
        self.unknown_functions = 0
        """CRC-valid candidates abandoned because the board never sends their FUNCTION (O50)."""

    def _candidate(self, buf: bytearray, pos: int, n: int, final: bool, out: list) -> int:
        if n - pos < 4:
            return WAIT
        length = buf[pos + 3]
        if length > self.max_length:
            return DROP
        end = pos + length + FRAME_OVERHEAD
        if end > n:
            return WAIT
        raw = bytes(buf[pos:end])
        table = CRC8_TABLE
        crc = 0
        for b in raw[2:-1]:
            crc = table[crc ^ b]
        if crc != raw[-1]:
            return BAD_CHECKSUM
        function = raw[2]
        if function > HOST_FUNCTION_MAX:
            # O50: the board never sends one; a CRC-valid "frame" of FUNCTION 13+ is noise
            # that happens to check, so real frames inside it are still looked for.
            self.unknown_functions += 1
            return DROP
        out.append(Frame(function, raw[4:-1], raw))
        return length + FRAME_OVERHEAD
