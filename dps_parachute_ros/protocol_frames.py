"""DPS-S protocol, the wire: headers, command codes, the P1 checksum and frames.

Pure and immutable, like every ``protocol_*`` module; :mod:`dps_parachute_ros.protocol` is the
public face that gathers them. Decision numbers (P1..) refer to ``docs/protocols.md``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


HOST_HEADER = b'\x42\x61'
"""Header of frames sent by the host (flight controller / companion computer)."""
MODULE_HEADER = b'\x41\x75'
"""Header of frames sent by the parachute module."""

CTRL_SET = 0x02
"""Host control byte D3 of a "set" command (P4)."""
CTRL_QUERY = 0x01
"""Host control byte D3 of a query; module replies carry it too (P4)."""

CMD_HEARTBEAT = 0x01
CMD_ARM = 0x10
CMD_DEPLOY = 0x11
CMD_SHUTDOWN = 0x12
CMD_STREAMING = 0x13
CMD_LIGHT_LEVEL = 0x14
CMD_LIGHT_THRESHOLD = 0x15
CMD_ATTITUDE_TRIGGER = 0x16
CMD_FREEFALL_TRIGGER = 0x17
CMD_ATTITUDE_THRESHOLD = 0x20
CMD_FREEFALL_THRESHOLD = 0x21
CMD_FREEFALL_TIME = 0x22
CMD_BOOT_COUNT = 0x23
CMD_BAUD_RATE = 0x24
CMD_SENSOR_ZERO = 0x25
CMD_ARMED = 0x30
CMD_TRIGGERED = 0x31
CMD_STATUS = 0x32
CMD_CHARGING = 0x33
CMD_CELL_VOLTAGE = 0x34
CMD_TRIGGER_RECORDS = 0x35
CMD_TRIGGER_REQUEST = 0x39

HEARTBEAT_PAYLOAD = b'\xa5\x5a'
"""D3-D4 of both heartbeats (P4)."""
CONFIRM_PAYLOAD = b'\xa5\x01'
"""D3-D4 of the host's trigger-request confirmation (P10)."""

FRAME_LEN = 6
STATUS_FRAME_LEN = 8
RECORD_FRAME_LEN = 16

SOURCE_SERIAL = 0x01
SOURCE_ATTITUDE = 0x02
SOURCE_PWM = 0x04
SOURCE_FREEFALL = 0x08
KNOWN_SOURCE_BITS = SOURCE_SERIAL | SOURCE_ATTITUDE | SOURCE_PWM | SOURCE_FREEFALL

BAUD_CODES: dict[int, int] = {1: 4800, 2: 9600, 3: 19200, 4: 38400, 5: 57600, 6: 115200}
"""Baud-rate code (D4 of 0x24) to bit/s (P9)."""
BAUD_TO_CODE: dict[int, int] = {baud: code for code, baud in BAUD_CODES.items()}

# Ranges the encoders accept, in raw steps (P13). The module itself takes any byte.
ATTITUDE_THRESHOLD_RANGE_DEG = (10, 90)
FREEFALL_THRESHOLD_RANGE_RAW = (1, 9)
FREEFALL_TIME_RANGE_RAW = (1, 255)
LIGHT_THRESHOLD_RANGE_RAW = (0, 255)

MODULE_CODES = frozenset({
    CMD_HEARTBEAT, CMD_ARM, CMD_DEPLOY, CMD_SHUTDOWN, CMD_STREAMING, CMD_LIGHT_LEVEL,
    CMD_LIGHT_THRESHOLD, CMD_ATTITUDE_TRIGGER, CMD_ATTITUDE_THRESHOLD, CMD_FREEFALL_THRESHOLD,
    CMD_FREEFALL_TIME, CMD_BOOT_COUNT, CMD_BAUD_RATE, CMD_SENSOR_ZERO, CMD_ARMED,
    CMD_TRIGGERED, CMD_STATUS, CMD_CHARGING, CMD_CELL_VOLTAGE, CMD_TRIGGER_RECORDS,
    CMD_TRIGGER_REQUEST,
})
"""Command codes the module is known to send with its own header."""

HOST_CODES = frozenset({
    CMD_HEARTBEAT, CMD_ARM, CMD_DEPLOY, CMD_SHUTDOWN, CMD_STREAMING, CMD_LIGHT_LEVEL,
    CMD_LIGHT_THRESHOLD, CMD_ATTITUDE_TRIGGER, CMD_FREEFALL_TRIGGER, CMD_ATTITUDE_THRESHOLD,
    CMD_FREEFALL_THRESHOLD, CMD_FREEFALL_TIME, CMD_BOOT_COUNT, CMD_BAUD_RATE, CMD_SENSOR_ZERO,
    CMD_ARMED, CMD_TRIGGERED, CMD_STATUS, CMD_CHARGING, CMD_CELL_VOLTAGE, CMD_TRIGGER_RECORDS,
    CMD_TRIGGER_REQUEST,
})
"""Command codes the host sends."""

REPLY_CODES: dict[int, frozenset[int]] = {code: frozenset({code}) for code in HOST_CODES}
REPLY_CODES[CMD_FREEFALL_TRIGGER] = frozenset({CMD_ATTITUDE_TRIGGER, CMD_FREEFALL_TRIGGER})
REPLY_CODES[CMD_CELL_VOLTAGE] = frozenset({CMD_CELL_VOLTAGE, CMD_TRIGGER_RECORDS})
"""Host command code to the reply codes that answer it (P3, P8)."""

FlagLayout = Literal['table', 'prose']
Direction = Literal['from_module', 'from_host']


class ProtocolError(ValueError):
    """Base class of every error this module raises."""


class ProtocolRangeError(ProtocolError):
    """A value given to an encoder is outside the range the protocol (or we) allow."""


class ChecksumError(ProtocolError):
    """A complete frame whose checksum byte does not match P1."""


class FrameError(ProtocolError):
    """Bytes that are not a frame of this protocol (header, length)."""


def checksum(body: bytes | bytearray) -> int:
    """Return the P1 checksum of ``body``: the low 8 bits of the sum of its bytes.

    ``body`` is D2 up to the byte before the checksum.
    """
    return sum(body) & 0xFF


def build_frame(header: bytes, code: int, payload: bytes | bytearray) -> bytes:
    """Assemble header, code, payload and the P1 checksum into one frame."""
    body = bytes((code,)) + bytes(payload)
    return bytes(header) + body + bytes((checksum(body),))


def _byte(name: str, value: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 0xFF:
        raise ProtocolRangeError(f'{name} must be an integer byte 0..255, got {value!r}')
    return value


def host_frame(code: int, control: int, value: int) -> bytes:
    """Build a 6-byte host frame ``42 61 code control value checksum``."""
    return build_frame(HOST_HEADER, _byte('code', code),
                       bytes((_byte('control', control), _byte('value', value))))


def module_frame(code: int, value: int, control: int = CTRL_QUERY) -> bytes:
    """Build a 6-byte module frame ``41 75 code control value checksum``."""
    return build_frame(MODULE_HEADER, _byte('code', code),
                       bytes((_byte('control', control), _byte('value', value))))


# ---------------------------------------------------------------------------------------------
# Frames
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class Frame:
    """One checksum-valid frame off the wire.

    ``data`` is D3 up to the byte before the checksum; ``raw`` is the whole frame.
    """

    header: bytes
    code: int
    data: bytes
    raw: bytes

    @property
    def from_module(self) -> bool:
        """Whether the frame carries the module's header ``41 75``."""
        return self.header == MODULE_HEADER

    @property
    def value(self) -> int:
        """D4, the value byte of a 6-byte frame (or the second data byte of longer ones)."""
        return self.data[1] if len(self.data) > 1 else 0


def parse_frame(raw: bytes | bytearray) -> Frame:
    """Check one complete frame (header, length 6/8/16, P1 checksum) and return it.

    Raises ``FrameError`` or ``ChecksumError``; never guesses.
    """
    raw = bytes(raw)
    if raw[:2] not in (HOST_HEADER, MODULE_HEADER):
        raise FrameError(f'no DPS-S header in {raw.hex(" ")}')
    if len(raw) not in (FRAME_LEN, STATUS_FRAME_LEN, RECORD_FRAME_LEN):
        raise FrameError(f'a DPS-S frame is 6, 8 or 16 bytes, got {len(raw)}: {raw.hex(" ")}')
    expected = checksum(raw[2:-1])
    if raw[-1] != expected:
        raise ChecksumError(
            f'checksum of {raw.hex(" ")} is {raw[-1]:02x}, expected {expected:02x}')
    return Frame(raw[:2], raw[2], raw[3:-1], raw)
