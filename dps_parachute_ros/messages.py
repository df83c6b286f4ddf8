"""Snapshots and events of the parachute session as ROS messages: pure functions, no I/O.

Each builder takes what it needs (a `Snapshot`, an event, the stamp and frame id) and returns a
message; the node publishes it. Units are SI; what the module has not told is NaN (floats) or
false (flags), as the message definitions say.
"""

from __future__ import annotations

import math
from typing import Optional

from builtin_interfaces.msg import Time
from sensor_msgs.msg import BatteryState
from std_msgs.msg import Bool

from dps_parachute_ros import protocol as p
from dps_parachute_ros.state import (Deployment, RequestDecision, SETTINGS, Snapshot,
                                     source_name)
from uav_serial_common import cdr
from uav_serial_drivers.msg import (ParachuteConfig, ParachuteStatus, TriggerEvent,
                                    TriggerRecord, TriggerRequest)

NAN = math.nan
VIA = {'deploy_ack': TriggerEvent.VIA_DEPLOY_ACK, 'status': TriggerEvent.VIA_STATUS,
       'record': TriggerEvent.VIA_RECORD}
DECISIONS = {'confirmed': TriggerRequest.CONFIRMED, 'denied': TriggerRequest.DENIED,
             'timed_out': TriggerRequest.TIMED_OUT}


def _f(value: Optional[float]) -> float:
    return NAN if value is None else float(value)


def _header(msg, stamp: Time, frame_id: str):
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    return msg


def status_msg(snap: Snapshot, stamp: Time, frame_id: str) -> ParachuteStatus:
    """`~/status` from a snapshot."""
    msg = ParachuteStatus(
        online=snap.online, armed=bool(snap.armed), triggered=bool(snap.triggered),
        tilt_deg=_f(snap.tilt_deg), accel_g=_f(snap.accel_g), streaming=snap.streaming,
        light_level_v=_f(snap.light_v), bay_open=snap.bay_open, charging=bool(snap.charging),
        cell_voltage_v=_f(snap.voltage_v),
        attitude_trigger_enabled=bool(snap.attitude_trigger_enabled),
        freefall_trigger_enabled=bool(snap.freefall_trigger_enabled))
    return _header(msg, stamp, frame_id)


class StatusPacker(cdr.FramedPacker):
    """``~/status`` as serialized bytes, the same message as :func:`status_msg` makes.

    The status stream is the one message of every frame (20 Hz by default): the frame id is
    serialized once, each message is a struct pack (``uav_serial_common.cdr``).
    """

    def _layout(self, frame: bytes, offset: int) -> tuple:
        # online armed triggered tilt accel streaming light bay_open charging voltage att ff
        return frame, cdr.fields('???dd?d??d??', offset)[0].pack

    def pack(self, snap: Snapshot, sec: int, nanosec: int) -> bytes:
        """Return the serialized ``~/status`` of `snap`, stamped (sec, nanosec)."""
        frame, body = self._parts
        return b''.join((cdr.ENCAPSULATION, cdr.STAMP.pack(sec, nanosec), frame, body(
            snap.online, bool(snap.armed), bool(snap.triggered), _f(snap.tilt_deg),
            _f(snap.accel_g), snap.streaming, _f(snap.light_v), snap.bay_open,
            bool(snap.charging), _f(snap.voltage_v), bool(snap.attitude_trigger_enabled),
            bool(snap.freefall_trigger_enabled))))


def battery_msg(snap: Snapshot, stamp: Time, frame_id: str, location: str) -> BatteryState:
    """`~/battery`: the 0x34 voltage (P24, D9); NaN for what the module does not measure."""
    msg = _header(BatteryState(), stamp, frame_id)
    msg.voltage = _f(snap.voltage_v) if snap.online else NAN
    for name in ('temperature', 'current', 'charge', 'capacity', 'design_capacity',
                 'percentage'):
        setattr(msg, name, NAN)
    if not snap.online or snap.charging is None:
        msg.power_supply_status = BatteryState.POWER_SUPPLY_STATUS_UNKNOWN
    elif snap.charging:
        msg.power_supply_status = BatteryState.POWER_SUPPLY_STATUS_CHARGING
    else:
        msg.power_supply_status = BatteryState.POWER_SUPPLY_STATUS_DISCHARGING
    msg.power_supply_health = BatteryState.POWER_SUPPLY_HEALTH_UNKNOWN
    msg.power_supply_technology = BatteryState.POWER_SUPPLY_TECHNOLOGY_UNKNOWN
    msg.present = snap.online
    msg.cell_voltage = [msg.voltage]
    msg.cell_temperature = [NAN]
    msg.location = location
    return msg


def config_msg(snap: Snapshot, stamp: Optional[Time], frame_id: str,
               baud: int) -> ParachuteConfig:
    """`~/config`: the settings as last read back; `stamp` = when (None: never)."""
    def si(name: str) -> float:
        raw = snap.raw(name)
        return NAN if raw is None else float(SETTINGS[name].to_si(raw))
    msg = ParachuteConfig(
        valid=snap.settings_valid,
        attitude_threshold_deg=snap.attitude_threshold_raw or 0,
        freefall_threshold_g=si('freefall_threshold_g'), freefall_time_s=si('freefall_time_s'),
        light_threshold_v=si('light_threshold_v'),
        attitude_trigger_enabled=bool(snap.attitude_trigger_enabled),
        freefall_trigger_enabled=bool(snap.freefall_trigger_enabled),
        auto_triggers_known=(snap.attitude_trigger_enabled is not None
                             and snap.freefall_trigger_enabled is not None),
        boot_count=-1 if snap.boot_count is None else snap.boot_count, baud_rate=baud,
        settings_verified=not snap.mismatch, mismatch='; '.join(snap.mismatch))
    msg.header.frame_id = frame_id
    if stamp is not None:
        msg.header.stamp = stamp
    return msg


def record_msg(record: p.TriggerRecord) -> TriggerRecord:
    """Convert a decoded 16-byte trigger record to its message, SI units."""
    return TriggerRecord(
        boot_count=record.boot_count, uptime_s=float(record.uptime_s), source=record.source,
        source_name=source_name(record.source),
        attitude_threshold_deg=record.attitude_threshold_deg,
        freefall_threshold_g=float(record.freefall_threshold_g),
        freefall_time_s=float(record.freefall_time_s), serial_connected=record.serial_link,
        charging=record.charging, light_threshold_v=float(record.light_threshold_v),
        cell_voltage_v=float(record.cell_voltage_v), raw=list(record.raw))


def event_msg(event: Deployment, stamp: Time, frame_id: str) -> TriggerEvent:
    """`~/trigger_event` for one deployment."""
    msg = TriggerEvent(source=event.source, source_name=source_name(event.source),
                       via=VIA[event.via], record_known=event.record is not None,
                       deployment_id=event.deployment_id, amends=event.amends)
    if event.record is not None:
        msg.record = record_msg(event.record)
    return _header(msg, stamp, frame_id)


def request_msg(decision: RequestDecision, stamp: Time, frame_id: str) -> TriggerRequest:
    """`~/trigger_request` for one answered (or unanswered) request."""
    msg = TriggerRequest(decision=DECISIONS[decision.decision],
                         decision_name=decision.decision, policy=decision.policy,
                         reason=decision.reason, latency_ms=_f(decision.latency_ms))
    return _header(msg, stamp, frame_id)


def triggered_msg(triggered: bool) -> Bool:
    """`~/triggered`."""
    return Bool(data=triggered)
