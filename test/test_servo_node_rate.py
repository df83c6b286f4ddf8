"""servo_bus_node when the bus cannot carry publish_rate_hz: it says so once and keeps going."""

from desheng_servo_ros import protocol as proto
from uav_serial_common.process import wait_for
from servo_rig import start_rig, stop_rig
from std_srvs.srv import Trigger
from uav_serial_drivers.srv import ReadRegister


def test_an_impossible_rate_is_logged_once_and_every_servo_keeps_being_published(tmp_path):
    # Three position READs take ~4.7 ms at 115200 baud: 1000 Hz cannot be carried.
    rig = start_rig(tmp_path, 'servo_rate', parameters={'publish_rate_hz': 1000.0})
    try:
        start = len(rig.joints)
        rig.joints.wait(lambda m: len(m.name) == 3, 5, start=start)
        # It is judged over a second of cycles; then keep reading for a while: the warning must
        # not repeat, and no servo may drop out.
        wait_for(lambda: 'the bus cannot keep up' in rig.node.output(), 10,
                 what='the warning that the bus cannot keep up')
        start = len(rig.joints)
        wait_for(lambda: len(rig.joints) >= start + 400, 20, what='400 more joint_states')
        recent = rig.joints.messages[start:]
        assert all(list(m.name) == ['servo_1', 'servo_2', 'servo_3'] for m in recent[-100:])
        log = rig.node.output()
        assert log.count('the bus cannot keep up with publish_rate_hz 1000') == 1, log
        # The READs now run back to back, cycle after cycle: a service and the emergency stop
        # still get the bus between two of them.
        resp = rig.call(ReadRegister, 'read_register', id=2, register_name='firmware_version')
        assert resp.success, resp.message
        mark = rig.wire.mark()
        assert rig.call(Trigger, 'emergency_stop').success
        wait_for(lambda: rig.wire.commands(mark), 5, what='the emergency stop on the wire')
        assert [r.raw for r in rig.wire.commands(mark)] == [
            proto.encode_write(254, 0x28, b'\x00')]
        after = len(rig.joints)
        wait_for(lambda: len(rig.joints) >= after + 50, 10,
                 what='the read loop going on after the emergency stop')
    finally:
        stop_rig(rig)
