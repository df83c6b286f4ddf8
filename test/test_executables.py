"""One smoke test per executable (issue 22 item 6): start, namespace, a bad port, double Ctrl-C.

Each executable runs as a real process under ``/smoke``. A driver given a port that does not exist
stays up, says which port and what to check, has its ``~/`` interface under the namespace, and
ends cleanly (exit 0, no traceback) on two SIGINTs back to back, as ``ros2 launch`` sends them.
A virtual device given a link it cannot make says so in one line and exits 1; given a good one,
it runs in the namespace and ends cleanly the same way. The report tool refuses a missing file.
"""

import os
import signal
import socket
import subprocess

import pytest
from uav_serial_common.process import executable_path, wait_for, wait_scale

NS = '/smoke'
BAD_PORT = '/nonexistent/dir/tty'
NOISE = ('Traceback', 'never retrieved', 'InvalidHandle')

DRIVERS = {
    # executable: (its port parameter, a `~/` name of its interface, its node name)
    'parachute_node': ('port', 'deploy', 'parachute'),
    'servo_bus_node': ('port', 'emergency_stop', 'servo_bus'),
    'handset_link_node': ('port', 'link', 'handset_link'),
    'originman_board_node': ('port', 'stop_motors', 'originman_board'),
    'parachute_mavlink': ('mavlink_url', 'release_gate', 'parachute_mavlink'),
}

VIRTUAL = {
    # executable: (its link parameter, a `~/` service, its node name)
    'virtual_parachute': ('link', 'power_cycle', 'virtual_parachute'),
    'virtual_servo_bus': ('link', 'set_fault', 'virtual_servo_bus'),
    'virtual_handset': ('link', 'send_raw', 'virtual_handset'),
    'virtual_originman_board': ('link', 'press_key', 'virtual_originman_board'),
    'virtual_autopilot': ('mavlink_url', 'rearm', 'virtual_autopilot'),
}


def interface_names(ros):
    node = ros.node
    return {name for name, _ in node.get_service_names_and_types()} | \
        {name for name, _ in node.get_topic_names_and_types()}


def ctrl_c_twice(proc):
    """Send SIGINT twice, back to back; return the exit code."""
    for _ in range(2):
        try:
            os.kill(proc.pid, signal.SIGINT)
        except ProcessLookupError:
            break
    proc.popen.wait(30 * wait_scale())
    return proc.popen.returncode


def free_udp_port():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(('127.0.0.1', 0))
        return sock.getsockname()[1]


@pytest.mark.parametrize('executable', sorted(DRIVERS))
def test_a_driver_with_a_bad_port_stays_up_says_why_and_ends_on_ctrl_c_twice(
        executable, ros, launch, tmp_path):
    param, name, node = DRIVERS[executable]
    port = '/nonexistent/tty' if param == 'mavlink_url' else BAD_PORT
    proc = launch.start(executable, parameters={param: port, 'blackbox_dir': str(tmp_path)}
                        if executable == 'parachute_node' else {param: port},
                        namespace=NS, ros=ros)
    full = f'{NS}/{node}/{name}'
    wait_for(lambda: full in interface_names(ros), 20, interval=0.05,
             what=f'{full} under the namespace')

    def said():
        return [line for line in proc.output().splitlines() if port in line and
                ('[ERROR]' in line or '[WARN]' in line)]
    wait_for(said, 10, what='the bad port named in an error or warning')
    assert proc.alive(), proc.output()
    assert ctrl_c_twice(proc) == 0, proc.output()
    assert not any(word in proc.output() for word in NOISE), proc.output()


@pytest.mark.parametrize('executable', sorted(VIRTUAL))
def test_a_virtual_device_refuses_a_bad_link_and_runs_in_a_namespace(
        executable, ros, launch, tmp_path):
    param, name, node = VIRTUAL[executable]
    bad = '/nonexistent/tty' if param == 'mavlink_url' else BAD_PORT
    refused = subprocess.run([executable_path(executable), '--ros-args', '-p',
                              f'{param}:={bad}'], capture_output=True, text=True, timeout=60)
    assert refused.returncode == 1, refused.stdout + refused.stderr
    lines = refused.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('fatal: ') and bad in lines[0], lines
    good = f'udpin:127.0.0.1:{free_udp_port()}' if param == 'mavlink_url' else \
        str(tmp_path / 'device')
    full = f'{NS}/{node}/{name}'
    proc = launch.start(executable, parameters={param: good}, namespace=NS, ros=ros,
                        wait_service=full)
    assert ctrl_c_twice(proc) == 0, proc.output()
    assert not any(word in proc.output() for word in NOISE), proc.output()
    if param == 'link':
        assert not os.path.lexists(good), 'the link to the pty was left behind'


def test_the_report_tool_refuses_a_missing_file_in_one_line(tmp_path):
    missing = str(tmp_path / 'none.jsonl')
    result = subprocess.run([executable_path('blackbox_report'), missing], capture_output=True,
                            text=True, timeout=120)
    assert result.returncode != 0
    assert 'Traceback' not in result.stderr
    assert missing in result.stderr and len(result.stderr.strip().splitlines()) == 1
