"""The servo bus's message builders: snapshots in, ROS messages out (no node, no rclpy.init)."""

import math

from builtin_interfaces.msg import Time
from desheng_servo_ros.core import BusSnapshot, ServoSnapshot
from desheng_servo_ros.messages import joint_state, servo_state_array


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
