"""The servo bus's snapshots as ROS messages (pure functions and packers, no node needed).

`joint_state` and `servo_state_array` build the message objects. The node publishes the same
messages as serialized bytes (CDR, little endian) from `JointStatePacker` and
`ServoStatesPacker`: they are published after every read cycle, and building a
``ServoStateArray`` of 12 ``ServoState`` objects and converting it for the middleware cost more
than everything else the driver does per cycle (``bench/README.md``, ``cpu_servo_pct``). Names,
ids and the frame are constant, so each message is a few ``struct`` packs of the values joined
to precomputed bytes; rclpy publishes ``bytes`` as a serialized message.
``test/test_servo_messages.py`` deserializes them and compares with the builders.
"""

from __future__ import annotations

import struct
from typing import Callable, Sequence, Tuple

from builtin_interfaces.msg import Time
from desheng_servo_ros import protocol as proto
from desheng_servo_ros.core import BusSnapshot, ServoSnapshot
from sensor_msgs.msg import JointState
from std_msgs.msg import Header
from uav_serial_common import cdr
from uav_serial_drivers.msg import ServoState, ServoStateArray


def joint_state(snapshot: BusSnapshot, stamp: Time, frame_id: str) -> JointState:
    """Return positions [rad] and velocities [rad/s] of every online servo (REP-103)."""
    online = [s for s in snapshot.servos if s.online]
    return JointState(header=Header(stamp=stamp, frame_id=frame_id),
                      name=[s.name for s in online],
                      position=[s.position_rad for s in online],
                      velocity=[s.velocity for s in online])


def servo_state_array(snapshot: BusSnapshot, stamp: Time, frame_id: str) -> ServoStateArray:
    """Return every configured servo's state, online or not."""
    return ServoStateArray(header=Header(stamp=stamp, frame_id=frame_id), servos=[
        ServoState(id=s.id, name=s.name, online=s.online, position_ticks=s.position_ticks,
                   position_rad=s.position_rad, speed_raw=s.speed_raw,
                   current_ma=s.current_ma, temperature_c=s.temperature_c, status=s.status,
                   overload=bool(s.status & proto.STATUS_OVERLOAD),
                   over_temperature=bool(s.status & proto.STATUS_OVER_TEMPERATURE),
                   voltage_fault=bool(s.status & proto.STATUS_VOLTAGE_FAULT),
                   torque_enabled=s.torque_enabled, error_count=s.error_count)
        for s in snapshot.servos])


# -- serialized messages ----------------------------------------------------------------------

_SERVO_FIELDS = '?ididdB????I'
"""ServoState after id and name: online .. error_count, as ``struct`` codes."""


class JointStatePacker(cdr.FramedPacker):
    """``joint_states`` of a snapshot as serialized bytes (see the module docstring)."""

    def _layout(self, frame: bytes, offset: int) -> tuple:
        return frame, offset, {}  # and the layout of each list of names, made when first met

    def _names_layout(self, names: Tuple[str, ...]) -> Tuple[bytes, Callable[..., bytes]]:
        frame, offset, layouts = self._parts
        listed, offset = cdr.string_sequence(names, offset)
        n = len(names)
        # position and velocity (count, values), effort (always empty)
        values = cdr.fields('I' + 'd' * n + 'I' + 'd' * n + 'I', offset)[0]
        layout = layouts[names] = (frame + listed, values.pack)
        return layout

    def pack(self, snapshot: BusSnapshot, sec: int, nanosec: int) -> bytes:
        """Return the serialized ``JointState`` of every online servo (as `joint_state`)."""
        online: Sequence[ServoSnapshot] = [s for s in snapshot.servos if s.online]
        names = tuple(s.name for s in online)
        head, pack = self._parts[2].get(names) or self._names_layout(names)
        n = len(online)
        return b''.join((cdr.ENCAPSULATION, cdr.STAMP.pack(sec, nanosec), head, pack(
            n, *[s.position_rad for s in online], n, *[s.velocity for s in online], 0)))


class ServoStatesPacker(cdr.FramedPacker):
    """``~/servo_states`` of a snapshot as serialized bytes (see the module docstring)."""

    def _layout(self, frame: bytes, offset: int) -> tuple:
        return frame, offset, {}  # and the layout of each list of servos, made when first met

    def _servos_layout(self, key: Tuple[Tuple[int, str], ...]) -> Tuple[bytes, list]:
        frame, offset, layouts = self._parts
        pad = bytes(-offset % 4)
        head = frame + pad + struct.pack('<I', len(key))
        offset += len(pad) + 4
        parts = []
        for servo_id, name in key:
            # id and name are constant; the rest of a ServoState is one struct of the values.
            named, offset = cdr.string(name, offset + 1)
            values, offset = cdr.fields(_SERVO_FIELDS, offset)
            parts.append((bytes((servo_id,)) + named, values.pack))
        layouts[key] = (head, parts)
        return head, parts

    def pack(self, snapshot: BusSnapshot, sec: int, nanosec: int) -> bytes:
        """Return the serialized ``ServoStateArray`` of every servo (as `servo_state_array`)."""
        servos = snapshot.servos
        key = tuple((s.id, s.name) for s in servos)
        head, parts = self._parts[2].get(key) or self._servos_layout(key)
        out = [cdr.ENCAPSULATION, cdr.STAMP.pack(sec, nanosec), head]
        overload, heat, voltage = (proto.STATUS_OVERLOAD, proto.STATUS_OVER_TEMPERATURE,
                                   proto.STATUS_VOLTAGE_FAULT)
        for s, (prefix, pack) in zip(servos, parts):
            status = s.status
            out.append(prefix)
            out.append(pack(s.online, s.position_ticks, s.position_rad, s.speed_raw,
                            s.current_ma, s.temperature_c, status, bool(status & overload),
                            bool(status & heat), bool(status & voltage), s.torque_enabled,
                            s.error_count))
        return b''.join(out)
