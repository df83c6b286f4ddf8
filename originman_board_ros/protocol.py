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

This module is the public face: every caller imports from here. The code lives in siblings by
responsibility: ``protocol_wire`` (codes and limits, range checks, CRC-8, frames, the host's
stream decoder), ``protocol_commands`` (host -> board commands), ``protocol_reports`` (board ->
host frames, built and typed) and ``protocol_firmware`` (the firmware's parser and its reading
of host commands).
"""

from __future__ import annotations

from originman_board_ros.protocol_wire import (
    ASR_MARKER, BAUD, BOARD_FUNCTION_LIMIT, BUS_BROADCAST_ID, BUS_DURATION_MAX_MS, BUS_FAILURE,
    BUS_ID_MAX, BUS_OFFSET_MAX, BUS_POSITION_MAX, BUS_READ_FORMATS, BUS_SUCCESS,
    BUS_TEMPERATURE_LIMIT_MAX_C, BUS_VOLTAGE_MAX_MV, BUS_VOLTAGE_MIN_MV, BusSub, crc8,
    CRC8_TABLE, encode_frame, Frame, FRAME_OVERHEAD, Function, HEADER, HOST_FUNCTION_MAX,
    KEY_EVENT_NAMES, KEY_IDS, KeyEvent, LED_IDS, MAX_BOARD_LENGTH, MAX_DATA, MAX_RPS,
    MOTOR_COUNT, MOTOR_TYPE_MAX_RPS, MotorSub, MotorType, OLED_LINES, OLED_TEXT_MAX_BYTES,
    parse_frame, ProtocolError, ProtocolRangeError, PWM_DURATION_MAX_MS, PWM_DURATION_MIN_MS,
    PWM_OFFSET_MAX_US, PWM_PULSE_MAX_US, PWM_PULSE_MIN_US, PWM_SERVO_COUNT, PwmSub,
    RGB_COMMAND, RGB_PIXEL_COUNT, SBUS_CHANNELS, StreamDecoder, SysSub, U16_MAX,
)
from originman_board_ros.protocol_commands import (
    encode_battery_limit, encode_bus_load, encode_bus_move, encode_bus_read,
    encode_bus_read_angle_limits, encode_bus_read_id, encode_bus_read_load,
    encode_bus_read_offset, encode_bus_read_position, encode_bus_read_temperature,
    encode_bus_read_temperature_limit, encode_bus_read_voltage, encode_bus_read_voltage_limits,
    encode_bus_save_offset, encode_bus_set_angle_limits, encode_bus_set_offset,
    encode_bus_set_temperature_limit, encode_bus_set_voltage_limits, encode_bus_stop,
    encode_bus_torque, encode_bus_unload, encode_bus_write_id, encode_buzzer, encode_led,
    encode_motor_speed, encode_motor_speeds, encode_motor_stop, encode_motor_stop_mask,
    encode_motor_type, encode_oled, encode_pwm_move, encode_pwm_move_one,
    encode_pwm_read_offset, encode_pwm_read_pulse, encode_pwm_set_offset, encode_rgb,
)
from originman_board_ros.protocol_reports import (
    AsrReport, BatteryReport, BoardMessage, BusServoReply, BusValue, decode_board_bytes,
    decode_board_frame, encode_asr_report, encode_battery_report, encode_bus_reply,
    encode_gamepad_report, encode_imu_report, encode_key_report, encode_pwm_offset_reply,
    encode_pwm_pulse_reply, encode_sbus_report, GamepadReport, ImuReport, KeyReport,
    PwmOffsetReply, PwmPulseReply, SbusReport, UnknownFrame,
)
from originman_board_ros.protocol_firmware import (
    BOARD_BUFFER, BoardParser, BusMove, BusRead, BusSaveOffset, BusSetLimits, BusSetOffset,
    BusSetTemperatureLimit, BusStop, BusTorque, BusWriteId, decode_host_command, HostCommand,
    HostFrame, IgnoredCommand, PwmMove, PwmRead, PwmSetOffset, SetBatteryLimit, SetBuzzer,
    SetLed, SetMotorSpeeds, SetMotorType, SetOledText, SetRgb, StopMotors,
)

__all__ = [
    'HEADER', 'FRAME_OVERHEAD', 'MAX_DATA', 'BAUD', 'Function', 'BOARD_FUNCTION_LIMIT',
    'HOST_FUNCTION_MAX', 'MAX_BOARD_LENGTH', 'SysSub', 'MotorSub', 'MotorType',
    'MOTOR_TYPE_MAX_RPS', 'MAX_RPS', 'MOTOR_COUNT', 'PwmSub', 'PWM_SERVO_COUNT',
    'PWM_PULSE_MIN_US', 'PWM_PULSE_MAX_US', 'PWM_DURATION_MIN_MS', 'PWM_DURATION_MAX_MS',
    'PWM_OFFSET_MAX_US', 'BusSub', 'BUS_READ_FORMATS', 'BUS_BROADCAST_ID', 'BUS_ID_MAX',
    'BUS_POSITION_MAX', 'BUS_DURATION_MAX_MS', 'BUS_OFFSET_MAX', 'BUS_VOLTAGE_MIN_MV',
    'BUS_VOLTAGE_MAX_MV', 'BUS_TEMPERATURE_LIMIT_MAX_C', 'BUS_SUCCESS', 'BUS_FAILURE',
    'KeyEvent', 'KEY_EVENT_NAMES', 'KEY_IDS', 'LED_IDS', 'OLED_LINES', 'OLED_TEXT_MAX_BYTES',
    'RGB_PIXEL_COUNT', 'RGB_COMMAND', 'SBUS_CHANNELS', 'ASR_MARKER', 'U16_MAX',
    'ProtocolError', 'ProtocolRangeError', 'CRC8_TABLE', 'crc8', 'encode_frame', 'Frame',
    'parse_frame', 'StreamDecoder', 'encode_battery_limit', 'encode_led', 'encode_buzzer',
    'encode_motor_speed', 'encode_motor_speeds', 'encode_motor_stop', 'encode_motor_stop_mask',
    'encode_motor_type', 'encode_pwm_move', 'encode_pwm_move_one', 'encode_pwm_read_pulse',
    'encode_pwm_set_offset', 'encode_pwm_read_offset', 'encode_bus_move', 'encode_bus_stop',
    'encode_bus_read', 'encode_bus_read_position', 'encode_bus_read_voltage',
    'encode_bus_read_temperature', 'encode_bus_unload', 'encode_bus_load', 'encode_bus_torque',
    'encode_bus_read_load', 'encode_bus_write_id', 'encode_bus_read_id',
    'encode_bus_set_offset', 'encode_bus_read_offset', 'encode_bus_save_offset',
    'encode_bus_set_angle_limits', 'encode_bus_read_angle_limits',
    'encode_bus_set_voltage_limits', 'encode_bus_read_voltage_limits',
    'encode_bus_set_temperature_limit', 'encode_bus_read_temperature_limit', 'encode_oled',
    'encode_rgb', 'encode_battery_report', 'encode_key_report', 'encode_imu_report',
    'encode_gamepad_report', 'encode_sbus_report', 'encode_asr_report',
    'encode_pwm_pulse_reply', 'encode_pwm_offset_reply', 'BusValue', 'encode_bus_reply',
    'BatteryReport', 'KeyReport', 'ImuReport', 'GamepadReport', 'SbusReport', 'AsrReport',
    'PwmPulseReply', 'PwmOffsetReply', 'BusServoReply', 'UnknownFrame', 'BoardMessage',
    'decode_board_frame', 'decode_board_bytes', 'BOARD_BUFFER', 'HostFrame', 'BoardParser',
    'SetBatteryLimit', 'SetLed', 'SetBuzzer', 'SetMotorSpeeds', 'StopMotors', 'SetMotorType',
    'PwmMove', 'PwmRead', 'PwmSetOffset', 'BusMove', 'BusStop', 'BusRead', 'BusTorque',
    'BusWriteId', 'BusSetOffset', 'BusSaveOffset', 'BusSetLimits', 'BusSetTemperatureLimit',
    'SetOledText', 'SetRgb', 'IgnoredCommand', 'HostCommand', 'decode_host_command',
]
