"""servo_bus_node start and end: torque on at start, torque off as the last frame on Ctrl-C."""

import os
import signal
import subprocess
import time

from desheng_servo_ros import protocol as proto
from uav_serial_common.process import executable_path, wait_for
from servo_rig import start_rig, stop_rig


def test_sigint_broadcasts_torque_off_as_the_last_frame(tmp_path):
    rig = start_rig(tmp_path, 'servo_shutdown', parameters={'torque_on_start': True})
    try:
        def all_torque():
            with rig.locked():
                return all(rig.sim_servo(i).torque_enabled for i in (1, 2, 3))
        wait_for(all_torque, 10, what='torque on at start')
        rig.joints.wait(lambda m: len(m.name) == 3, 5)
        assert rig.node.stop(signal.SIGINT, timeout=10) == 0
        sent = rig.wire.requests()
        assert sent[-1].raw == proto.encode_write(254, 0x28, b'\x00')
        with rig.locked():
            assert not any(rig.sim_servo(i).torque_enabled for i in (1, 2, 3))
    finally:
        stop_rig(rig)


def test_safety_10_ctrl_c_twice_still_sends_the_final_torque_off(tmp_path):
    """``ros2 launch`` delivers Ctrl-C twice; the second must not cut the shutdown short."""
    rig = start_rig(tmp_path, 'servo_double_sigint', parameters={'torque_on_start': True})
    try:
        def all_torque():
            with rig.locked():
                return all(rig.sim_servo(i).torque_enabled for i in (1, 2, 3))
        wait_for(all_torque, 10, what='torque on at start')
        rig.joints.wait(lambda m: len(m.name) == 3, 5)
        os.kill(rig.node.pid, signal.SIGINT)
        time.sleep(0.002)  # the terminal's SIGINT, then launch's: a few ms apart
        os.kill(rig.node.pid, signal.SIGINT)
        assert rig.node.stop(signal.SIGINT, timeout=10) == 0
        output = rig.node.output()
        assert 'KeyboardInterrupt' not in output and 'Traceback' not in output, output
        assert rig.wire.requests()[-1].raw == proto.encode_write(254, 0x28, b'\x00')
        with rig.locked():
            assert not any(rig.sim_servo(i).torque_enabled for i in (1, 2, 3))
    finally:
        stop_rig(rig)


def test_mismatched_joint_names_are_a_clear_startup_error():
    result = subprocess.run(
        [executable_path('servo_bus_node'), '--ros-args', '-p', 'port:=/nonexistent/servo',
         '-p', 'servo_ids:=[1, 2]', '-p', 'joint_names:=[pan]'],
        capture_output=True, text=True, timeout=30)
    assert result.returncode != 0
    assert 'joint_names has 1 names but servo_ids has 2 ids' in result.stderr
