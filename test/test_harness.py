"""The test harness itself: private ROS domain, in-process rclpy context, process launcher."""

import os

from std_msgs.msg import String

from uav_serial_common.process import executable_path


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
