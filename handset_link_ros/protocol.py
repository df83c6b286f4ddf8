"""Handset control link: frames, both payload encodings, validation and a stream decoder.

Pure functions and immutable dataclasses only: no I/O, no threads, no ROS. Decision numbers
(H1..) refer to ``docs/protocols.md``.

Frame (H1, H2): ``AA LEN TYPE PAYLOAD.. CHK 55``; ``LEN = len(PAYLOAD) + 2`` (the checksum and
end byte; TYPE is not counted), so a frame is ``LEN + 3`` bytes; ``CHK`` is the XOR of every byte
before it, the start byte included. Payloads are JSON (``{"yaw": 90}``) or binary, told apart by
their first and last byte and their length (H5).
"""

from __future__ import annotations

from dataclasses import dataclass
import enum
from functools import reduce
import json
import math
from operator import xor
import struct
from typing import Literal, Optional, Union

from uav_serial_common.stream_decoder import BAD_CHECKSUM, DROP, WAIT
from uav_serial_common.stream_decoder import StreamDecoder as BaseStreamDecoder

START = 0xAA
"""First byte of every frame."""
END = 0x55
"""Last byte of every frame."""
MIN_LEN = 2
"""LEN of a frame with an empty payload; anything smaller is invalid (H1)."""
MAX_LEN = 0xFF
MAX_PAYLOAD = MAX_LEN - 2
"""253 payload bytes at most: LEN is one byte and counts the checksum and end byte (H1)."""
OVERHEAD = 5
"""Start, LEN, TYPE, checksum and end byte around the payload."""
IDLE_TIMEOUT_S = 0.1
"""A partial frame followed by this much silence is malformed (H3)."""
_TIME_EPS = 1e-9
"""So that 10.1 - 10.0 (0.0999999...) counts as 0.1 s of silence."""


class CommandType(enum.IntEnum):
    """The TYPE byte of the seven commands (H4)."""

    SET_YAW = 0x01
    SET_PITCH = 0x02
    SET_ROLL = 0x03
    SET_ALTITUDE = 0x04
    SET_LIGHTS = 0x05
    SET_CAMERA_ANGLE = 0x06
    SET_CAMERA_RECORD = 0x07


Encoding = Literal['json', 'int8', 'int16', 'float32']
ENCODINGS: tuple[Encoding, ...] = ('json', 'int8', 'int16', 'float32')
BINARY_ENCODINGS: dict[int, Encoding] = {1: 'int8', 2: 'int16', 4: 'float32'}
"""Binary payload length to its encoding (H5); any other length is malformed."""
_STRUCT: dict[str, str] = {'int8': '<b', 'int16': '<h', 'float32': '<f'}
INT_LIMITS: dict[str, tuple[int, int]] = {'int8': (-128, 127), 'int16': (-32768, 32767)}
"""What the integer encodings can carry at all (before the H4 range of the type)."""


@dataclass(frozen=True, slots=True)
class CommandSpec:
    """What one command type carries: its JSON key, range and unit (H4, H5, H6)."""

    type: CommandType
    key: str
    lo: float
    hi: float
    whole: bool
    unit: str


SPECS: dict[int, CommandSpec] = {s.type: s for s in (
    CommandSpec(CommandType.SET_YAW, 'yaw', -180, 180, False, 'deg'),
    CommandSpec(CommandType.SET_PITCH, 'pitch', -90, 90, False, 'deg'),
    CommandSpec(CommandType.SET_ROLL, 'roll', -90, 90, False, 'deg'),
    CommandSpec(CommandType.SET_ALTITUDE, 'altitude', -100, 1000, False, 'm'),
    CommandSpec(CommandType.SET_LIGHTS, 'lights', 0, 100, True, '%'),
    CommandSpec(CommandType.SET_CAMERA_ANGLE, 'camera_angle', -90, 90, False, 'deg'),
    CommandSpec(CommandType.SET_CAMERA_RECORD, 'record', 0, 1, True, '(1 start, 0 stop)'),
)}
"""Command type to its spec (H4): ranges inclusive; ``whole`` fields take no fraction (H6)."""


class ProtocolError(ValueError):
    """Base class of every error this module raises."""


class ProtocolRangeError(ProtocolError):
    """A value given to an encoder is one the protocol does not allow (H6) or cannot carry."""


# ---------------------------------------------------------------------------------------------
# Decoded results
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class Command:
    """An accepted command: a sound frame of a known type with a valid value (H1-H6).

    ``value`` is a float for angles and altitude, an int for ``lights``, a bool for
    ``record``. ``bytes_after`` is how many bytes the decoder held after the frame's last byte
    when it was delivered (with the baud rate, it dates the last byte).
    """

    type: CommandType
    field: str
    value: Union[float, int, bool]
    encoding: Encoding
    raw: bytes
    bytes_after: int = 0


@dataclass(frozen=True, slots=True)
class Malformed:
    """Bytes rejected as malformed (H3, H5); ``reason`` says why.

    ``type`` is set when the frame itself was sound (start, LEN, checksum, end byte) and only
    its payload was malformed; it is None for a broken frame, whose TYPE byte means nothing.
    """

    reason: str
    raw: bytes
    type: Optional[CommandType] = None
    bytes_after: int = 0


@dataclass(frozen=True, slots=True)
class OutOfRange:
    """A well-formed command whose value is refused whole (H6): never clamped or rounded."""

    type: CommandType
    field: str
    value: float
    encoding: Encoding
    reason: str
    raw: bytes
    bytes_after: int = 0


@dataclass(frozen=True, slots=True)
class UnknownType:
    """A sound frame whose TYPE is none of the seven (H4): counted and ignored."""

    type: int
    raw: bytes
    bytes_after: int = 0


Decoded = Union[Command, Malformed, OutOfRange, UnknownType]


# ---------------------------------------------------------------------------------------------
# Frames and encoders
# ---------------------------------------------------------------------------------------------

def checksum(data: Union[bytes, bytearray]) -> int:
    """Return the H2 checksum: the XOR of ``data`` (start byte to the last payload byte)."""
    return reduce(xor, data, 0)


def build_frame(type_: int, payload: Union[bytes, bytearray]) -> bytes:
    """Assemble ``AA LEN TYPE PAYLOAD CHK 55`` (H1, H2) around any payload of 0..253 bytes."""
    if isinstance(type_, bool) or not isinstance(type_, int) or not 0 <= type_ <= 0xFF:
        raise ProtocolError(f'frame type must be a byte 0..255, got {type_!r}')
    payload = bytes(payload)
    if len(payload) > MAX_PAYLOAD:
        raise ProtocolError(f'a payload holds at most {MAX_PAYLOAD} bytes, got {len(payload)}')
    body = bytes((START, len(payload) + 2, type_)) + payload
    return body + bytes((checksum(body), END))


def spec_of(type_: int) -> CommandSpec:
    """Return the spec of a command type; raise ProtocolError for an unknown one."""
    spec = SPECS.get(type_) if not isinstance(type_, bool) else None
    if spec is None:
        known = ', '.join(f'0x{t:02X} {SPECS[t].type.name}' for t in SPECS)
        raise ProtocolError(f'unknown command type {type_!r}; known: {known}')
    return spec


def range_problem(type_: int, value: object) -> Optional[str]:
    """Return why ``value`` is refused for ``type_`` under H6, or None when it is valid.

    Numbers only (a bool counts as 0/1 for ``record`` alone); NaN and inf are refused, a
    fraction for a whole field is refused, the range is inclusive.
    """
    spec = spec_of(type_)
    if isinstance(value, bool):
        if spec.type != CommandType.SET_CAMERA_RECORD:
            return f'{spec.key} must be a number, got {value!r}'
        value = int(value)
    if not isinstance(value, (int, float)):
        return f'{spec.key} must be a number, got {value!r}'
    if isinstance(value, float) and not math.isfinite(value):
        return f'{spec.key} {value} is not a finite number'
    if spec.whole and isinstance(value, float) and not value.is_integer():
        return f'{spec.key} {value!r} is not a whole number ({_range_text(spec)})'
    if not spec.lo <= value <= spec.hi:
        return f'{spec.key} {_fmt(value)} is out of range ({_range_text(spec)})'
    return None


def normalize(type_: int, value: Union[float, int, bool]) -> Union[float, int, bool]:
    """Return a valid value in its Python type: float, int (``lights``) or bool (``record``)."""
    spec = spec_of(type_)
    if spec.type == CommandType.SET_CAMERA_RECORD:
        return bool(value)
    if spec.whole:
        return int(value)
    return float(value)


def _range_text(spec: CommandSpec) -> str:
    kind = 'whole numbers ' if spec.whole else ''
    return f'allowed {kind}{_fmt(spec.lo)}..{_fmt(spec.hi)} {spec.unit}'


def _fmt(value: float) -> str:
    if isinstance(value, int):
        return str(value)
    return f'{value:.6g}'


def encode_payload(type_: int, value: Union[float, int, bool], encoding: Encoding = 'json', *,
                   check: bool = True) -> bytes:
    """Return the payload of a command in one of the H5 encodings.

    With ``check`` (the default) a value H6 refuses raises ProtocolRangeError before anything is
    built. ``check=False`` builds what the encoding can physically hold, for tests and the
    simulator (JSON then also writes ``NaN``, strings and out-of-range numbers). int8 and int16
    carry whole numbers only: a fraction or a number beyond the type always raises.
    """
    spec = spec_of(type_)
    if encoding not in ENCODINGS:
        raise ProtocolError(f'encoding must be one of {", ".join(ENCODINGS)}, got {encoding!r}')
    if check:
        problem = range_problem(type_, value)
        if problem is not None:
            raise ProtocolRangeError(f'{spec.type.name}: {problem}')
    if encoding == 'json':
        if spec.whole and isinstance(value, float) and value.is_integer():
            value = int(value)
        return json.dumps({spec.key: value}).encode()
    if isinstance(value, bool):
        value = int(value)
    if not isinstance(value, (int, float)):
        raise ProtocolRangeError(f'{spec.type.name}: {encoding} carries numbers, got {value!r}')
    if encoding == 'float32':
        try:
            return struct.pack('<f', value)
        except (OverflowError, struct.error) as exc:
            raise ProtocolRangeError(f'{spec.type.name}: float32 cannot carry {value!r}') from exc
    if isinstance(value, float) and not value.is_integer():
        raise ProtocolRangeError(
            f'{spec.type.name}: {encoding} carries whole numbers only, got {value!r}')
    lo, hi = INT_LIMITS[encoding]
    if not lo <= value <= hi:
        raise ProtocolRangeError(
            f'{spec.type.name}: {encoding} carries {lo}..{hi}, got {_fmt(value)}')
    return struct.pack(_STRUCT[encoding], int(value))


def encode_command(type_: int, value: Union[float, int, bool], encoding: Encoding = 'json', *,
                   check: bool = True) -> bytes:
    """Return a whole frame for one command (see ``encode_payload`` for ``check``)."""
    return build_frame(spec_of(type_).type, encode_payload(type_, value, encoding, check=check))


def encode_set_yaw(yaw_deg: float, encoding: Encoding = 'json') -> bytes:
    """SET_YAW 0x01, −180..180 deg."""
    return encode_command(CommandType.SET_YAW, yaw_deg, encoding)


def encode_set_pitch(pitch_deg: float, encoding: Encoding = 'json') -> bytes:
    """SET_PITCH 0x02, −90..90 deg."""
    return encode_command(CommandType.SET_PITCH, pitch_deg, encoding)


def encode_set_roll(roll_deg: float, encoding: Encoding = 'json') -> bytes:
    """SET_ROLL 0x03, −90..90 deg."""
    return encode_command(CommandType.SET_ROLL, roll_deg, encoding)


def encode_set_altitude(altitude_m: float, encoding: Encoding = 'json') -> bytes:
    """SET_ALTITUDE 0x04, −100..1000 m."""
    return encode_command(CommandType.SET_ALTITUDE, altitude_m, encoding)


def encode_set_lights(percent: int, encoding: Encoding = 'json') -> bytes:
    """SET_LIGHTS 0x05, whole 0..100 %."""
    return encode_command(CommandType.SET_LIGHTS, percent, encoding)


def encode_set_camera_angle(angle_deg: float, encoding: Encoding = 'json') -> bytes:
    """SET_CAMERA_ANGLE 0x06, −90..90 deg."""
    return encode_command(CommandType.SET_CAMERA_ANGLE, angle_deg, encoding)


def encode_set_camera_record(recording: Union[bool, int], encoding: Encoding = 'json') -> bytes:
    """SET_CAMERA_RECORD 0x07: 1 (or true) starts, 0 (or false) stops recording."""
    return encode_command(CommandType.SET_CAMERA_RECORD, recording, encoding)


# ---------------------------------------------------------------------------------------------
# Payload and frame decoding
# ---------------------------------------------------------------------------------------------

class _PayloadError(Exception):
    """A payload that is neither valid JSON of its type nor a binary form (H5)."""


def _no_constant(name: str) -> None:
    raise ValueError(f'{name} is not JSON')


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f'{text} does not fit a float64')
    return value


def _float64_int(text: str) -> int:
    value = int(text)
    try:
        float(value)
    except OverflowError:
        raise ValueError(f'{text[:20]}... does not fit a float64') from None
    return value


def _unique_keys(pairs: list) -> dict:
    keys = [k for k, _ in pairs]
    if len(set(keys)) != len(keys):
        raise ValueError(f'duplicate key in {keys}')
    return dict(pairs)


_JSON = json.JSONDecoder(parse_constant=_no_constant, parse_float=_finite_float,
                         parse_int=_float64_int, object_pairs_hook=_unique_keys)
"""The strict decoder of H5, made once (json.loads with hooks makes one per call)."""


def _decode_json(spec: CommandSpec, payload: bytes) -> Union[int, float]:
    try:
        text = payload.decode('utf-8')
    except UnicodeDecodeError:
        raise _PayloadError('JSON payload is not UTF-8') from None
    try:
        # A payload starting with '{' cannot start with a BOM, which json.loads also refuses.
        obj = _JSON.decode(text)
    except (ValueError, RecursionError) as exc:
        raise _PayloadError(f'invalid JSON: {exc}') from None
    if not isinstance(obj, dict) or list(obj) != [spec.key]:
        shown = list(obj) if isinstance(obj, dict) else type(obj).__name__
        raise _PayloadError(f'{spec.type.name} JSON must be an object with the one key '
                            f'"{spec.key}", got {shown}')
    value = obj[spec.key]
    if isinstance(value, bool):
        if spec.type != CommandType.SET_CAMERA_RECORD:
            raise _PayloadError(f'"{spec.key}" must be a number, got {json.dumps(value)}')
        return int(value)
    if not isinstance(value, (int, float)):
        raise _PayloadError(f'"{spec.key}" must be a number, got {json.dumps(value)[:40]}')
    return value


def decode_payload(type_: int, payload: Union[bytes, bytearray]) -> Decoded:
    """Type and check one payload (0..253 bytes) of a frame of ``type_`` (H4-H6).

    JSON when it starts with ``{`` and ends with ``}``, else binary by length (H5). No binary
    form of a valid value starts with ``7B`` and ends with ``7D`` (as int16 that is 32123, as
    float32 about 1e37), so the rule never hides a valid binary command.
    """
    payload = bytes(payload)
    raw = build_frame(type_, payload)
    return _interpret(raw, 0)


def _interpret(raw: bytes, bytes_after: int) -> Decoded:
    """Type a frame whose start, LEN, checksum and end byte are already known to be sound."""
    type_ = raw[2]
    spec = SPECS.get(type_)
    if spec is None:
        return UnknownType(type_, raw, bytes_after)
    payload = raw[3:-2]
    encoding: Encoding
    try:
        if len(payload) >= 2 and payload[0] == 0x7B and payload[-1] == 0x7D:
            encoding = 'json'
            value: Union[int, float] = _decode_json(spec, payload)
        else:
            binary = BINARY_ENCODINGS.get(len(payload))
            if binary is None:
                raise _PayloadError(f'{len(payload)}-byte payload is neither JSON nor '
                                    f'int8 (1), int16 (2) or float32 (4 bytes)')
            encoding = binary
            value = struct.unpack(_STRUCT[encoding], payload)[0]
    except _PayloadError as exc:
        return Malformed(f'{spec.type.name}: {exc}', raw, spec.type, bytes_after)
    problem = range_problem(spec.type, value)
    if problem is not None:
        return OutOfRange(spec.type, spec.key, float(value), encoding,
                          f'{spec.type.name}: {problem}', raw, bytes_after)
    return Command(spec.type, spec.key, normalize(spec.type, value), encoding, raw, bytes_after)


def decode_frame(raw: Union[bytes, bytearray]) -> Decoded:
    """Check and type exactly one complete frame (H1-H6); never raises, never guesses."""
    raw = bytes(raw)
    if len(raw) < OVERHEAD or raw[0] != START:
        return Malformed(f'not a frame: {raw.hex(" ")}', raw)
    length = raw[1]
    if length < MIN_LEN:
        return Malformed(f'LEN {length} < {MIN_LEN}', raw)
    if len(raw) != length + 3:
        return Malformed(f'LEN {length} says {length + 3} bytes, got {len(raw)}', raw)
    problem = _frame_problem(raw, 0, len(raw))
    if problem is not None:
        return Malformed(problem, raw)
    return _interpret(raw, 0)


def _frame_problem(buf: Union[bytes, bytearray], pos: int, end: int) -> Optional[str]:
    """Return what is wrong with the end byte or checksum of ``buf[pos:end]``, or None."""
    if buf[end - 1] != END:
        return f'end byte 0x{buf[end - 1]:02X}, expected 0x55'
    expected = reduce(xor, buf[pos:end - 2], 0)
    if buf[end - 2] != expected:
        return f'checksum 0x{buf[end - 2]:02X}, expected 0x{expected:02X}'
    return None


# ---------------------------------------------------------------------------------------------
# Stream decoder
# ---------------------------------------------------------------------------------------------

class StreamDecoder(BaseStreamDecoder):
    """Incremental decoder for the handset's byte stream (H3); never raises on input.

    ``feed(data, now)`` returns a ``Decoded`` for every frame settled by ``data``, in wire order:
    ``Command``, ``OutOfRange``, ``UnknownType`` for sound frames, ``Malformed`` for everything
    rejected. A candidate whose end byte or checksum is wrong, or whose LEN is below 2, is
    malformed and the search resumes at the byte after its start byte, so a frame hidden behind a
    truncated one is found. A partial frame is malformed once the line has been silent for
    ``idle_timeout_s``: pass ``now`` to ``feed`` (a gap before new bytes settles it first) and call
    ``flush(now)`` while the line is quiet, or ``flush()`` when the caller has measured the
    silence itself. A partial candidate is also given up as soon as a complete sound frame lies
    inside it (no accepted frame can hold one, H12), so a false start in noise never delays the
    frames behind it; so is a complete one whose payload is malformed, so a false start whose
    checksum matches by chance never swallows the frames inside it.

    Counters: ``frames_accepted``, ``frames_malformed``, ``frames_out_of_range``,
    ``frames_unknown_type``, and the base's ``frames_decoded`` (sound frames, whatever their
    payload), ``checksum_errors`` (complete candidates whose end byte is right and checksum
    wrong) and ``bytes_discarded`` (bytes outside sound frames, the start byte of each rejected
    candidate included, and bytes forgotten by ``reset``).
    """

    headers = (bytes([START]),)

    def __init__(self, idle_timeout_s: float = IDLE_TIMEOUT_S) -> None:
        super().__init__()
        self.idle_timeout_s = idle_timeout_s
        self._last_rx: Optional[float] = None
        self.frames_accepted = 0
        self.frames_malformed = 0
        self.frames_out_of_range = 0
        self.frames_unknown_type = 0

    def reset(self) -> None:
        """Forget held bytes (e.g. the port closed); they count as discarded, not malformed."""
        self.bytes_discarded += len(self._buf)
        super().reset()

    def feed(self, data: Union[bytes, bytearray], now: Optional[float] = None) -> list[Decoded]:
        """Add received bytes (read at ``now``, seconds) and return every result now settled."""
        settled: list[Decoded] = []
        if now is not None:
            if self._buf and self._last_rx is not None and \
                    now - self._last_rx >= self.idle_timeout_s - _TIME_EPS:
                settled = self._run(True)
            self._last_rx = now
        out = super().feed(data)
        return settled + out if settled else out

    def flush(self, now: Optional[float] = None) -> list[Decoded]:
        """Settle a held partial frame as malformed because the line went quiet (H3).

        With ``now``, only if nothing was fed for ``idle_timeout_s`` before it; without, at once.
        """
        if not self._buf:
            return []
        if now is not None and self._last_rx is not None and \
                now - self._last_rx < self.idle_timeout_s - _TIME_EPS:
            return []
        return self._run(True)

    def idle_deadline(self) -> Optional[float]:
        """Return when ``flush(now)`` would settle the held bytes, None if nothing is held."""
        if not self._buf or self._last_rx is None:
            return None
        return self._last_rx + self.idle_timeout_s

    def _candidate(self, buf: bytearray, pos: int, n: int, final: bool, out: list) -> int:
        avail = n - pos
        if avail < 2:
            if not final:
                return WAIT
            out.append(self._reject(pos, n, 1, 'truncated frame: a start byte, then silence'))
            return DROP
        length = buf[pos + 1]
        if length < MIN_LEN:
            out.append(self._reject(pos, n, 2, f'LEN {length} < {MIN_LEN}'))
            return DROP
        total = length + 3
        if avail < total:
            if final:
                reason = f'truncated frame: {avail} of {total} bytes, then silence'
            elif self._sound_frame_within(pos + 1, n):
                reason = (f'truncated frame: {avail} of {total} bytes, and a complete frame '
                          f'starts inside it')
            else:
                return WAIT
            out.append(self._reject(pos, n, total, reason))
            return DROP
        end = pos + total
        raw = bytes(buf[pos:end])
        if raw[-1] != END or reduce(xor, raw[:-2], 0) != raw[-2]:
            out.append(self._reject(pos, n, total, _frame_problem(buf, pos, end) or ''))
            return DROP if raw[-1] != END else BAD_CHECKSUM
        result = _interpret(raw, n - end)
        kind = type(result)
        if kind is Malformed and self._sound_frame_within(pos + 1, end):
            # H12 for a complete candidate: a sound-framed candidate whose payload is malformed
            # and that holds a complete sound frame is a false start (its checksum a 1-in-256
            # coincidence over noise and truncated frames), not a frame that swallows one.
            out.append(self._reject(pos, n, total, 'a complete frame starts inside it'))
            return DROP
        if kind is Command:
            self.frames_accepted += 1
        elif kind is OutOfRange:
            self.frames_out_of_range += 1
        elif kind is UnknownType:
            self.frames_unknown_type += 1
        else:
            self.frames_malformed += 1
        out.append(result)
        return total

    def _sound_frame_within(self, pos: int, n: int) -> bool:
        """Whether a complete frame with a good end byte and checksum starts in buf[pos:n]."""
        buf = self._buf
        q = buf.find(START, pos)
        while 0 <= q <= n - OVERHEAD:
            length = buf[q + 1]
            end = q + length + 3
            if length >= MIN_LEN and end <= n and _frame_problem(buf, q, end) is None:
                return True
            q = buf.find(START, q + 1)
        return False

    def _reject(self, pos: int, n: int, total: int, reason: str) -> Malformed:
        # The base counts the start byte as discarded when the candidate is abandoned.
        end = min(n, pos + total)
        self.frames_malformed += 1
        return Malformed(reason, bytes(self._buf[pos:end]), None, n - end)
