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
from typing import Dict, List, Sequence, Tuple

from builtin_interfaces.msg import Time
from desheng_servo_ros import protocol as proto
from desheng_servo_ros.core import BusSnapshot, ServoSnapshot
from sensor_msgs.msg import JointState
from std_msgs.msg import Header
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

_ENCAPSULATION = b'\x00\x01\x00\x00'  # CDR, little endian, no options
_STAMP = struct.Struct('<iI')


class _Cdr:
    """CDR bytes being laid out.

    Alignment counts from the start of the data (after the 4-byte encapsulation). Constant
    parts become bytes; variable parts become a struct format.
    """

    def __init__(self, offset: int = 0) -> None:
        self.offset = offset
        self.data: List[bytes] = []
        self.fmt: List[str] = ['<']

    def _pad(self, size: int, in_format: bool) -> None:
        pad = -self.offset % size
        if pad:
            if in_format:
                self.fmt.append(f'{pad}x')
            else:
                self.data.append(bytes(pad))
            self.offset += pad

    def constant(self, fmt: str, *values: object) -> None:
        """Append constant values (one alignment, that of their first item)."""
        packed = struct.pack('<' + fmt, *values)
        self._pad(struct.calcsize('<' + fmt[0]), False)
        self.data.append(packed)
        self.offset += len(packed)

    def string(self, text: str) -> None:
        """Append a constant string: its length with the NUL, then its bytes."""
        raw = text.encode('utf-8') + b'\x00'
        self.constant('I', len(raw))
        self.data.append(raw)
        self.offset += len(raw)

    def variable(self, code: str, count: int = 1) -> None:
        """Append `count` values of struct type `code` to the format, aligned."""
        size = struct.calcsize('<' + code)
        self._pad(size, True)
        if count:
            self.fmt.append(f'{count}{code}')
        self.offset += size * count

    def constant_bytes(self) -> bytes:
        """Return the constant bytes laid out so far."""
        return b''.join(self.data)


def _header(frame_id: str) -> Tuple[bytes, int]:
    """Return the constant part of a Header after its stamp, and the offset after it."""
    cdr = _Cdr(offset=_STAMP.size)
    cdr.string(frame_id)
    return cdr.constant_bytes(), cdr.offset


class JointStatePacker:
    """``joint_states`` of a snapshot as serialized bytes (see the module docstring)."""

    def __init__(self, frame_id: str) -> None:
        self._layouts: Dict[Tuple[str, ...], Tuple[bytes, struct.Struct]] = {}
        self.set_frame_id(frame_id)

    def set_frame_id(self, frame_id: str) -> None:
        """Change ``header.frame_id``."""
        self.frame_id = frame_id
        self._header, self._offset = _header(frame_id)
        self._layouts = {}

    def _layout(self, names: Tuple[str, ...]) -> Tuple[bytes, struct.Struct]:
        cdr = _Cdr(self._offset)
        cdr.constant('I', len(names))
        for name in names:
            cdr.string(name)
        cdr.variable('I')  # position: count, values
        cdr.variable('d', len(names))
        cdr.variable('I')  # velocity
        cdr.variable('d', len(names))
        cdr.variable('I')  # effort: always empty
        layout = (self._header + cdr.constant_bytes(), struct.Struct(''.join(cdr.fmt)))
        self._layouts[names] = layout
        return layout

    def pack(self, snapshot: BusSnapshot, sec: int, nanosec: int) -> bytes:
        """Return the serialized ``JointState`` of every online servo (as `joint_state`)."""
        online: Sequence[ServoSnapshot] = [s for s in snapshot.servos if s.online]
        names = tuple(s.name for s in online)
        layout = self._layouts.get(names) or self._layout(names)
        n = len(online)
        return b''.join((_ENCAPSULATION, _STAMP.pack(sec, nanosec), layout[0], layout[1].pack(
            n, *[s.position_rad for s in online], n, *[s.velocity for s in online], 0)))


class ServoStatesPacker:
    """``~/servo_states`` of a snapshot as serialized bytes (see the module docstring)."""

    def __init__(self, frame_id: str) -> None:
        self._layouts: Dict[Tuple[Tuple[int, str], ...], Tuple[bytes, list]] = {}
        self.set_frame_id(frame_id)

    def set_frame_id(self, frame_id: str) -> None:
        """Change ``header.frame_id``."""
        self.frame_id = frame_id
        self._header, self._offset = _header(frame_id)
        self._layouts = {}

    def _layout(self, key: Tuple[Tuple[int, str], ...]) -> Tuple[bytes, list]:
        cdr = _Cdr(self._offset)
        cdr.constant('I', len(key))
        head = self._header + cdr.constant_bytes()
        parts = []
        for servo_id, name in key:
            # id and name are constant; the rest of ServoState is one struct of the values.
            cdr.data = []
            cdr.constant('B', servo_id)
            cdr.string(name)
            prefix = cdr.constant_bytes()
            cdr.fmt = ['<']
            for code in ('?', 'i', 'd', 'i', 'd', 'd', 'B', '?', '?', '?', '?', 'I'):
                cdr.variable(code)
            parts.append((prefix, struct.Struct(''.join(cdr.fmt)).pack))
        self._layouts[key] = (head, parts)
        return head, parts

    def pack(self, snapshot: BusSnapshot, sec: int, nanosec: int) -> bytes:
        """Return the serialized ``ServoStateArray`` of every servo (as `servo_state_array`)."""
        servos = snapshot.servos
        key = tuple((s.id, s.name) for s in servos)
        head, parts = self._layouts.get(key) or self._layout(key)
        out = [_ENCAPSULATION, _STAMP.pack(sec, nanosec), head]
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
