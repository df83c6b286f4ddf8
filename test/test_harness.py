"""The test harness itself: private ROS domain, rclpy context, processes, in-process drivers."""

import os
import subprocess
import sys
import threading
import time

import pytest
from rcl_interfaces.srv import GetParameters
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
from std_srvs.srv import Trigger

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


RESPONSE_WAIT_SERVER = r"""
import sys
import time

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger

rclpy.init()
node = Node('response_wait_server')
# Best effort: its response writer never matches a reliable caller's response reader.
service = node.create_service(Trigger, sys.argv[1], lambda request, response: response,
                              qos_profile=QoSProfile(
                                  depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
send = service.send_response


def timed_send(response, header):
    print('sending', flush=True)
    start = time.monotonic()
    send(response, header)
    print(f'gave up after {time.monotonic() - start:.3f} s', flush=True)


service.send_response = timed_send
executor = SingleThreadedExecutor()
executor.add_node(node)
executor.spin()
"""


def test_issue22_6_a_service_waits_for_its_callers_response_reader_instead_of_dropping(ros):
    # A server answers before it has discovered the caller's response reader when the caller
    # was made just before the call (a node process started a moment before, a loaded host):
    # rmw_fastrtps waits 100 ms for the reader, then drops the answer, and the caller waits in
    # vain (a MAVLink test's call, 60 s). Here the reader is never matched (incompatible QoS),
    # so the server's wait shows: in the session's processes it still waits long after 100 ms.
    name = f'/response_wait_{os.getpid()}'
    server = subprocess.Popen([sys.executable, '-c', RESPONSE_WAIT_SERVER, name],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = []
    threading.Thread(target=lambda: lines.extend(server.stdout), daemon=True).start()
    try:
        ros.wait_for_service(name)
        client = ros.node.create_client(
            Trigger, name, callback_group=ros.group,
            qos_profile=QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))

        def request_arrived():
            # Sent again until one arrives (the server takes the first and blocks): this client
            # is never ready (its response reader never matches), and a request sent before its
            # writer matched the server's reader goes nowhere.
            client.call_async(Trigger.Request())
            return 'sending\n' in lines
        wait_for(request_arrived, 15, interval=0.2, what='a request at the server')
        # 20 times rmw_fastrtps's default wait (the session's is 10 s).
        time.sleep(2.0)
        assert not any(line.startswith('gave up') for line in lines), lines
    finally:
        server.kill()
        server.wait(10)
