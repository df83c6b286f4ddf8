"""The virtual-device node base: the cable, wire faults and noise of every virtual device."""

import importlib
import time

import pytest
from rclpy.parameter import Parameter
import serial
from std_srvs.srv import SetBool, Trigger

from uav_serial_common.process import wait_for, wait_scale

# (module, node class, node name, whether the device replies, its extra next-reply services)
VIRTUAL_NODES = [
    ('dps_parachute_ros.virtual_node', 'VirtualParachuteNode', 'virtual_parachute', True, True),
    ('desheng_servo_ros.virtual_node', 'VirtualServoBusNode', 'virtual_servo_bus', True, False),
    ('handset_link_ros.virtual_node', 'VirtualHandsetNode', 'virtual_handset', False, False),
    ('originman_board_ros.virtual_node', 'VirtualOriginManBoardNode', 'virtual_originman_board',
     True, False),
]


def _read_until(port, wanted: bytes, timeout: float) -> bytes:
    seen = b''
    deadline = time.monotonic() + timeout * wait_scale()
    while wanted not in seen and time.monotonic() < deadline:
        seen += port.read(4096)
    return seen


@pytest.mark.parametrize('module, cls, name, replies, next_reply', VIRTUAL_NODES,
                         ids=[case[2] for case in VIRTUAL_NODES])
def test_issue22_5_every_virtual_device_has_the_shared_cable_wire_faults_and_noise(
        ros, tmp_path, module, cls, name, replies, next_reply):
    from uav_serial_common.virtual_node import VirtualDeviceNode, WIRE_FAULTS
    node_class = getattr(importlib.import_module(module), cls)
    assert issubclass(node_class, VirtualDeviceNode)
    link = tmp_path / 'link'
    node = node_class(context=ros.context,
                      parameter_overrides=[Parameter('link', value=str(link))])
    ros.executor.add_node(node)
    port = None
    try:
        runner = node.wire_runner
        assert runner is not None and runner.path == str(link)
        # The wire faults are parameters, checked, and applied to the runner at runtime.
        names = [n for n in WIRE_FAULTS if replies or n != 'reply_delay_s']
        assert node.has_parameter('reply_delay_s') == replies
        results = node.set_parameters([Parameter(n, value=0.25) for n in names])
        assert all(r.successful for r in results), [r.reason for r in results]
        assert all(getattr(runner.faults, n) == 0.25 for n in names)
        for bad in (float('nan'), 1.5):
            assert not node.set_parameters(
                [Parameter('drop_probability', value=bad)])[0].successful
        assert runner.faults.drop_probability == 0.25
        assert all(r.successful for r in node.set_parameters(
            [Parameter(n, value=0.0) for n in names]))
        assert runner.faults.garbage_probability == 0.0

        # ~/inject_garbage: the device's noise reaches whoever has the port open.
        # At the device's own baud: at another one the runner garbles the bytes, as a wire does.
        port = serial.Serial(str(link), node.get_parameter('baud').value, timeout=0.1)
        reply = ros.call(Trigger, f'/{name}/inject_garbage')
        assert reply.success, reply.message
        assert node.garbage in _read_until(port, node.garbage, 15.0)

        # ~/disconnect: true pulls the cable (the path vanishes), false plugs it back in.
        reply = ros.call(SetBool, f'/{name}/disconnect', SetBool.Request(data=True))
        assert reply.success, reply.message
        assert not runner.port.plugged
        wait_for(lambda: not link.exists(), 10, what='the link gone while unplugged')
        reply = ros.call(SetBool, f'/{name}/disconnect', SetBool.Request(data=False))
        assert reply.success, reply.message
        wait_for(lambda: link.exists() and runner.port.plugged, 10, what='the link back')

        if next_reply:
            before = runner.faults.drop_next, runner.faults.corrupt_next
            assert ros.call(Trigger, f'/{name}/drop_next_reply').success
            assert ros.call(Trigger, f'/{name}/corrupt_next_reply').success
            assert (runner.faults.drop_next, runner.faults.corrupt_next) == \
                (before[0] + 1, before[1] + 1)
    finally:
        if port is not None:
            port.close()
        ros.executor.remove_node(node)
        node.on_shutdown()
        node.destroy_node()
    assert not link.exists()
