"""The servo bus's snapshots as ROS messages (pure functions, no node needed)."""

from __future__ import annotations

from builtin_interfaces.msg import Time
from desheng_servo_ros import protocol as proto
from desheng_servo_ros.core import BusSnapshot
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
