"""OriginMan board: the host's commands (SYS, LED/buzzer, motors, PWM and bus servos, OLED, RGB).

The encoders refuse, with a :class:`ProtocolRangeError` naming the field and its range,
anything the board would misread or that would reach undefined firmware behaviour (motor wire
id 4, PWM id 0, OLED text over 23 bytes ...), so nothing out of range is ever encoded.
"""

from __future__ import annotations

import struct
from typing import Sequence, Tuple, Union

from originman_board_ros.protocol_wire import (
    _bus_id, _count, _distinct, _float, _int, BUS_BROADCAST_ID, BUS_DURATION_MAX_MS,
    BUS_ID_MAX, BUS_OFFSET_MAX, BUS_POSITION_MAX, BUS_READ_FORMATS,
    BUS_TEMPERATURE_LIMIT_MAX_C, BUS_VOLTAGE_MAX_MV, BUS_VOLTAGE_MIN_MV, BusSub, encode_frame,
    Function, LED_IDS, MAX_DATA, MAX_RPS, MOTOR_COUNT, MotorSub, MotorType, OLED_LINES,
    OLED_TEXT_MAX_BYTES, ProtocolRangeError, PWM_DURATION_MAX_MS, PWM_DURATION_MIN_MS,
    PWM_OFFSET_MAX_US, PWM_PULSE_MAX_US, PWM_PULSE_MIN_US, PWM_SERVO_COUNT, PwmSub,
    RGB_COMMAND, RGB_PIXEL_COUNT, SysSub, U16_MAX,
)


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
