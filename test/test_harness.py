"""The test harness itself: private ROS domain, rclpy context, processes, in-process drivers."""

import os
import sys
import threading

import pytest
from rcl_interfaces.srv import GetParameters
from std_msgs.msg import String

from uav_serial_common.process import executable_path, wait_for


def test_the_session_has_its_own_domain_and_localhost_discovery():
    domain = int(os.environ['ROS_DOMAIN_ID'])
    assert 20 <= domain <= 100
    assert os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'


def test_messages_flow_inside_the_test_context(ros):
    log = ros.subscribe(String, 'harness_check')
    pub = ros.publisher(String, 'harness_check')
    pub.publish(String(data='hello'))
    assert log.wait(lambda m: m.data == 'hello', timeout=5).data == 'hello'


def test_every_executable_is_installed():
    for name in ['parachute_node', 'servo_bus_node', 'handset_link_node', 'virtual_parachute',
                 'virtual_servo_bus', 'virtual_handset', 'blackbox_report',
                 'originman_board_node', 'virtual_originman_board']:
        assert os.access(executable_path(name), os.X_OK), name


def test_issue22_6_a_driver_in_the_test_process_is_its_own_participant_and_leaves_nothing(
        ros, driver, tmp_path):
    threads_before = set(threading.enumerate())
    interval_before = sys.getswitchinterval()
    node = driver.start('servo_bus_node', node_name='bus', namespace='/t', ros=ros,
                        parameters={'port': str(tmp_path / 'absent'), 'servo_ids': [4, 5],
                                    'telemetry_period_s': 0.5},
                        wait_service='/t/bus/get_parameters')
    assert node.alive() and node.context is not ros.context
    # main()'s GIL switch interval while it runs.
    assert sys.getswitchinterval() == pytest.approx(0.0005)
    # Its parameters, typed as a process gets them from the same YAML.
    reply = ros.call(GetParameters, '/t/bus/get_parameters',
                     GetParameters.Request(names=['servo_ids', 'telemetry_period_s']))
    assert list(reply.values[0].integer_array_value) == [4, 5]
    assert reply.values[1].double_value == 0.5
    # Its log lines, as its process prints them.
    line = wait_for(lambda: next((x for x in node.output().splitlines()
                                  if x.startswith('[ERROR]') and '[t.bus]: cannot open' in x),
                                 None), 10, what='the cannot-open log line')
    assert str(tmp_path / 'absent') in line
    driver.stop_all()
    assert not node.alive() and not node.context.ok()
    assert sys.getswitchinterval() == interval_before
    # Every thread it started has ended, and the test's own context still works.
    wait_for(lambda: not [t for t in threading.enumerate() if t not in threads_before], 10,
             what='the driver threads to end')
    assert ros.context.ok()
    test_messages_flow_inside_the_test_context(ros)
