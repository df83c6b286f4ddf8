"""Wire format of the OriginMan expansion board: encoders, typed decoders, stream decoders.

Pure functions and immutable dataclasses only: no I/O, no threads, no ROS. Decision numbers
(O1..) refer to ``docs/protocols.md`` ("OriginMan expansion board").

Every frame, in both directions, is ``AA 55 FUNCTION LENGTH DATA[LENGTH] CRC`` with
``CRC = crc8(FUNCTION, LENGTH, DATA...)`` (CRC-8/MAXIM-DOW, init 0, O1); multi-byte fields are
little-endian and packed. The encoders refuse, with a :class:`ProtocolRangeError` naming the
field and its range, anything the board would misread or that would reach undefined firmware
behaviour (motor wire id 4, PWM id 0, OLED text over 23 bytes ...), so nothing out of range is
ever encoded. Decoders never raise on board output: a frame they cannot type becomes an
:class:`UnknownFrame`.

Two stream decoders: :class:`StreamDecoder` is the host's (resynchronises by hunting for
``AA 55``, accepts FUNCTION 0..12, §2.4 of the board's protocol), :class:`BoardParser` is the
firmware's own parser with its quirks (O21, O22), for the device model.
"""

from __future__ import annotations

from dataclasses import dataclass
import enum
import math
import struct
from typing import Iterable, Optional, Sequence, Tuple, Union

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


# ---------------------------------------------------------------------------------------------
# Host -> board commands
# ---------------------------------------------------------------------------------------------

def encode_battery_limit(limit_mv: int) -> bytes:
    """SYS 0x01: the low-battery alarm threshold in mV (the board's default is 6300)."""
    _int('battery limit [mV]', limit_mv, 0, U16_MAX)
    return encode_frame(Function.SYS, struct.pack('<BH', SysSub.BATTERY_LIMIT, limit_mv))


def encode_led(led_id: int, on_ms: int, off_ms: int, repeat: int) -> bytes:
    """LED pattern: on 0 = off, off 0 = steady on, else blink ``repeat`` times (0 = forever, O31).

    Only LEDs 1 and 2 exist (O25).
    """
    _int('led_id', led_id, LED_IDS[0], LED_IDS[-1])
    _int('LED on time [ms]', on_ms, 0, U16_MAX)
    _int('LED off time [ms]', off_ms, 0, U16_MAX)
    _int('LED repeat', repeat, 0, U16_MAX)
    return encode_frame(Function.LED, struct.pack('<BHHH', led_id, on_ms, off_ms, repeat))


def encode_buzzer(frequency_hz: int, on_ms: int, off_ms: int, repeat: int) -> bytes:
    """Buzzer pattern, the LED's rules plus frequency 0 = silent (O31)."""
    _int('buzzer frequency [Hz]', frequency_hz, 0, U16_MAX)
    _int('buzzer on time [ms]', on_ms, 0, U16_MAX)
    _int('buzzer off time [ms]', off_ms, 0, U16_MAX)
    _int('buzzer repeat', repeat, 0, U16_MAX)
    return encode_frame(Function.BUZZER,
                        struct.pack('<HHHH', frequency_hz, on_ms, off_ms, repeat))


def _motor_id(value: object) -> int:
    # O3: wire ids are 0-based; 4 and above index past the firmware's motor table.
    return _int('motor wire id', value, 0, MOTOR_COUNT - 1,
                f'a wire id 0..{MOTOR_COUNT - 1} (motors 1..4, O3)')


def encode_motor_speed(wire_id: int, rps: float) -> bytes:
    """MOTOR 0x00: the speed set-point of one motor, revolutions per second (signed)."""
    _motor_id(wire_id)
    speed = _float('motor speed [rps]', rps, MAX_RPS)
    return encode_frame(Function.MOTOR, struct.pack('<BBf', MotorSub.SET_ONE, wire_id, speed))


def encode_motor_speeds(items: Sequence[Tuple[int, float]]) -> bytes:
    """MOTOR 0x01: set-points of several motors, ``[(wire_id, rps), ...]``."""
    _count('motor list', items, 1, MOTOR_COUNT)
    data = bytearray((MotorSub.SET_MANY, len(items)))
    for wire_id, rps in items:
        _motor_id(wire_id)
        data += struct.pack('<Bf', wire_id, _float('motor speed [rps]', rps, MAX_RPS))
    _distinct('motor wire ids', [i for i, _ in items])
    return encode_frame(Function.MOTOR, data)


def encode_motor_stop(wire_id: int) -> bytes:
    """MOTOR 0x02: set-point 0 for one motor."""
    _motor_id(wire_id)
    return encode_frame(Function.MOTOR, bytes((MotorSub.STOP_ONE, wire_id)))


def encode_motor_stop_mask(mask: int) -> bytes:
    """MOTOR 0x03: set-point 0 for every motor whose wire id's bit is set (O4)."""
    _int('motor stop mask', mask, 0, (1 << MOTOR_COUNT) - 1,
         'a mask 0x0..0xF (bit i = wire id i, O4)')
    return encode_frame(Function.MOTOR, bytes((MotorSub.STOP_MASK, mask)))


def encode_motor_type(motor_type: int) -> bytes:
    """MOTOR 0x05: the motor model of all four motors (O5)."""
    _int('motor type', motor_type, 0, len(MotorType) - 1,
         'a motor type 0..3 (JGB520, JGB37, JGA27, JGB528)')
    return encode_frame(Function.MOTOR, bytes((MotorSub.SET_TYPE, motor_type)))


def _pwm_id(value: object) -> int:
    return _int('PWM servo id', value, 1, PWM_SERVO_COUNT, f'1..{PWM_SERVO_COUNT} (O30)')


def _pwm_pulse(value: object) -> int:
    return _int('PWM pulse [us]', value, PWM_PULSE_MIN_US, PWM_PULSE_MAX_US)


def _pwm_duration(value: object) -> int:
    return _int('PWM move duration [ms]', value, PWM_DURATION_MIN_MS, PWM_DURATION_MAX_MS)


def encode_pwm_move(duration_ms: int, items: Sequence[Tuple[int, int]]) -> bytes:
    """PWM_SERVO 0x01: move servos ``[(id, pulse_us), ...]`` in ``duration_ms`` (O10)."""
    _pwm_duration(duration_ms)
    _count('PWM servo list', items, 1, PWM_SERVO_COUNT)
    data = bytearray(struct.pack('<BHB', PwmSub.MOVE_MANY, duration_ms, len(items)))
    for servo_id, pulse in items:
        data += struct.pack('<BH', _pwm_id(servo_id), _pwm_pulse(pulse))
    _distinct('PWM servo ids', [i for i, _ in items])
    return encode_frame(Function.PWM_SERVO, data)


def encode_pwm_move_one(duration_ms: int, servo_id: int, pulse_us: int) -> bytes:
    """PWM_SERVO 0x03: move exactly one servo (O10)."""
    _pwm_duration(duration_ms)
    return encode_frame(Function.PWM_SERVO, struct.pack(
        '<BHBH', PwmSub.MOVE_ONE, duration_ms, _pwm_id(servo_id), _pwm_pulse(pulse_us)))


def encode_pwm_read_pulse(servo_id: int) -> bytes:
    """PWM_SERVO 0x05: ask for the current pulse (without the offset); answered."""
    return encode_frame(Function.PWM_SERVO, bytes((PwmSub.READ_PULSE, _pwm_id(servo_id))))


def encode_pwm_set_offset(servo_id: int, offset_us: int) -> bytes:
    """PWM_SERVO 0x07: the servo's offset (deviation) in us, -100..100."""
    _pwm_id(servo_id)
    _int('PWM offset [us]', offset_us, -PWM_OFFSET_MAX_US, PWM_OFFSET_MAX_US)
    return encode_frame(Function.PWM_SERVO,
                        struct.pack('<BBb', PwmSub.SET_OFFSET, servo_id, offset_us))


def encode_pwm_read_offset(servo_id: int) -> bytes:
    """PWM_SERVO 0x09: ask for the servo's offset; answered with sub-command 0x09 (O11)."""
    return encode_frame(Function.PWM_SERVO, bytes((PwmSub.READ_OFFSET, _pwm_id(servo_id))))


def encode_bus_move(duration_ms: int, items: Sequence[Tuple[int, int]]) -> bytes:
    """BUS_SERVO 0x01: move servos ``[(id, position 0..1000), ...]`` in ``duration_ms`` (O23)."""
    _int('bus servo move duration [ms]', duration_ms, 0, BUS_DURATION_MAX_MS)
    _count('bus servo list', items, 1, (MAX_DATA - 4) // 3)
    data = bytearray(struct.pack('<BHB', BusSub.MOVE, duration_ms, len(items)))
    for servo_id, position in items:
        _bus_id('bus servo id', servo_id)
        _int('bus servo position', position, 0, BUS_POSITION_MAX)
        data += struct.pack('<BH', servo_id, position)
    _distinct('bus servo ids', [i for i, _ in items])
    return encode_frame(Function.BUS_SERVO, data)


def encode_bus_stop(ids: Sequence[int]) -> bytes:
    """BUS_SERVO 0x03: stop servos where they are."""
    _count('bus servo list', ids, 1, MAX_DATA - 2)
    for servo_id in ids:
        _bus_id('bus servo id', servo_id)
    _distinct('bus servo ids', ids)
    return encode_frame(Function.BUS_SERVO, bytes((BusSub.STOP, len(ids))) + bytes(ids))


def _bus_simple(sub: int, servo_id: int) -> bytes:
    return encode_frame(Function.BUS_SERVO, bytes((sub, _bus_id('bus servo id', servo_id))))


def encode_bus_read(sub: int, servo_id: int) -> bytes:
    """Any of the nine BUS_SERVO reads (``BUS_READ_FORMATS``); the board answers each."""
    if sub not in BUS_READ_FORMATS:
        raise ProtocolRangeError('bus servo read sub-command', sub,
                                 'one of ' + ', '.join(f'0x{s:02X}' for s in BUS_READ_FORMATS))
    return _bus_simple(sub, servo_id)


def encode_bus_read_position(servo_id: int) -> bytes:
    """BUS_SERVO 0x05: read the position (0..1000, may be outside with offsets, O23)."""
    return _bus_simple(BusSub.READ_POSITION, servo_id)


def encode_bus_read_voltage(servo_id: int) -> bytes:
    """BUS_SERVO 0x07: read the input voltage in mV."""
    return _bus_simple(BusSub.READ_VOLTAGE, servo_id)


def encode_bus_read_temperature(servo_id: int) -> bytes:
    """BUS_SERVO 0x09: read the temperature in degrees Celsius."""
    return _bus_simple(BusSub.READ_TEMPERATURE, servo_id)


def encode_bus_unload(servo_id: int) -> bytes:
    """BUS_SERVO 0x0B: torque off (O6)."""
    return _bus_simple(BusSub.UNLOAD, servo_id)


def encode_bus_load(servo_id: int) -> bytes:
    """BUS_SERVO 0x0C: torque on (O6)."""
    return _bus_simple(BusSub.LOAD, servo_id)


def encode_bus_torque(servo_id: int, enable: bool) -> bytes:
    """Torque on (0x0C) or off (0x0B), the right way round whatever the SDK says (O6)."""
    return encode_bus_load(servo_id) if enable else encode_bus_unload(servo_id)


def encode_bus_read_load(servo_id: int) -> bytes:
    """BUS_SERVO 0x0D: read whether the servo is loaded (torque on)."""
    return _bus_simple(BusSub.READ_LOAD, servo_id)


def encode_bus_write_id(servo_id: int, new_id: int) -> bytes:
    """BUS_SERVO 0x10: give a servo a new id (``servo_id`` 0xFE with one servo on the bus)."""
    _bus_id('bus servo id', servo_id)
    _int('new bus servo id', new_id, 0, BUS_ID_MAX)
    return encode_frame(Function.BUS_SERVO, bytes((BusSub.WRITE_ID, servo_id, new_id)))


def encode_bus_read_id(servo_id: int = BUS_BROADCAST_ID) -> bytes:
    """BUS_SERVO 0x12: read the id (with 0xFE only one servo may be on the bus)."""
    return _bus_simple(BusSub.READ_ID, servo_id)


def encode_bus_set_offset(servo_id: int, offset: int) -> bytes:
    """BUS_SERVO 0x20: the servo's deviation adjustment, -125..125 (not saved, see 0x24)."""
    _bus_id('bus servo id', servo_id)
    _int('bus servo offset', offset, -BUS_OFFSET_MAX, BUS_OFFSET_MAX)
    return encode_frame(Function.BUS_SERVO,
                        struct.pack('<BBb', BusSub.SET_OFFSET, servo_id, offset))


def encode_bus_read_offset(servo_id: int) -> bytes:
    """BUS_SERVO 0x22: read the deviation."""
    return _bus_simple(BusSub.READ_OFFSET, servo_id)


def encode_bus_save_offset(servo_id: int) -> bytes:
    """BUS_SERVO 0x24: store the deviation in the servo's flash."""
    return _bus_simple(BusSub.SAVE_OFFSET, servo_id)


def encode_bus_set_angle_limits(servo_id: int, low: int, high: int) -> bytes:
    """BUS_SERVO 0x30: position limits, 0 <= low <= high <= 1000 (O24)."""
    _bus_id('bus servo id', servo_id)
    _int('bus servo min position', low, 0, BUS_POSITION_MAX)
    _int('bus servo max position', high, low, BUS_POSITION_MAX,
         f'an integer in {low}..{BUS_POSITION_MAX} (not below the min position)')
    return encode_frame(Function.BUS_SERVO,
                        struct.pack('<BBHH', BusSub.SET_ANGLE_LIMITS, servo_id, low, high))


def encode_bus_read_angle_limits(servo_id: int) -> bytes:
    """BUS_SERVO 0x32: read the position limits."""
    return _bus_simple(BusSub.READ_ANGLE_LIMITS, servo_id)


def encode_bus_set_voltage_limits(servo_id: int, low_mv: int, high_mv: int) -> bytes:
    """BUS_SERVO 0x34: input voltage limits, 4500 <= low <= high <= 14000 mV (O24)."""
    _bus_id('bus servo id', servo_id)
    _int('bus servo min voltage [mV]', low_mv, BUS_VOLTAGE_MIN_MV, BUS_VOLTAGE_MAX_MV)
    _int('bus servo max voltage [mV]', high_mv, low_mv, BUS_VOLTAGE_MAX_MV,
         f'an integer in {low_mv}..{BUS_VOLTAGE_MAX_MV} (not below the min voltage)')
    return encode_frame(Function.BUS_SERVO, struct.pack(
        '<BBHH', BusSub.SET_VOLTAGE_LIMITS, servo_id, low_mv, high_mv))


def encode_bus_read_voltage_limits(servo_id: int) -> bytes:
    """BUS_SERVO 0x36: read the voltage limits."""
    return _bus_simple(BusSub.READ_VOLTAGE_LIMITS, servo_id)


def encode_bus_set_temperature_limit(servo_id: int, max_c: int) -> bytes:
    """BUS_SERVO 0x38: the over-temperature limit, 1..100 degrees Celsius (O24)."""
    _bus_id('bus servo id', servo_id)
    _int('bus servo max temperature [C]', max_c, 1, BUS_TEMPERATURE_LIMIT_MAX_C)
    return encode_frame(Function.BUS_SERVO,
                        bytes((BusSub.SET_TEMPERATURE_LIMIT, servo_id, max_c)))


def encode_bus_read_temperature_limit(servo_id: int) -> bytes:
    """BUS_SERVO 0x3A: read the temperature limit."""
    return _bus_simple(BusSub.READ_TEMPERATURE_LIMIT, servo_id)


def encode_oled(line: int, text: Union[str, bytes]) -> bytes:
    """OLED: one line of text (1 or 2), at most 23 bytes of UTF-8, no terminator (O19)."""
    _int('OLED line', line, OLED_LINES[0], OLED_LINES[-1])
    if isinstance(text, str):
        data = text.encode('utf-8')
    elif isinstance(text, (bytes, bytearray)):
        data = bytes(text)
    else:
        raise ProtocolRangeError('OLED text', text, 'a string')
    if len(data) > OLED_TEXT_MAX_BYTES:
        raise ProtocolRangeError('OLED text', text,
                                 f'at most {OLED_TEXT_MAX_BYTES} bytes of UTF-8 '
                                 f'(this is {len(data)})')
    return encode_frame(Function.OLED, bytes((line, len(data))) + data)


def encode_rgb(pixels: Sequence[Tuple[int, int, int, int]]) -> bytes:
    """RGB: colours of pixels ``[(index, r, g, b), ...]``, index 0-based: 0 or 1 (O18)."""
    _count('RGB pixel list', pixels, 1, RGB_PIXEL_COUNT)
    data = bytearray((RGB_COMMAND, len(pixels)))
    for pixel in pixels:
        if not isinstance(pixel, (list, tuple)) or len(pixel) != 4:
            raise ProtocolRangeError('RGB pixel', pixel, 'an (index, red, green, blue) tuple')
        index, r, g, b = pixel
        _int('RGB pixel index', index, 0, RGB_PIXEL_COUNT - 1,
             f'0..{RGB_PIXEL_COUNT - 1} (0-based on the wire, O18)')
        for name, value in (('red', r), ('green', g), ('blue', b)):
            _int(f'RGB {name}', value, 0, 255)
        data += bytes((index, r, g, b))
    _distinct('RGB pixel indices', [p[0] for p in pixels])
    return encode_frame(Function.RGB, data)


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
class Frame:
    """One CRC-checked frame as the host's decoder found it."""

    function: int
    data: bytes
    raw: bytes


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
