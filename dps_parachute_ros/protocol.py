"""DPS-S parachute module serial protocol: frame builders, typed decoders and a stream decoder.

Pure functions and immutable dataclasses only: no I/O, no threads, no ROS. Values cross this
module's boundary in SI units (degrees where a name says ``_deg``, g where it says ``_g``); raw
bytes stay on every decoded object as ``raw``. Decision numbers (P1..) refer to
``docs/protocols.md``.

This module is the public face: every caller imports from here. The code lives in siblings by
responsibility: ``protocol_frames`` (codes, checksum, frames), ``protocol_encoders`` (SI values
to bytes, host commands, module frames), ``protocol_replies`` (typed module messages) and
``protocol_decoder`` (the stream decoder).
"""

from __future__ import annotations

from dps_parachute_ros.protocol_frames import (
    ATTITUDE_THRESHOLD_RANGE_DEG, BAUD_CODES, BAUD_TO_CODE, build_frame, checksum,
    ChecksumError, CMD_ARM, CMD_ARMED, CMD_ATTITUDE_THRESHOLD, CMD_ATTITUDE_TRIGGER,
    CMD_BAUD_RATE, CMD_BOOT_COUNT, CMD_CELL_VOLTAGE, CMD_CHARGING, CMD_DEPLOY,
    CMD_FREEFALL_THRESHOLD, CMD_FREEFALL_TIME, CMD_FREEFALL_TRIGGER, CMD_HEARTBEAT,
    CMD_LIGHT_LEVEL, CMD_LIGHT_THRESHOLD, CMD_SENSOR_ZERO, CMD_SHUTDOWN, CMD_STATUS,
    CMD_STREAMING, CMD_TRIGGER_RECORDS, CMD_TRIGGER_REQUEST, CMD_TRIGGERED, CONFIRM_PAYLOAD,
    CTRL_QUERY, CTRL_SET, Direction, FlagLayout, Frame, FRAME_LEN, FrameError,
    FREEFALL_THRESHOLD_RANGE_RAW, FREEFALL_TIME_RANGE_RAW, HEARTBEAT_PAYLOAD, HOST_CODES,
    host_frame, HOST_HEADER, KNOWN_SOURCE_BITS, LIGHT_THRESHOLD_RANGE_RAW, MODULE_CODES,
    module_frame, MODULE_HEADER, parse_frame, ProtocolError, ProtocolRangeError,
    RECORD_FRAME_LEN, REPLY_CODES, SOURCE_ATTITUDE, SOURCE_FREEFALL, SOURCE_PWM, SOURCE_SERIAL,
    STATUS_FRAME_LEN,
)
from dps_parachute_ros.protocol_encoders import (
    attitude_threshold_to_raw, baud_to_code, encode_arm, encode_armed_query,
    encode_attitude_threshold_query, encode_attitude_threshold_set, encode_attitude_trigger,
    encode_auto_trigger_query, encode_baud_rate_set, encode_boot_count_query,
    encode_cell_voltage_query, encode_charging_query, encode_deploy,
    encode_freefall_threshold_query, encode_freefall_threshold_set, encode_freefall_time_query,
    encode_freefall_time_set, encode_freefall_trigger, encode_heartbeat,
    encode_light_level_query, encode_light_threshold_query, encode_light_threshold_set,
    encode_module_heartbeat, encode_sensor_zero, encode_shutdown, encode_status_frame,
    encode_status_query, encode_streaming, encode_trigger_confirm, encode_trigger_record,
    encode_trigger_records_query, encode_trigger_request, encode_triggered_query,
    freefall_threshold_to_raw, freefall_time_to_raw, light_threshold_to_raw,
)
from dps_parachute_ros.protocol_replies import (
    ArmedState, ArmReply, AttitudeThreshold, AutoTriggerFlags, BaudRate, BootCount,
    CellVoltage, Charging, decode_auto_trigger_flags, decode_module_bytes, decode_module_frame,
    DeployAck, encode_auto_trigger_flags, FreefallThreshold, FreefallTime, Heartbeat,
    is_set_ack, LightLevel, LightThreshold, ModuleMessage, RECORD_SLOTS, reply_matches,
    ShutdownAck, Status, StreamingReply, TriggeredState, TriggerRecord, TriggerRecords,
    TriggerRequest, UnknownFrame, ZeroAck,
)
from dps_parachute_ros.protocol_decoder import StreamDecoder

__all__ = [
    'HOST_HEADER', 'MODULE_HEADER', 'CTRL_SET', 'CTRL_QUERY', 'CMD_HEARTBEAT', 'CMD_ARM',
    'CMD_DEPLOY', 'CMD_SHUTDOWN', 'CMD_STREAMING', 'CMD_LIGHT_LEVEL', 'CMD_LIGHT_THRESHOLD',
    'CMD_ATTITUDE_TRIGGER', 'CMD_FREEFALL_TRIGGER', 'CMD_ATTITUDE_THRESHOLD',
    'CMD_FREEFALL_THRESHOLD', 'CMD_FREEFALL_TIME', 'CMD_BOOT_COUNT', 'CMD_BAUD_RATE',
    'CMD_SENSOR_ZERO', 'CMD_ARMED', 'CMD_TRIGGERED', 'CMD_STATUS', 'CMD_CHARGING',
    'CMD_CELL_VOLTAGE', 'CMD_TRIGGER_RECORDS', 'CMD_TRIGGER_REQUEST', 'HEARTBEAT_PAYLOAD',
    'CONFIRM_PAYLOAD', 'FRAME_LEN', 'STATUS_FRAME_LEN', 'RECORD_FRAME_LEN', 'SOURCE_SERIAL',
    'SOURCE_ATTITUDE', 'SOURCE_PWM', 'SOURCE_FREEFALL', 'KNOWN_SOURCE_BITS', 'BAUD_CODES',
    'BAUD_TO_CODE', 'ATTITUDE_THRESHOLD_RANGE_DEG', 'FREEFALL_THRESHOLD_RANGE_RAW',
    'FREEFALL_TIME_RANGE_RAW', 'LIGHT_THRESHOLD_RANGE_RAW', 'MODULE_CODES', 'HOST_CODES',
    'REPLY_CODES', 'FlagLayout', 'Direction', 'ProtocolError', 'ProtocolRangeError',
    'ChecksumError', 'FrameError', 'checksum', 'build_frame', 'host_frame', 'module_frame',
    'Frame', 'parse_frame', 'attitude_threshold_to_raw', 'freefall_threshold_to_raw',
    'freefall_time_to_raw', 'light_threshold_to_raw', 'baud_to_code', 'encode_heartbeat',
    'encode_arm', 'encode_deploy', 'encode_shutdown', 'encode_streaming',
    'encode_light_level_query', 'encode_light_threshold_set', 'encode_light_threshold_query',
    'encode_attitude_trigger', 'encode_freefall_trigger', 'encode_auto_trigger_query',
    'encode_attitude_threshold_set', 'encode_attitude_threshold_query',
    'encode_freefall_threshold_set', 'encode_freefall_threshold_query',
    'encode_freefall_time_set', 'encode_freefall_time_query', 'encode_boot_count_query',
    'encode_baud_rate_set', 'encode_sensor_zero', 'encode_armed_query',
    'encode_triggered_query', 'encode_status_query', 'encode_charging_query',
    'encode_cell_voltage_query', 'encode_trigger_records_query', 'encode_trigger_confirm',
    'encode_module_heartbeat', 'encode_status_frame', 'encode_trigger_request',
    'encode_trigger_record', 'Heartbeat', 'ArmReply', 'DeployAck', 'ShutdownAck',
    'StreamingReply', 'LightLevel', 'LightThreshold', 'AutoTriggerFlags', 'AttitudeThreshold',
    'FreefallThreshold', 'FreefallTime', 'BootCount', 'BaudRate', 'ZeroAck', 'ArmedState',
    'TriggeredState', 'Status', 'Charging', 'CellVoltage', 'TriggerRecord', 'TriggerRecords',
    'RECORD_SLOTS', 'TriggerRequest',
    'UnknownFrame', 'ModuleMessage', 'decode_auto_trigger_flags', 'encode_auto_trigger_flags',
    'decode_module_frame', 'decode_module_bytes', 'is_set_ack', 'reply_matches',
    'StreamDecoder',
]
