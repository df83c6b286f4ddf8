"""The handset core's snapshots as ROS messages: pure builders, no node, no clock read.

Stamps: the core stamps with its monotonic clock (the arrival of a frame's last byte, H16);
``ros_stamp`` moves such a time onto the ROS clock given one reading of both clocks, so a
setpoint's header says when its frame arrived, not when it was published.
"""

from __future__ import annotations

import math
from typing import Dict, Tuple

from builtin_interfaces.msg import Time
from std_msgs.msg import Header
from uav_serial_drivers.msg import Failsafe, HandsetAuxiliary, HandsetLink, HandsetSetpoint

from handset_link_ros import core
from uav_serial_common import cdr

_NS = 1_000_000_000


def ros_stamp(stamp: float, now_mono: float, now_ros_ns: int) -> Time:
    """Return the ROS time of monotonic time `stamp`, given both clocks read at one moment.

    A NaN `stamp` (nothing to date) is "now".
    """
    age_ns = 0 if math.isnan(stamp) else round((now_mono - stamp) * _NS)
    ns = max(0, now_ros_ns - age_ns)
    return Time(sec=ns // _NS, nanosec=ns % _NS)


def setpoint_msg(sp: core.Setpoint, frame_id: str, stamp: Time) -> HandsetSetpoint:
    """Return ``~/setpoint``: the four sticks (NaN until received) and what this one updates."""
    return HandsetSetpoint(
        header=Header(stamp=stamp, frame_id=frame_id),
        yaw_deg=float(sp.yaw_deg), pitch_deg=float(sp.pitch_deg), roll_deg=float(sp.roll_deg),
        altitude_m=float(sp.altitude_m), updated=list(sp.updated))


class SetpointPacker(cdr.FramedPacker):
    """``~/setpoint`` as serialized bytes, the same message as :func:`setpoint_msg` makes.

    One setpoint goes out per stick frame (~200/s at the handset's 50 Hz): the frame id is
    serialized once, and the ``updated`` list once per combination of names
    (``uav_serial_common.cdr``); a message is a struct pack and a join.
    """

    def _layout(self, frame: bytes, offset: int) -> tuple:
        sticks, offset = cdr.fields('dddd', offset)
        tails: Dict[Tuple[str, ...], bytes] = {}
        return frame, sticks.pack, tails, offset

    def pack(self, sp: core.Setpoint, sec: int, nanosec: int) -> bytes:
        """Return the serialized ``~/setpoint`` of `sp`, stamped (sec, nanosec)."""
        frame, sticks, tails, offset = self._parts
        tail = tails.get(sp.updated)
        if tail is None:
            tail = tails[sp.updated] = cdr.string_sequence(sp.updated, offset)[0]
        return b''.join((cdr.ENCAPSULATION, cdr.STAMP.pack(sec, nanosec), frame,
                         sticks(sp.yaw_deg, sp.pitch_deg, sp.roll_deg, sp.altitude_m), tail))


def ros_time_ns(stamp: float, now_mono: float, now_ros_ns: int) -> Tuple[int, int]:
    """`ros_stamp` as (sec, nanosec)."""
    age_ns = 0 if math.isnan(stamp) else round((now_mono - stamp) * _NS)
    return divmod(max(0, now_ros_ns - age_ns), _NS)


def auxiliary_msg(aux: core.Auxiliary, frame_id: str, stamp: Time) -> HandsetAuxiliary:
    """Return ``~/auxiliary``: lights (-1 until received), camera angle (NaN), recording."""
    return HandsetAuxiliary(
        header=Header(stamp=stamp, frame_id=frame_id),
        lights_percent=int(aux.lights_percent), camera_angle_deg=float(aux.camera_angle_deg),
        camera_recording=bool(aux.camera_recording),
        camera_recording_known=bool(aux.camera_recording_known), updated=list(aux.updated))


def link_msg(state: core.LinkState, frame_id: str, stamp: Time) -> HandsetLink:
    """Return ``~/link``: connected, port open, measured rates, counters, age of the last frame."""
    return HandsetLink(
        header=Header(stamp=stamp, frame_id=frame_id),
        connected=bool(state.connected), port_open=bool(state.port_open),
        frame_rate_hz=float(state.frame_rate_hz), command_rate_hz=float(state.command_rate_hz),
        frames_accepted=state.frames_accepted, frames_malformed=state.frames_malformed,
        frames_out_of_range=state.frames_out_of_range,
        frames_unknown_type=state.frames_unknown_type,
        frames_rejected_recently=state.frames_rejected_recently,
        last_frame_age_s=float(state.last_frame_age_s))


def failsafe_msg(state: core.Failsafe, frame_id: str, stamp: Time) -> Failsafe:
    """Return ``~/failsafe``: the conditions, the requested action and why."""
    return Failsafe(
        header=Header(stamp=stamp, frame_id=frame_id),
        link_lost=bool(state.link_lost), battery_low=bool(state.battery_low),
        action=state.action, reason=state.reason,
        battery_fraction=float(state.battery_fraction))
