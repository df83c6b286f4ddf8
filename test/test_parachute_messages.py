"""The parachute's message builders: the serialized ``~/status`` is the status message."""

import math

from builtin_interfaces.msg import Time
from dps_parachute_ros import messages as m
from dps_parachute_ros.state import Snapshot
import pytest
from rclpy.serialization import deserialize_message
from uav_serial_drivers.msg import ParachuteStatus

STAMP = Time(sec=1700000000, nanosec=123456789)
FIELDS = ('online', 'armed', 'triggered', 'tilt_deg', 'accel_g', 'streaming', 'light_level_v',
          'bay_open', 'charging', 'cell_voltage_v', 'attitude_trigger_enabled',
          'freefall_trigger_enabled')


def same(a: ParachuteStatus, b: ParachuteStatus) -> bool:
    """Field by field, NaN equal to NaN (what the driver publishes before a value is read)."""
    def eq(x, y):
        return (math.isnan(x) and math.isnan(y)) if isinstance(x, float) and x != x else x == y
    return a.header == b.header and all(eq(getattr(a, f), getattr(b, f)) for f in FIELDS)


SNAPSHOTS = [
    Snapshot(),  # nothing read yet: NaN and false
    Snapshot(port_open=True, online=True, armed=True, triggered=False, tilt_deg=12.0,
             accel_g=0.9, streaming=True, light_v=3.2, charging=True, voltage_v=4.1,
             attitude_trigger_enabled=True, freefall_trigger_enabled=False,
             light_threshold_raw=20),  # bay open: 3.2 V > 2.0 V
    Snapshot(online=False, armed=None, triggered=True, tilt_deg=-89.0, accel_g=0.0,
             light_v=0.5, light_threshold_raw=20, voltage_v=3.3, charging=False,
             attitude_trigger_enabled=False, freefall_trigger_enabled=True),
]


@pytest.mark.parametrize('frame_id', ['', 'a', 'parachute', 'abcdefg', 'chute_link_01', 'ñandú'])
@pytest.mark.parametrize('snap', SNAPSHOTS)
def test_the_packed_status_is_the_status_message(frame_id, snap):
    packer = m.StatusPacker('other')
    packer.set_frame_id(frame_id)
    got = deserialize_message(packer.pack(snap, STAMP.sec, STAMP.nanosec), ParachuteStatus)
    want = m.status_msg(snap, STAMP, frame_id)
    assert same(got, want), f'{got} != {want}'
    assert got.bay_open == snap.bay_open
