"""DPS-S protocol: SI values to raw bytes with range checks, host commands, module frames.

Values cross this boundary in SI units (degrees where a name says ``_deg``, g where it says
``_g``). Decision numbers (P1..) refer to ``docs/protocols.md``.
"""

from __future__ import annotations

import math

from dps_parachute_ros.protocol_frames import (
    _byte, ATTITUDE_THRESHOLD_RANGE_DEG, BAUD_TO_CODE, build_frame, CMD_ARM, CMD_ARMED,
    CMD_ATTITUDE_THRESHOLD, CMD_ATTITUDE_TRIGGER, CMD_BAUD_RATE, CMD_BOOT_COUNT,
    CMD_CELL_VOLTAGE, CMD_CHARGING, CMD_DEPLOY, CMD_FREEFALL_THRESHOLD, CMD_FREEFALL_TIME,
    CMD_FREEFALL_TRIGGER, CMD_HEARTBEAT, CMD_LIGHT_LEVEL, CMD_LIGHT_THRESHOLD, CMD_SENSOR_ZERO,
    CMD_SHUTDOWN, CMD_STATUS, CMD_STREAMING, CMD_TRIGGER_RECORDS, CMD_TRIGGER_REQUEST,
    CMD_TRIGGERED, CONFIRM_PAYLOAD, CTRL_QUERY, CTRL_SET, FrameError,
    FREEFALL_THRESHOLD_RANGE_RAW, FREEFALL_TIME_RANGE_RAW, HEARTBEAT_PAYLOAD, host_frame,
    HOST_HEADER, LIGHT_THRESHOLD_RANGE_RAW, MODULE_HEADER, ProtocolRangeError,
)


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
