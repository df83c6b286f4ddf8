"""Wire format of the Desheng (德晟) serial bus servos: frame encoders, parsers and a stream decoder.

Pure functions and dataclasses only: no I/O, no threads, no ROS. Decisions S1..S7 and S8+ of
``docs/protocols.md`` are implemented here.

Request: ``FF FF ID LEN INSTR PARAMS.. CHK``; reply: ``FF F5 ID LEN STATUS PARAMS.. CHK``;
``LEN = len(PARAMS) + 2``; ``CHK = ~(ID + LEN + INSTR|STATUS + PARAMS..) & 0xFF``;
multi-byte values are big-endian (S1).
"""

from __future__ import annotations

from dataclasses import dataclass
import enum
from typing import Iterable, Sequence

from uav_serial_common.stream_decoder import BAD_CHECKSUM, DROP, WAIT
from uav_serial_common.stream_decoder import StreamDecoder as BaseStreamDecoder

REQUEST_HEADER = b'\xff\xff'
REPLY_HEADER = b'\xff\xf5'
MIN_ID = 1
MAX_ID = 250
BROADCAST_ID = 254

# LEN counts ID, instruction/status and the N params (N + 2), so a frame is LEN + 4 bytes long
# and the one-byte LEN caps the params of any frame at 253.
MAX_LEN = 255
MAX_REQUEST_PARAMS = MAX_LEN - 2
# S10: the documented register table spans 0x03..0x42, i.e. 64 bytes; nothing longer is ever
# worth reading, and the bound keeps a false header in line noise from stalling the reply decoder.
MAX_READ_LENGTH = 64
MAX_REPLY_LEN = MAX_READ_LENGTH + 2

STATUS_OVERLOAD = 0x20
STATUS_OVER_TEMPERATURE = 0x04
STATUS_VOLTAGE_FAULT = 0x01

TARGET_POSITION_ADDRESS = 0x2A
POSITION_MIN = 0
POSITION_MAX = 4095
RUN_TIME_MAX_MS = 0xFFFF
POSITION_PAYLOAD_LENGTH = 4
# 2 params (address, data length) + 5 bytes (id + 4 data bytes) per servo must fit 253 params.
MAX_SYNC_WRITE_POSITIONS = (MAX_REQUEST_PARAMS - 2) // (1 + POSITION_PAYLOAD_LENGTH)


class Instruction(enum.IntEnum):
    """Instruction codes of request frames."""

    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    RESET = 0x06
    SYNC_WRITE = 0x83


# Inclusive LEN bounds per instruction, from the parameter counts of the document's table 2.3
# (WRITE >= 1 param, REG WRITE >= 2, SYNC WRITE > 2). Used by the request decoder to reject false
# headers early (S9).
REQUEST_LEN_BOUNDS: dict[int, tuple[int, int]] = {
    Instruction.PING: (2, 2),
    Instruction.READ: (4, 4),
    Instruction.WRITE: (3, MAX_LEN),
    Instruction.REG_WRITE: (4, MAX_LEN),
    Instruction.ACTION: (2, 2),
    Instruction.RESET: (2, 2),
    Instruction.SYNC_WRITE: (5, MAX_LEN),
}


class ProtocolError(ValueError):
    """A frame or a value that the servo protocol cannot carry."""


def checksum(body: bytes | bytearray | Iterable[int]) -> int:
    """Return ``~sum(body) & 0xFF``; ``body`` is ID, LEN, instruction/status and params."""
    return ~sum(body) & 0xFF


def is_servo_id(value: object) -> bool:
    """Tell whether ``value`` is a unicast servo id (1..250)."""
    return _is_int(value) and MIN_ID <= value <= MAX_ID  # type: ignore[operator]


def _is_int(value: object) -> bool:
    # bool is an int subclass but True as an id or a byte count is almost certainly a bug.
    return isinstance(value, int) and not isinstance(value, bool)


def _check_int(value: object, lo: int, hi: int, what: str) -> int:
    if not _is_int(value):
        raise ProtocolError(f'{what} must be an int, got {type(value).__name__} {value!r}')
    if not lo <= value <= hi:  # type: ignore[operator]
        raise ProtocolError(f'{what} must be in {lo}..{hi}, got {value}')
    return value  # type: ignore[return-value]


def _check_id(servo_id: object, *, broadcast: bool, what: str) -> int:
    if _is_int(servo_id) and servo_id == BROADCAST_ID:
        if broadcast:
            return BROADCAST_ID
        raise ProtocolError(f'{what} cannot be sent to the broadcast id {BROADCAST_ID}')
    if not is_servo_id(servo_id):
        allowed = f'{MIN_ID}..{MAX_ID}' + (f' or {BROADCAST_ID} (broadcast)' if broadcast else '')
        raise ProtocolError(f'{what}: servo id must be {allowed}, got {servo_id!r}')
    return servo_id  # type: ignore[return-value]


def _as_bytes(data: object, what: str) -> bytes:
    if isinstance(data, (bytes, bytearray, memoryview)):
        return bytes(data)
    if isinstance(data, (list, tuple)):
        for b in data:
            _check_int(b, 0, 255, f'{what} byte')
        return bytes(data)
    raise ProtocolError(f'{what} must be bytes, got {type(data).__name__}')


def _frame(header: bytes, servo_id: int, code: int, params: bytes) -> bytes:
    body = bytes((servo_id, len(params) + 2, code)) + params
    return header + body + bytes((checksum(body),))


def encode_request(servo_id: int, instruction: int, params: bytes = b'') -> bytes:
    """Build any request frame; checks only the id range (1..250, 254) and the frame size."""
    _check_id(servo_id, broadcast=True, what='request')
    _check_int(instruction, 0, 255, 'instruction')
    params = _as_bytes(params, 'params')
    if len(params) > MAX_REQUEST_PARAMS:
        raise ProtocolError(f'a frame carries at most {MAX_REQUEST_PARAMS} params, '
                            f'got {len(params)}')
    return _frame(REQUEST_HEADER, servo_id, instruction, params)


def encode_ping(servo_id: int) -> bytes:
    """PING one servo (never broadcast, S3); it answers with its status."""
    _check_id(servo_id, broadcast=False, what='PING')
    return _frame(REQUEST_HEADER, servo_id, Instruction.PING, b'')


def encode_read(servo_id: int, address: int, length: int) -> bytes:
    """READ ``length`` bytes from ``address`` of one servo (never broadcast, S3)."""
    _check_id(servo_id, broadcast=False, what='READ')
    _check_int(address, 0, 255, 'address')
    _check_int(length, 1, MAX_READ_LENGTH, 'read length')
    if address + length > 256:
        raise ProtocolError(f'read of {length} bytes at 0x{address:02X} runs past address 0xFF')
    return _frame(REQUEST_HEADER, servo_id, Instruction.READ, bytes((address, length)))


def encode_write(servo_id: int, address: int, data: bytes = b'') -> bytes:
    """WRITE ``data`` at ``address`` of one servo or of all (254, no reply).

    Empty ``data`` is the address-only form used by the preset registers (S12).
    """
    _check_id(servo_id, broadcast=True, what='WRITE')
    _check_int(address, 0, 255, 'address')
    data = _as_bytes(data, 'data')
    if len(data) > MAX_REQUEST_PARAMS - 1:
        raise ProtocolError(f'WRITE carries at most {MAX_REQUEST_PARAMS - 1} data bytes')
    return _frame(REQUEST_HEADER, servo_id, Instruction.WRITE, bytes((address,)) + data)


def encode_reg_write(servo_id: int, address: int, data: bytes) -> bytes:
    """Stage a write in one servo until ACTION (unicast only; the firmware honours 0x2A, S6)."""
    _check_id(servo_id, broadcast=False, what='REG WRITE')
    _check_int(address, 0, 255, 'address')
    data = _as_bytes(data, 'data')
    if not 1 <= len(data) <= MAX_REQUEST_PARAMS - 1:
        raise ProtocolError(f'REG WRITE carries 1..{MAX_REQUEST_PARAMS - 1} data bytes, '
                            f'got {len(data)}')
    return _frame(REQUEST_HEADER, servo_id, Instruction.REG_WRITE, bytes((address,)) + data)


def encode_action(servo_id: int = BROADCAST_ID) -> bytes:
    """Build ACTION: every servo with a staged REG WRITE executes it (broadcast, no reply)."""
    if servo_id != BROADCAST_ID:
        raise ProtocolError(f'ACTION is sent to the broadcast id {BROADCAST_ID} only, '
                            f'got {servo_id!r}')
    return _frame(REQUEST_HEADER, BROADCAST_ID, Instruction.ACTION, b'')


def encode_reset(servo_id: int) -> bytes:
    """RESET one servo to factory settings; never broadcast (S11)."""
    _check_id(servo_id, broadcast=False, what='RESET')
    return _frame(REQUEST_HEADER, servo_id, Instruction.RESET, b'')


def encode_sync_write(address: int, data_length: int,
                      items: Sequence[tuple[int, bytes]]) -> bytes:
    """Build a SYNC WRITE of ``data_length`` bytes at ``address`` per (id, data); no reply."""
    _check_int(address, 0, 255, 'address')
    _check_int(data_length, 1, MAX_REQUEST_PARAMS - 3, 'SYNC WRITE data length')
    if not items:
        raise ProtocolError('SYNC WRITE needs at least one servo')
    params = bytearray((address, data_length))
    seen: set[int] = set()
    for servo_id, data in items:
        _check_id(servo_id, broadcast=False, what='SYNC WRITE entry')
        if servo_id in seen:
            raise ProtocolError(f'SYNC WRITE lists servo {servo_id} twice')
        seen.add(servo_id)
        data = _as_bytes(data, f'SYNC WRITE data of servo {servo_id}')
        if len(data) != data_length:
            raise ProtocolError(f'SYNC WRITE data of servo {servo_id} is {len(data)} bytes, '
                                f'expected {data_length}')
        params.append(servo_id)
        params += data
    if len(params) > MAX_REQUEST_PARAMS:
        per = data_length + 1
        raise ProtocolError(f'SYNC WRITE of {len(items)} servos does not fit one frame '
                            f'(at most {(MAX_REQUEST_PARAMS - 2) // per} with {data_length} '
                            'bytes each); split it')
    return _frame(REQUEST_HEADER, BROADCAST_ID, Instruction.SYNC_WRITE, bytes(params))


def encode_position_payload(position_ticks: int, run_time_ms: int) -> bytes:
    """Return the 4 bytes written at 0x2A: target position (0..4095) and run time (ms)."""
    _check_int(position_ticks, POSITION_MIN, POSITION_MAX, 'position_ticks')
    _check_int(run_time_ms, 0, RUN_TIME_MAX_MS, 'run_time_ms')
    return position_ticks.to_bytes(2, 'big') + run_time_ms.to_bytes(2, 'big')


def decode_position_payload(data: bytes) -> tuple[int, int]:
    """Split the 4 bytes of register 0x2A into (position_ticks, run_time_ms)."""
    if len(data) != POSITION_PAYLOAD_LENGTH:
        raise ProtocolError(f'a position payload is 4 bytes, got {len(data)}')
    return int.from_bytes(data[0:2], 'big'), int.from_bytes(data[2:4], 'big')


def encode_write_position(servo_id: int, position_ticks: int, run_time_ms: int) -> bytes:
    """WRITE target position and run time to one servo (or broadcast)."""
    payload = encode_position_payload(position_ticks, run_time_ms)
    return encode_write(servo_id, TARGET_POSITION_ADDRESS, payload)


def encode_reg_write_position(servo_id: int, position_ticks: int, run_time_ms: int) -> bytes:
    """Stage target position and run time in one servo until ACTION."""
    payload = encode_position_payload(position_ticks, run_time_ms)
    return encode_reg_write(servo_id, TARGET_POSITION_ADDRESS, payload)


def encode_sync_write_positions(targets: Iterable[tuple[int, int, int]]) -> bytes:
    """SYNC WRITE (id, position_ticks, run_time_ms) for up to 50 servos in one frame."""
    items = [(servo_id, encode_position_payload(ticks, ms)) for servo_id, ticks, ms in targets]
    return encode_sync_write(TARGET_POSITION_ADDRESS, POSITION_PAYLOAD_LENGTH, items)


def parse_sync_write(params: bytes) -> tuple[int, int, list[tuple[int, bytes]]]:
    """Split SYNC WRITE params into (address, data_length, [(id, data), ...])."""
    if len(params) < 3:
        raise ProtocolError('SYNC WRITE params are address, length and at least one entry')
    address, length = params[0], params[1]
    body = params[2:]
    if length == 0 or len(body) % (length + 1):
        raise ProtocolError(f'SYNC WRITE body of {len(body)} bytes is not a whole number of '
                            f'entries of 1 + {length} bytes')
    step = length + 1
    items = [(body[k], bytes(body[k + 1:k + step])) for k in range(0, len(body), step)]
    return address, length, items


def encode_reply(servo_id: int, status: int, params: bytes = b'') -> bytes:
    """Build a servo's reply frame (used by the simulator and by tests)."""
    _check_id(servo_id, broadcast=False, what='reply')
    _check_int(status, 0, 255, 'status')
    params = _as_bytes(params, 'params')
    if len(params) > MAX_READ_LENGTH:
        raise ProtocolError(f'a reply carries at most {MAX_READ_LENGTH} params')
    return _frame(REPLY_HEADER, servo_id, status, params)


@dataclass(frozen=True, slots=True)
class Reply:
    """A decoded servo reply: status byte (S4: bits 5, 2, 0 decoded) and params."""

    servo_id: int
    status: int
    params: bytes
    raw: bytes

    @property
    def overload(self) -> bool:
        """Bit 5: stall/overload protection has tripped."""
        return bool(self.status & STATUS_OVERLOAD)

    @property
    def over_temperature(self) -> bool:
        """Bit 2: temperature outside its range."""
        return bool(self.status & STATUS_OVER_TEMPERATURE)

    @property
    def voltage_fault(self) -> bool:
        """Bit 0: supply voltage outside its range."""
        return bool(self.status & STATUS_VOLTAGE_FAULT)

    @property
    def faults(self) -> list[str]:
        """Names of the status bits that are set (unknown bits as ``bitN``)."""
        return describe_status(self.status)


@dataclass(frozen=True, slots=True)
class Request:
    """A decoded host request."""

    servo_id: int
    instruction: int
    params: bytes
    raw: bytes

    @property
    def is_broadcast(self) -> bool:
        """Whether the request is addressed to every servo (id 254)."""
        return self.servo_id == BROADCAST_ID


def describe_status(status: int) -> list[str]:
    """Return the names of the set bits of a status byte."""
    names = {5: 'overload', 2: 'over_temperature', 0: 'voltage_fault'}
    return [names.get(bit, f'bit{bit}') for bit in range(8) if status & (1 << bit)]


def _parse(frame: bytes, header: bytes, what: str) -> tuple[int, int, bytes]:
    frame = bytes(frame)
    if len(frame) < 6 or frame[:2] != header:
        raise ProtocolError(f'not a {what} frame: {frame.hex(" ")}')
    length = frame[3]
    if len(frame) != length + 4:
        raise ProtocolError(f'{what} LEN {length} does not match a frame of {len(frame)} bytes')
    expected = checksum(frame[2:-1])
    if frame[-1] != expected:
        raise ProtocolError(f'{what} checksum is 0x{frame[-1]:02X}, expected 0x{expected:02X}')
    return frame[2], frame[4], frame[5:-1]


def parse_reply(frame: bytes) -> Reply:
    """Parse exactly one reply frame; raise ProtocolError on any defect."""
    servo_id, status, params = _parse(frame, REPLY_HEADER, 'reply')
    return Reply(servo_id, status, params, bytes(frame))


def parse_request(frame: bytes) -> Request:
    """Parse exactly one request frame; raise ProtocolError on any defect."""
    servo_id, instruction, params = _parse(frame, REQUEST_HEADER, 'request')
    return Request(servo_id, instruction, params, bytes(frame))


def _table(pred) -> bytes:
    return bytes(1 if pred(v) else 0 for v in range(256))


class StreamDecoder(BaseStreamDecoder):
    """Incremental frame decoder for a byte stream cut at arbitrary points.

    ``kind="reply"`` finds servo replies (``FF F5``), ``kind="request"`` host requests
    (``FF FF``). It never raises on input: garbage is skipped and counted, a candidate whose
    id, LEN or checksum is impossible is abandoned one byte at a time, so a real frame that
    starts inside a false candidate is still found. Counters and ``pending`` are the base's.
    """

    def __init__(self, kind: str = 'reply') -> None:
        if kind == 'reply':
            self.headers = (REPLY_HEADER,)
            id_ok = _table(lambda v: MIN_ID <= v <= MAX_ID)
            len_min = bytes([2] * 256)
            len_max = bytes([MAX_REPLY_LEN] * 256)
            make = Reply
        elif kind == 'request':
            self.headers = (REQUEST_HEADER,)
            id_ok = _table(lambda v: MIN_ID <= v <= MAX_ID or v == BROADCAST_ID)
            # Unknown instructions get an empty range (min 255 > max 0): no such frame exists.
            len_min = bytes(REQUEST_LEN_BOUNDS.get(v, (255, 0))[0] for v in range(256))
            len_max = bytes(REQUEST_LEN_BOUNDS.get(v, (255, 0))[1] for v in range(256))
            make = Request
        else:
            raise ValueError(f'kind must be "reply" or "request", got {kind!r}')
        self.kind = kind
        super().__init__()
        self._candidate = _candidate_judge(id_ok, len_min, len_max, make)


def _candidate_judge(id_ok: bytes, len_min: bytes, len_max: bytes, make: type):
    """Return the decoder's ``_candidate``: a closure over its tables, the hot loop's call."""
    def candidate(buf: bytearray, pos: int, n: int, final: bool, out: list) -> int:
        if n - pos < 5:
            return WAIT
        length = buf[pos + 3]
        code = buf[pos + 4]
        if not id_ok[buf[pos + 2]] or length < len_min[code] or length > len_max[code]:
            return DROP
        end = pos + length + 4
        if end > n:
            return WAIT
        raw = bytes(buf[pos:end])
        if ~sum(raw[2:-1]) & 0xFF != raw[-1]:
            return BAD_CHECKSUM
        out.append(make(raw[2], code, raw[5:-1], raw))
        return length + 4
    return candidate
