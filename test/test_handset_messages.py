"""The handset's message builders: the serialized ``~/setpoint`` is the setpoint message."""

import math

from builtin_interfaces.msg import Time
from handset_link_ros import messages
from handset_link_ros.core import Setpoint
import pytest
from rclpy.serialization import deserialize_message
from uav_serial_drivers.msg import HandsetSetpoint

STAMP = Time(sec=1700000000, nanosec=987654321)
NAN = math.nan


def same(a: HandsetSetpoint, b: HandsetSetpoint) -> bool:
    """Field by field, NaN equal to NaN (a stick not received yet)."""
    def eq(x, y):
        return (math.isnan(x) and math.isnan(y)) if x != x else x == y
    sticks = ('yaw_deg', 'pitch_deg', 'roll_deg', 'altitude_m')
    return a.header == b.header and list(a.updated) == list(b.updated) and all(
        eq(getattr(a, f), getattr(b, f)) for f in sticks)


SETPOINTS = [
    Setpoint(),
    Setpoint(yaw_deg=-179.9, updated=('yaw_deg',)),
    Setpoint(12.5, -90.0, 90.0, 1000.0, ('pitch_deg', 'roll_deg')),
    Setpoint(1.0, 2.0, 3.0, -100.0, ('yaw_deg', 'pitch_deg', 'roll_deg', 'altitude_m')),
    Setpoint(NAN, NAN, NAN, 0.25, ('altitude_m',)),
]


@pytest.mark.parametrize('frame_id', ['', 'a', 'handset', 'abcdefg', 'handset_link_1', 'ñandú'])
@pytest.mark.parametrize('sp', SETPOINTS)
def test_the_packed_setpoint_is_the_setpoint_message(frame_id, sp):
    packer = messages.SetpointPacker('other')
    packer.set_frame_id(frame_id)
    for _ in range(2):  # the second time from the cached list of names
        got = deserialize_message(packer.pack(sp, STAMP.sec, STAMP.nanosec), HandsetSetpoint)
        want = messages.setpoint_msg(sp, frame_id, STAMP)
        assert same(got, want), f'{got} != {want}'


def test_the_stamp_is_the_frames_arrival_on_the_ros_clock():
    # A frame that arrived 2.5 ms before the clocks were read is stamped 2.5 ms earlier.
    now_ns = 1_700_000_000_000_000_000
    sec, nanosec = messages.ros_time_ns(10.0, 10.0025, now_ns)
    assert sec * 1_000_000_000 + nanosec == now_ns - 2_500_000
    assert Time(sec=sec, nanosec=nanosec) == messages.ros_stamp(10.0, 10.0025, now_ns)
    assert messages.ros_time_ns(NAN, 10.0, now_ns) == divmod(now_ns, 1_000_000_000)
