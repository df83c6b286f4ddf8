"""The servo bus's message builders: snapshots in, ROS messages out (no node, no rclpy.init)."""

import math

from builtin_interfaces.msg import Time
from desheng_servo_ros.core import BusSnapshot, ServoSnapshot
from desheng_servo_ros.messages import (joint_state, JointStatePacker, servo_state_array,
                                        ServoStatesPacker)
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState
from uav_serial_drivers.msg import ServoStateArray


def servo(servo_id, name, online, ticks, status=0):
    rad = (ticks - 2048) * 2 * math.pi / 4096
    return ServoSnapshot(id=servo_id, name=name, online=online, seen=True, position_ticks=ticks,
                         position_rad=rad, speed_raw=100, velocity=-0.15, current_ma=40.0,
                         temperature_c=31.0, status=status, torque_enabled=True,
                         error_count=2, duplicate=False)


SNAPSHOT = BusSnapshot(True, (servo(1, 'pan', True, 3072), servo(2, 'tilt', False, 2048, 0x25)))


def test_joint_state_lists_online_servos_in_rad():
    msg = joint_state(SNAPSHOT, Time(sec=5), 'bus')
    assert msg.header.frame_id == 'bus' and msg.header.stamp.sec == 5
    assert list(msg.name) == ['pan']
    assert list(msg.position) == [math.pi / 2] and list(msg.velocity) == [-0.15]


def test_servo_states_list_every_servo_with_its_status_bits():
    msg = servo_state_array(SNAPSHOT, Time(sec=5), 'bus')
    assert [s.name for s in msg.servos] == ['pan', 'tilt']
    tilt = msg.servos[1]
    assert not tilt.online and tilt.status == 0x25
    assert tilt.overload and tilt.over_temperature and tilt.voltage_fault
    pan = msg.servos[0]
    assert pan.position_ticks == 3072 and pan.current_ma == 40.0 and pan.error_count == 2
    assert not (pan.overload or pan.over_temperature or pan.voltage_fault)


def test_the_packed_messages_are_the_messages_serialized():
    # What the node publishes (bytes) deserializes to what the builders make, for names and
    # frame ids of every length (CDR alignment), NaN telemetry and servos offline.
    servos = tuple(
        ServoSnapshot(id=k, name='j' * k, online=k % 3 != 0, seen=True, position_ticks=2000 + k,
                      position_rad=0.01 * k, speed_raw=k, velocity=-0.1 * k,
                      current_ma=math.nan if k == 2 else 10.0 * k, temperature_c=30.0 + k,
                      status=0x25 if k == 4 else 0, torque_enabled=k % 2 == 0, error_count=k,
                      duplicate=False)
        for k in range(1, 10))
    snapshot = BusSnapshot(True, servos, 1.0)
    for frame_id in ('', 'b', 'servo_bus', 'frame_8_'):
        joints, states = JointStatePacker('x'), ServoStatesPacker('x')
        joints.set_frame_id(frame_id)
        states.set_frame_id(frame_id)
        stamp = Time(sec=1795000000, nanosec=123456789)
        got = deserialize_message(joints.pack(snapshot, stamp.sec, stamp.nanosec), JointState)
        assert got == joint_state(snapshot, stamp, frame_id)
        got = deserialize_message(states.pack(snapshot, stamp.sec, stamp.nanosec),
                                  ServoStateArray)
        # NaN is not equal to itself: compare the printed messages.
        assert repr(got) == repr(servo_state_array(snapshot, stamp, frame_id))
    # No servo online: an empty joint_states.
    offline = BusSnapshot(True, tuple(s._replace(online=False) for s in servos))
    got = deserialize_message(JointStatePacker('b').pack(offline, 1, 2), JointState)
    assert list(got.name) == [] and list(got.position) == []
