"""DPS-S parachute module serial protocol: frame builders, typed decoders and a stream decoder.

Pure functions and immutable dataclasses only: no I/O, no threads, no ROS. Values cross this
module's boundary in SI units (degrees where a name says ``_deg``, g where it says ``_g``); raw
bytes stay on every decoded object as ``raw``. Decision numbers (P1..) refer to
``docs/protocols.md``.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Literal, Union

from uav_serial_common.stream_decoder import BAD_CHECKSUM, DROP, WAIT
from uav_serial_common.stream_decoder import StreamDecoder as BaseStreamDecoder

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
# Value conversion with range checks (P9, P13)
# ---------------------------------------------------------------------------------------------

def _to_raw(name: str, value: float, unit: str, step: float,
            raw_range: tuple[int, int]) -> int:
    """Convert an SI value to raw steps, rounding halves up, and check the raw range."""
    lo, hi = raw_range
    allowed = f'{_fmt(lo * step)}..{_fmt(hi * step)} {unit}'
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ProtocolRangeError(f'{name} must be a number in {unit}, got {value!r}')
    if not math.isfinite(value):
        raise ProtocolRangeError(f'{name} {value!r} {unit} is not finite; allowed {allowed}')
    # The epsilon keeps decimal halves such as 0.55 g on the upper side despite binary floats.
    raw = math.floor(value / step + 0.5 + 1e-9)
    if not lo <= raw <= hi:
        raise ProtocolRangeError(
            f'{name} {_fmt(value)} {unit} is out of range; allowed {allowed} '
            f'in steps of {_fmt(step)} {unit}')
    return raw


def _fmt(value: float) -> str:
    return f'{value:.4f}'.rstrip('0').rstrip('.')


def attitude_threshold_to_raw(degrees: int | float) -> int:
    """Return the raw byte of an attitude threshold in whole degrees (range P13)."""
    lo, hi = ATTITUDE_THRESHOLD_RANGE_DEG
    if isinstance(degrees, float) and math.isfinite(degrees) and degrees.is_integer():
        degrees = int(degrees)
    if isinstance(degrees, bool) or not isinstance(degrees, int):
        raise ProtocolRangeError(
            f'attitude threshold {degrees!r} deg must be a whole number of degrees '
            f'in {lo}..{hi} deg')
    if not lo <= degrees <= hi:
        raise ProtocolRangeError(
            f'attitude threshold {degrees} deg is out of range; allowed {lo}..{hi} deg')
    return degrees


def freefall_threshold_to_raw(g: float) -> int:
    """Return the raw byte (0.1 g steps) of a free-fall threshold in g (range P13)."""
    return _to_raw('free-fall threshold', g, 'g', 0.1, FREEFALL_THRESHOLD_RANGE_RAW)


def freefall_time_to_raw(seconds: float) -> int:
    """Return the raw byte (0.01 s steps) of a free-fall time in seconds."""
    return _to_raw('free-fall time', seconds, 's', 0.01, FREEFALL_TIME_RANGE_RAW)


def light_threshold_to_raw(volts: float) -> int:
    """Return the raw byte (0.1 V steps) of a light threshold in volts."""
    return _to_raw('light threshold', volts, 'V', 0.1, LIGHT_THRESHOLD_RANGE_RAW)


def baud_to_code(baud: int) -> int:
    """Return the 0x24 code of a baud rate in bit/s; only the six documented rates exist."""
    if isinstance(baud, bool) or baud not in BAUD_TO_CODE:
        allowed = ', '.join(str(b) for b in sorted(BAUD_TO_CODE))
        raise ProtocolRangeError(f'baud rate {baud!r} bit/s is not supported; allowed {allowed}')
    return BAUD_TO_CODE[baud]


# ---------------------------------------------------------------------------------------------
# Host command encoders
# ---------------------------------------------------------------------------------------------

def encode_heartbeat() -> bytes:
    """Build the host heartbeat ``42 61 01 a5 5a 00`` (P4; its sum 0x100 makes the checksum 00)."""
    return build_frame(HOST_HEADER, CMD_HEARTBEAT, HEARTBEAT_PAYLOAD)


def encode_arm(armed: bool) -> bytes:
    """Arm (activate, ``True``) or lock (``False``) the module: 0x10."""
    return host_frame(CMD_ARM, CTRL_SET, 1 if armed else 0)


def encode_deploy(deploy: bool = True) -> bytes:
    """Request a serial deploy 0x11: D4 0x01 deploys; 0x00 is the document's "forbid trigger"."""
    return host_frame(CMD_DEPLOY, CTRL_SET, 1 if deploy else 0)


def encode_shutdown() -> bytes:
    """Software shutdown 0x12 (the module answers, then switches itself off)."""
    return host_frame(CMD_SHUTDOWN, CTRL_SET, 0x01)


def encode_streaming(enabled: bool) -> bytes:
    """Turn the module's 0x32 status stream on or off: 0x13."""
    return host_frame(CMD_STREAMING, CTRL_SET, 1 if enabled else 0)


def encode_light_level_query() -> bytes:
    """Query the light-sensor voltage: ``42 61 14 01 01 16`` (D4 0x01 as documented)."""
    return host_frame(CMD_LIGHT_LEVEL, CTRL_QUERY, 0x01)


def encode_light_threshold_set(volts: float) -> bytes:
    """Set the light threshold in volts (0.1 V steps): 0x15."""
    return host_frame(CMD_LIGHT_THRESHOLD, CTRL_SET, light_threshold_to_raw(volts))


def encode_light_threshold_query() -> bytes:
    """Query the light threshold: 0x15."""
    return host_frame(CMD_LIGHT_THRESHOLD, CTRL_QUERY, 0x00)


def encode_attitude_trigger(enabled: bool) -> bytes:
    """Enable or disable the attitude auto trigger: 0x16 (D4 0x01 disables, P8)."""
    return host_frame(CMD_ATTITUDE_TRIGGER, CTRL_SET, 0 if enabled else 1)


def encode_freefall_trigger(enabled: bool) -> bytes:
    """Enable or disable the free-fall auto trigger: 0x17 (D4 0x01 disables, P8)."""
    return host_frame(CMD_FREEFALL_TRIGGER, CTRL_SET, 0 if enabled else 1)


def encode_auto_trigger_query() -> bytes:
    """Query both auto-trigger flags ``42 61 16 01 00 17``: our extension (P14)."""
    return host_frame(CMD_ATTITUDE_TRIGGER, CTRL_QUERY, 0x00)


def encode_attitude_threshold_set(degrees: int) -> bytes:
    """Set the attitude threshold in whole degrees: 0x20."""
    return host_frame(CMD_ATTITUDE_THRESHOLD, CTRL_SET, attitude_threshold_to_raw(degrees))


def encode_attitude_threshold_query() -> bytes:
    """Query the attitude threshold: 0x20."""
    return host_frame(CMD_ATTITUDE_THRESHOLD, CTRL_QUERY, 0x00)


def encode_freefall_threshold_set(g: float) -> bytes:
    """Set the free-fall acceleration threshold in g (0.1 g steps): 0x21."""
    return host_frame(CMD_FREEFALL_THRESHOLD, CTRL_SET, freefall_threshold_to_raw(g))


def encode_freefall_threshold_query() -> bytes:
    """Query the free-fall threshold: 0x21."""
    return host_frame(CMD_FREEFALL_THRESHOLD, CTRL_QUERY, 0x00)


def encode_freefall_time_set(seconds: float) -> bytes:
    """Set the free-fall time in seconds (0.01 s steps): 0x22."""
    return host_frame(CMD_FREEFALL_TIME, CTRL_SET, freefall_time_to_raw(seconds))


def encode_freefall_time_query() -> bytes:
    """Query the free-fall time: 0x22."""
    return host_frame(CMD_FREEFALL_TIME, CTRL_QUERY, 0x00)


def encode_boot_count_query() -> bytes:
    """Query the boot count: 0x23."""
    return host_frame(CMD_BOOT_COUNT, CTRL_QUERY, 0x00)


def encode_baud_rate_set(baud: int) -> bytes:
    """Set the module's baud rate in bit/s (one of the six codes): 0x24."""
    return host_frame(CMD_BAUD_RATE, CTRL_SET, baud_to_code(baud))


def encode_sensor_zero() -> bytes:
    """Zero the attitude sensor at the present mounting: ``42 61 25 01 00 26``."""
    return host_frame(CMD_SENSOR_ZERO, CTRL_QUERY, 0x00)


def encode_armed_query() -> bytes:
    """Query whether the module is armed: 0x30."""
    return host_frame(CMD_ARMED, CTRL_QUERY, 0x00)


def encode_triggered_query() -> bytes:
    """Query whether the module has triggered: 0x31."""
    return host_frame(CMD_TRIGGERED, CTRL_QUERY, 0x00)


def encode_status_query() -> bytes:
    """Query one 8-byte status frame: 0x32."""
    return host_frame(CMD_STATUS, CTRL_QUERY, 0x00)


def encode_charging_query() -> bytes:
    """Query the charging state: 0x33."""
    return host_frame(CMD_CHARGING, CTRL_QUERY, 0x00)


def encode_cell_voltage_query() -> bytes:
    """Query the cell (or charging) voltage: 0x34 (the reply may be coded 0x35, P3)."""
    return host_frame(CMD_CELL_VOLTAGE, CTRL_QUERY, 0x00)


def encode_trigger_records_query() -> bytes:
    """Query the stored trigger records: 0x35 (answered with 16-byte frames, P15)."""
    return host_frame(CMD_TRIGGER_RECORDS, CTRL_QUERY, 0x00)


def encode_trigger_confirm() -> bytes:
    """Confirm a pending trigger request: ``42 61 39 a5 01 df`` (P10)."""
    return build_frame(HOST_HEADER, CMD_TRIGGER_REQUEST, CONFIRM_PAYLOAD)


# ---------------------------------------------------------------------------------------------
# Module frame builders (used by the simulator and by tests)
# ---------------------------------------------------------------------------------------------

def encode_module_heartbeat() -> bytes:
    """Build the module heartbeat ``41 75 01 a5 5a 00`` (P4, P5)."""
    return build_frame(MODULE_HEADER, CMD_HEARTBEAT, HEARTBEAT_PAYLOAD)


def encode_status_frame(tilt_deg: int, accel_raw: int, triggered: bool, armed: bool) -> bytes:
    """Build the 8-byte 0x32 status frame (P2); ``accel_raw`` is in 0.1 g."""
    payload = bytes((_byte('tilt', tilt_deg), _byte('acceleration', accel_raw),
                     1 if triggered else 0, 1 if armed else 0))
    return build_frame(MODULE_HEADER, CMD_STATUS, payload)


def encode_trigger_request(header: bytes = MODULE_HEADER) -> bytes:
    """Build the module's trigger request ``.. 39 02 01 3c`` with either header (P10)."""
    if header not in (MODULE_HEADER, HOST_HEADER):
        raise FrameError(f'unknown header {header.hex(" ")}')
    return build_frame(header, CMD_TRIGGER_REQUEST, bytes((CTRL_SET, 0x01)))


def encode_trigger_record(boot_count: int, uptime_s: int, source: int,
                          attitude_threshold_raw: int, freefall_threshold_raw: int,
                          freefall_time_raw: int, serial_link: bool, charging: bool,
                          light_threshold_raw: int, cell_voltage_raw: int) -> bytes:
    """Build a 16-byte 0x35 trigger record from raw field values (P2)."""
    if isinstance(uptime_s, bool) or not isinstance(uptime_s, int) or not 0 <= uptime_s <= 0xFFFF:
        raise ProtocolRangeError(f'uptime {uptime_s!r} s must be an integer 0..65535 s')
    payload = bytes((
        CTRL_QUERY, _byte('boot count', boot_count), uptime_s >> 8, uptime_s & 0xFF,
        _byte('source', source), _byte('attitude threshold', attitude_threshold_raw),
        _byte('free-fall threshold', freefall_threshold_raw),
        _byte('free-fall time', freefall_time_raw), 1 if serial_link else 0,
        1 if charging else 0, _byte('light threshold', light_threshold_raw),
        _byte('cell voltage', cell_voltage_raw)))
    return build_frame(MODULE_HEADER, CMD_TRIGGER_RECORDS, payload)


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


# ---------------------------------------------------------------------------------------------
# Typed module messages
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class Heartbeat:
    """Module heartbeat; unsolicited ones mean the module has booted (P5)."""

    raw: bytes


@dataclass(frozen=True, slots=True)
class ArmReply:
    """Reply to arm/lock 0x10."""

    armed: bool
    value: int
    raw: bytes


@dataclass(frozen=True, slots=True)
class DeployAck:
    """Reply to serial deploy 0x11; ``success`` is D4 0x01 (P11)."""

    success: bool
    value: int
    raw: bytes


@dataclass(frozen=True, slots=True)
class ShutdownAck:
    """Sent by the module right before it switches itself off (0x12)."""

    value: int
    raw: bytes


@dataclass(frozen=True, slots=True)
class StreamingReply:
    """Reply to streaming on/off 0x13."""

    enabled: bool
    value: int
    raw: bytes


@dataclass(frozen=True, slots=True)
class LightLevel:
    """Light-sensor voltage (0x14), raw/10 V."""

    volts: float
    value: int
    raw: bytes


@dataclass(frozen=True, slots=True)
class LightThreshold:
    """Light threshold (0x15), raw/10 V."""

    volts: float
    value: int
    raw: bytes


@dataclass(frozen=True, slots=True)
class AutoTriggerFlags:
    """Both auto-trigger states from a 0x16 reply (P8), decoded with ``layout``."""

    attitude_enabled: bool
    freefall_enabled: bool
    layout: str
    value: int
    raw: bytes


@dataclass(frozen=True, slots=True)
class AttitudeThreshold:
    """Attitude threshold in whole degrees (0x20)."""

    degrees: int
    value: int
    raw: bytes


@dataclass(frozen=True, slots=True)
class FreefallThreshold:
    """Free-fall acceleration threshold (0x21), raw/10 g."""

    g: float
    value: int
    raw: bytes


@dataclass(frozen=True, slots=True)
class FreefallTime:
    """Free-fall time (0x22), raw/100 s."""

    seconds: float
    value: int
    raw: bytes


@dataclass(frozen=True, slots=True)
class BootCount:
    """Boot count (0x23), wraps to 0 after 255."""

    count: int
    raw: bytes


@dataclass(frozen=True, slots=True)
class BaudRate:
    """Reply to baud-rate set 0x24; ``baud`` is None for a code outside 1..6."""

    code: int
    baud: int | None
    value: int
    raw: bytes


@dataclass(frozen=True, slots=True)
class ZeroAck:
    """Reply to sensor zeroing 0x25."""

    success: bool
    value: int
    raw: bytes


@dataclass(frozen=True, slots=True)
class ArmedState:
    """Reply to query-armed 0x30: 0x01 armed, 0x00 locked (P7)."""

    armed: bool
    value: int
    raw: bytes


@dataclass(frozen=True, slots=True)
class TriggeredState:
    """Reply to query-triggered 0x31."""

    triggered: bool
    value: int
    raw: bytes


@dataclass(frozen=True, slots=True)
class Status:
    """The 8-byte 0x32 status frame (P2): reply to 0x32 and the stream."""

    tilt_deg: int
    accel_g: float
    triggered: bool
    armed: bool
    raw: bytes


@dataclass(frozen=True, slots=True)
class Charging:
    """Reply to the charging query 0x33."""

    charging: bool
    value: int
    raw: bytes


@dataclass(frozen=True, slots=True)
class CellVoltage:
    """6-byte cell-voltage reply coded 0x34 or 0x35 (P3), raw x 0.02 V."""

    volts: float
    code: int
    value: int
    raw: bytes


@dataclass(frozen=True, slots=True)
class TriggerRecord:
    """One 16-byte trigger record (P2), every field in SI units.

    A record whose source byte is 0 describes no trigger (an empty slot, P15).
    """

    boot_count: int
    uptime_s: int
    source: int
    serial_trigger: bool
    attitude_trigger: bool
    pwm_trigger: bool
    freefall_trigger: bool
    attitude_threshold_deg: int
    freefall_threshold_g: float
    freefall_time_s: float
    serial_link: bool
    charging: bool
    light_threshold_v: float
    cell_voltage_v: float
    raw: bytes

    @property
    def is_empty(self) -> bool:
        """Whether this is an unused slot rather than a deployment."""
        return self.source == 0


@dataclass(frozen=True, slots=True)
class TriggerRequest:
    """The module asks the host to confirm a deployment within 1 s (P10)."""

    header: bytes
    raw: bytes


@dataclass(frozen=True, slots=True)
class UnknownFrame:
    """A checksum-valid frame this module cannot type; ``reason`` says why."""

    header: bytes
    code: int
    reason: str
    raw: bytes


ModuleMessage = Union[
    Heartbeat, ArmReply, DeployAck, ShutdownAck, StreamingReply, LightLevel, LightThreshold,
    AutoTriggerFlags, AttitudeThreshold, FreefallThreshold, FreefallTime, BootCount, BaudRate,
    ZeroAck, ArmedState, TriggeredState, Status, Charging, CellVoltage, TriggerRecord,
    TriggerRequest, UnknownFrame,
]


def decode_auto_trigger_flags(value: int, layout: FlagLayout = 'table') -> tuple[bool, bool]:
    """Return ``(attitude_enabled, freefall_enabled)`` from a 0x16 reply byte (P8).

    ``table``: low nibble set = attitude disabled, high nibble set = free-fall disabled.
    ``prose``: the other way round.
    """
    low_set = (value & 0x0F) != 0
    high_set = (value >> 4) != 0
    if layout == 'table':
        return not low_set, not high_set
    if layout == 'prose':
        return not high_set, not low_set
    raise ValueError(f"auto-trigger flag layout must be 'table' or 'prose', got {layout!r}")


def encode_auto_trigger_flags(attitude_enabled: bool, freefall_enabled: bool,
                              layout: FlagLayout = 'table') -> int:
    """Return the 0x16 reply byte for both states (inverse of ``decode_auto_trigger_flags``)."""
    attitude_bit = 0 if attitude_enabled else 1
    freefall_bit = 0 if freefall_enabled else 1
    if layout == 'table':
        return (freefall_bit << 4) | attitude_bit
    if layout == 'prose':
        return (attitude_bit << 4) | freefall_bit
    raise ValueError(f"auto-trigger flag layout must be 'table' or 'prose', got {layout!r}")


def _decode_record(frame: Frame) -> TriggerRecord:
    d = frame.data
    source = d[4]
    return TriggerRecord(
        boot_count=d[1],
        uptime_s=(d[2] << 8) | d[3],
        source=source,
        serial_trigger=bool(source & SOURCE_SERIAL),
        attitude_trigger=bool(source & SOURCE_ATTITUDE),
        pwm_trigger=bool(source & SOURCE_PWM),
        freefall_trigger=bool(source & SOURCE_FREEFALL),
        attitude_threshold_deg=d[5],
        freefall_threshold_g=d[6] / 10,
        freefall_time_s=d[7] / 100,
        serial_link=d[8] == 1,
        charging=d[9] == 1,
        light_threshold_v=d[10] / 10,
        cell_voltage_v=round(d[11] * 0.02, 2),
        raw=frame.raw,
    )


def decode_module_frame(frame: Frame, layout: FlagLayout = 'table') -> ModuleMessage:
    """Type one frame from the module; never raises for a frame ``StreamDecoder`` delivered.

    Frames that cannot be typed (unknown code, a host-header frame other than the trigger
    request, unexpected length or heartbeat payload) come back as ``UnknownFrame``.
    """
    code, raw, n = frame.code, frame.raw, len(frame.raw)
    if code == CMD_TRIGGER_REQUEST and n == FRAME_LEN:
        # P10: the request is accepted with either header; the confirmation payload is ours.
        if frame.data == CONFIRM_PAYLOAD:
            return UnknownFrame(frame.header, code, 'trigger confirmation (host frame)', raw)
        return TriggerRequest(frame.header, raw)
    if frame.header != MODULE_HEADER:
        # An echo of our own frames (loopback, half-duplex) must never look like a reply.
        return UnknownFrame(frame.header, code, 'host header', raw)
    if code == CMD_STATUS:
        if n != STATUS_FRAME_LEN:
            return UnknownFrame(frame.header, code, f'status frame of {n} bytes', raw)
        d = frame.data
        return Status(d[0], d[1] / 10, d[2] == 1, d[3] == 1, raw)
    if code == CMD_TRIGGER_RECORDS and n == RECORD_FRAME_LEN:
        return _decode_record(frame)
    if n != FRAME_LEN:
        return UnknownFrame(frame.header, code, f'{n}-byte frame', raw)
    v = frame.data[1]
    if code == CMD_HEARTBEAT:
        if frame.data != HEARTBEAT_PAYLOAD:
            return UnknownFrame(frame.header, code, 'heartbeat with unexpected payload', raw)
        return Heartbeat(raw)
    if code == CMD_ARM:
        return ArmReply(v == 1, v, raw)
    if code == CMD_DEPLOY:
        return DeployAck(v == 1, v, raw)
    if code == CMD_SHUTDOWN:
        return ShutdownAck(v, raw)
    if code == CMD_STREAMING:
        return StreamingReply(v == 1, v, raw)
    if code == CMD_LIGHT_LEVEL:
        return LightLevel(v / 10, v, raw)
    if code == CMD_LIGHT_THRESHOLD:
        return LightThreshold(v / 10, v, raw)
    if code in (CMD_ATTITUDE_TRIGGER, CMD_FREEFALL_TRIGGER):
        attitude, freefall = decode_auto_trigger_flags(v, layout)
        return AutoTriggerFlags(attitude, freefall, layout, v, raw)
    if code == CMD_ATTITUDE_THRESHOLD:
        return AttitudeThreshold(v, v, raw)
    if code == CMD_FREEFALL_THRESHOLD:
        return FreefallThreshold(v / 10, v, raw)
    if code == CMD_FREEFALL_TIME:
        return FreefallTime(v / 100, v, raw)
    if code == CMD_BOOT_COUNT:
        return BootCount(v, raw)
    if code == CMD_BAUD_RATE:
        return BaudRate(v, BAUD_CODES.get(v), v, raw)
    if code == CMD_SENSOR_ZERO:
        return ZeroAck(v == 1, v, raw)
    if code == CMD_ARMED:
        return ArmedState(v == 1, v, raw)
    if code == CMD_TRIGGERED:
        return TriggeredState(v == 1, v, raw)
    if code == CMD_CHARGING:
        return Charging(v == 1, v, raw)
    if code in (CMD_CELL_VOLTAGE, CMD_TRIGGER_RECORDS):
        return CellVoltage(round(v * 0.02, 2), code, v, raw)
    return UnknownFrame(frame.header, code, 'unknown command code', raw)


def decode_module_bytes(raw: bytes | bytearray, layout: FlagLayout = 'table') -> ModuleMessage:
    """Check one complete frame (``parse_frame``) and type it (``decode_module_frame``)."""
    return decode_module_frame(parse_frame(raw), layout)


def is_set_ack(reply: ModuleMessage, sent_value: int) -> bool:
    """Whether a set reply acknowledges ``sent_value`` (raw D4): echo or 0x01 (P6).

    Success towards a user still needs a matching read-back where a query exists (P6).
    """
    value = getattr(reply, 'value', None)
    return value is not None and value in (sent_value, 0x01)


def reply_matches(command: bytes | Frame, reply: ModuleMessage | Frame) -> bool:
    """Whether ``reply`` (a module frame) carries a code that answers host ``command``."""
    code = command.code if isinstance(command, Frame) else command[2]
    reply_raw = reply.raw
    if reply_raw[:2] != MODULE_HEADER:
        return False
    return reply_raw[2] in REPLY_CODES.get(code, frozenset({code}))


# ---------------------------------------------------------------------------------------------
# Stream decoder
# ---------------------------------------------------------------------------------------------

class StreamDecoder(BaseStreamDecoder):
    """Incremental frame decoder for either direction of the link; never raises.

    ``from_module`` accepts module frames (6, 8 and 16 bytes) and 6-byte frames with the host
    header (the trigger request of P10, or echoes). ``from_host`` accepts 6-byte host frames.
    Frames are delimited by header, the length the command code dictates and the P1
    checksum; the 0x34/0x35 collision is settled per P3/P16. Call ``flush()`` when the line
    has been idle for a few character times to settle a frame that could still grow (a 6-byte
    0x35 voltage reply waiting for a possible 16-byte record is then delivered).

    Counters: those of :class:`uav_serial_common.stream_decoder.StreamDecoder`
    (``frames_decoded`` includes unknown codes; ``checksum_errors`` counts header-started
    candidates whose checksum matched at no allowed length) and ``unknown_frames``.
    """

    def __init__(self, direction: Direction = 'from_module') -> None:
        if direction not in ('from_module', 'from_host'):
            raise ValueError(f"direction must be 'from_module' or 'from_host', got {direction!r}")
        self.direction = direction
        self._from_module = direction == 'from_module'
        self.headers = (MODULE_HEADER, HOST_HEADER) if self._from_module else (HOST_HEADER,)
        super().__init__()
        self.unknown_frames = 0
        """Delivered frames whose code (or header) this protocol does not define."""

    def _candidate(self, buf: bytearray, pos: int, n: int, final: bool, out: list) -> int:
        avail = n - pos
        if avail < 3:
            return WAIT
        code = buf[pos + 2]
        checked = False
        if buf[pos] == 0x41:  # MODULE_HEADER, only looked for from the module
            if code == CMD_STATUS:
                length = STATUS_FRAME_LEN
            elif code == CMD_TRIGGER_RECORDS:
                length = self._record_or_voltage(buf, pos, avail, final)
                if length <= 0:
                    return length
                checked = True
            else:
                length = FRAME_LEN
            known = code in MODULE_CODES
        else:
            length = FRAME_LEN
            known = code in HOST_CODES and (not self._from_module or code == CMD_TRIGGER_REQUEST)
        if avail < length:
            return WAIT
        end = pos + length
        if checked or sum(buf[pos + 2:end - 1]) & 0xFF == buf[end - 1]:
            raw = bytes(buf[pos:end])
            out.append(Frame(raw[:2], code, raw[3:-1], raw))
            if not known:
                self.unknown_frames += 1
            return length
        return BAD_CHECKSUM

    @staticmethod
    def _record_or_voltage(buf: bytearray, pos: int, avail: int, final: bool) -> int:
        """P3/P16: 0x35 is a 16-byte record or a 6-byte voltage reply, by checksum and length.

        Returns the checked length, or WAIT / BAD_CHECKSUM.
        """
        if avail < FRAME_LEN:
            return WAIT
        ok6 = sum(buf[pos + 2:pos + 5]) & 0xFF == buf[pos + 5]
        if avail >= RECORD_FRAME_LEN:
            ok16 = sum(buf[pos + 2:pos + 15]) & 0xFF == buf[pos + 15]
            if ok16 and (not ok6 or _record_plausible(buf, pos, RECORD_FRAME_LEN)):
                return RECORD_FRAME_LEN
            if ok6:
                return FRAME_LEN
            return BAD_CHECKSUM
        if ok6 and (final or not _record_plausible(buf, pos, avail)):
            return FRAME_LEN
        if final:
            return DROP
        return WAIT


def _record_plausible(buf: bytearray, pos: int, avail: int) -> bool:
    """Whether the bytes at ``pos`` (``avail`` of them) can still be a trigger record.

    Used only to break a tie where both the 6- and 16-byte readings pass the checksum (P16):
    a record has no source bits beyond the four documented and 0/1 link and charging bytes.
    """
    if avail > 7 and buf[pos + 7] & ~KNOWN_SOURCE_BITS & 0xFF:
        return False
    if avail > 11 and buf[pos + 11] > 1:
        return False
    if avail > 12 and buf[pos + 12] > 1:
        return False
    return True
