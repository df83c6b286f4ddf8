"""servo_bus_node when the bus cannot carry publish_rate_hz: it says so once and keeps going."""

from ros_harness import wait_for
from servo_rig import start_rig, stop_rig


def test_an_impossible_rate_is_logged_once_and_every_servo_keeps_being_published(tmp_path):
    # Three position READs take ~4.7 ms at 115200 baud: 1000 Hz cannot be carried.
    rig = start_rig(tmp_path, 'servo_rate', parameters={'publish_rate_hz': 1000.0})
    try:
        start = len(rig.joints)
        rig.joints.wait(lambda m: len(m.name) == 3, 5, start=start)
        # Keep reading for a while: the warning must not repeat, and no servo may drop out.
        wait_for(lambda: len(rig.joints) >= start + 200, 20, what='200 more joint_states')
        recent = rig.joints.messages[start:]
        assert all(list(m.name) == ['servo_1', 'servo_2', 'servo_3'] for m in recent[-100:])
        log = rig.node.output()
        assert log.count('the bus cannot keep up with publish_rate_hz 1000') == 1, log
    finally:
        stop_rig(rig)
