"""DPS-S protocol: the typed messages of the module and the functions that type a frame.

Raw bytes stay on every decoded object as ``raw``. Decision numbers (P1..) refer to
``docs/protocols.md``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Tuple, Union

from dps_parachute_ros.protocol_frames import (
    BAUD_CODES, CMD_ARM, CMD_ARMED, CMD_ATTITUDE_THRESHOLD, CMD_ATTITUDE_TRIGGER,
    CMD_BAUD_RATE, CMD_BOOT_COUNT, CMD_CELL_VOLTAGE, CMD_CHARGING, CMD_DEPLOY,
    CMD_FREEFALL_THRESHOLD, CMD_FREEFALL_TIME, CMD_FREEFALL_TRIGGER, CMD_HEARTBEAT,
    CMD_LIGHT_LEVEL, CMD_LIGHT_THRESHOLD, CMD_SENSOR_ZERO, CMD_SHUTDOWN, CMD_STATUS,
    CMD_STREAMING, CMD_TRIGGER_RECORDS, CMD_TRIGGER_REQUEST, CMD_TRIGGERED, CONFIRM_PAYLOAD,
    FlagLayout, Frame, FRAME_LEN, HEARTBEAT_PAYLOAD, MODULE_HEADER, parse_frame,
    RECORD_FRAME_LEN, REPLY_CODES, SOURCE_ATTITUDE, SOURCE_FREEFALL, SOURCE_PWM, SOURCE_SERIAL,
    STATUS_FRAME_LEN,
)


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


RECORD_SLOTS = 8
"""The module's ring of trigger records: its answer to the query has one frame per slot (P15)."""


class TriggerRecords(Tuple[TriggerRecord, ...]):
    """The records of one answer to the trigger-record query, as they came.

    `complete` when a frame came for every slot of the ring (P15): only then does a record's
    absence say that the module did not deploy. An answer cut short (a frame lost or corrupted)
    tells what it holds and nothing about what it does not.
    """

    complete: bool

    def __new__(cls, records: Iterable[TriggerRecord] = ()) -> 'TriggerRecords':
        """Take the records of one answer, empty slots included."""
        self = super().__new__(cls, records)
        self.complete = len(self) >= RECORD_SLOTS
        return self

    def stored(self) -> 'TriggerRecords':
        """Return the records that describe a deployment (no empty slot), as complete."""
        out = TriggerRecords(r for r in self if not r.is_empty)
        out.complete = self.complete
        return out


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
