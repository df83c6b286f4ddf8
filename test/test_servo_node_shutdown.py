"""servo_bus_node start and end: torque on at start, torque off as the last frame on Ctrl-C."""

import os
import signal
import subprocess
import time

from desheng_servo_ros import protocol as proto
import pytest
from servo_rig import start_rig, stop_rig
from uav_serial_common.process import executable_path, wait_for

TORQUE_OFF_TO_ALL = proto.encode_write(254, 0x28, b'\x00')


@pytest.fixture
def rig(tmp_path, request):
    """The node started with torque_on_start, once every servo holds and joints are published."""
    rig = start_rig(tmp_path, request.node.name[:40], parameters={'torque_on_start': True})
    try:
        wait_for(lambda: torque(rig) == [True] * 3, 10, what='torque on at start')
        rig.joints.wait(lambda m: len(m.name) == 3, 5)
        yield rig
    finally:
        stop_rig(rig)


def last_frame(rig):
    """Return the last frame the bus got from the node, once its torque off is in.

    The node has ended; the virtual bus's thread, on a loaded host, may not have read its last
    bytes yet (campaign s15b, run 6: the READ before the torque off seen as the last frame).
    """
    wait_for(lambda: any(r.raw == TORQUE_OFF_TO_ALL for r in rig.wire.requests()), 5,
             what='the torque off at the bus')
    return rig.wire.requests()[-1].raw


def torque(rig):
    with rig.locked():
        return [rig.sim_servo(i).torque_enabled for i in (1, 2, 3)]


def test_sigint_broadcasts_torque_off_as_the_last_frame(rig):
    assert rig.node.stop(signal.SIGINT, timeout=10) == 0
    assert last_frame(rig) == TORQUE_OFF_TO_ALL
    wait_for(lambda: torque(rig) == [False] * 3, 5, what='every servo let go')


def ctrl_c_twice(rig):
    """Press Ctrl-C under ``ros2 launch`` (two SIGINTs); return the node's output once it ended
    cleanly (exit 0, no traceback)."""
    os.kill(rig.node.pid, signal.SIGINT)
    time.sleep(0.002)  # the terminal's SIGINT, then launch's: a few ms apart
    os.kill(rig.node.pid, signal.SIGINT)
    assert rig.node.stop(signal.SIGINT, timeout=10) == 0
    output = rig.node.output()
    assert 'KeyboardInterrupt' not in output and 'Traceback' not in output, output
    return output


def test_safety_10_ctrl_c_twice_still_sends_the_final_torque_off(rig):
    """``ros2 launch`` delivers Ctrl-C twice; the second must not cut the shutdown short."""
    ctrl_c_twice(rig)
    assert last_frame(rig) == TORQUE_OFF_TO_ALL
    wait_for(lambda: torque(rig) == [False] * 3, 5, what='every servo let go')


def test_safety_10_ctrl_c_twice_while_unplugged_ends_and_says_the_torque_stays_on(rig):
    rig.dev.runner.unplug()
    rig.state(1, start=len(rig.states), pred=lambda s: not s.online, what='the bus offline')
    mark = rig.wire.mark()
    output = ctrl_c_twice(rig)
    # Nothing could reach the servos, and the log says what that leaves: torque still on.
    assert 'torque off on shutdown NOT sent' in output and 'still hold it' in output, output
    rig.dev.runner.replug()
    assert rig.wire.requests(mark) == [] and torque(rig) == [True] * 3


def test_mismatched_joint_names_are_a_clear_startup_error():
    result = subprocess.run(
        [executable_path('servo_bus_node'), '--ros-args', '-p', 'port:=/nonexistent/servo',
         '-p', 'servo_ids:=[1, 2]', '-p', 'joint_names:=[pan]'],
        capture_output=True, text=True, timeout=30)
    assert result.returncode != 0
    assert 'joint_names has 1 names but servo_ids has 2 ids' in result.stderr
