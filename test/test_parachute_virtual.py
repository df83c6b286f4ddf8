"""virtual_parachute and parachute_node from the installed package, as two processes."""

import json
import os
import signal

from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from std_srvs.srv import SetBool, Trigger
from std_msgs.msg import String
from support import arm_parachute
from uav_serial_drivers.msg import ParachuteConfig, ParachuteStatus
from uav_serial_drivers.srv import Deploy


def test_driver_and_virtual_module_talk_to_each_other(ros, launch, tmp_path):
    link = str(tmp_path / 'vparachute')
    state = ros.subscribe(String, '/virtual_parachute/state')
    launch.start('virtual_parachute', parameters={'link': link, 'stream_rate_hz': 20.0},
                 ros=ros, wait_service='/virtual_parachute/power_cycle')
    status = ros.subscribe(ParachuteStatus, '/parachute/status')
    config = ros.subscribe(ParachuteConfig, '/parachute/config', latched=True)
    driver = launch.start('parachute_node',
                          parameters={'port': link, 'blackbox_dir': str(tmp_path / 'bb')},
                          ros=ros, wait_service='/parachute/deploy')
    status.wait(lambda m: m.online and m.streaming, 15, what='online status')
    first = config.wait(lambda m: m.valid, 10, what='config').boot_count
    arm_parachute(ros)
    seen = state.wait(lambda m: json.loads(m.data)['armed'], 5, what='model armed')
    assert json.loads(seen.data)['plugged']
    # A power cycle of the virtual module: the driver notices and re-initializes it.
    assert ros.call(Trigger, '/virtual_parachute/power_cycle').success
    config.wait(lambda m: m.boot_count == first + 1, 10, what='boot count after power cycle')
    status.wait(lambda m: m.online and m.streaming and not m.armed, 10,
                what='streaming again after the power cycle', start=len(status) - 1)
    # Pulling the virtual cable takes the driver offline; plugging it back brings it online.
    assert ros.call(SetBool, '/virtual_parachute/disconnect', SetBool.Request(data=True)).success
    status.wait(lambda m: not m.online, 3, what='offline', start=len(status) - 1)
    assert ros.call(SetBool, '/virtual_parachute/disconnect',
                    SetBool.Request(data=False)).success
    status.wait(lambda m: m.online, 10, what='online again', start=len(status) - 1)
    # Deploy frames lost on their way in: the driver gives up after two of them, and refuses
    # a third until the module has rebooted.
    assert set_lost_commands(ros, [0x11]).successful
    reply = ros.call(Deploy, '/parachute/deploy',
                     Deploy.Request(confirm='DEPLOY', arm_if_locked=True))
    assert not reply.success and 'NOT acknowledged after 2 attempts' in reply.message
    assert not set_lost_commands(ros, [256]).successful
    assert set_lost_commands(ros, []).successful
    reply = ros.call(Deploy, '/parachute/deploy', Deploy.Request(confirm='DEPLOY'))
    assert not reply.success and 'reboot' in reply.message
    assert ros.call(Trigger, '/virtual_parachute/power_cycle').success
    config.wait(lambda m: m.boot_count == first + 2, 10, what='boot count after power cycle')
    status.wait(lambda m: m.online and m.streaming, 10, what='streaming after the reboot',
                start=len(status) - 1)
    # The deploy acknowledgement is on disk before the service answers: SIGKILL keeps it.
    reply = ros.call(Deploy, '/parachute/deploy',
                     Deploy.Request(confirm='DEPLOY', arm_if_locked=True))
    assert reply.success, reply.message
    os.kill(driver.pid, signal.SIGKILL)
    driver.popen.wait(5)
    box = next((tmp_path / 'bb').glob('parachute-*.jsonl'))
    # Only lines after the last sync may be cut short by the kill.
    assert any('"what":"deploy acknowledged"' in line for line in box.read_text().splitlines())


def set_lost_commands(ros, codes):
    value = ParameterValue(type=ParameterType.PARAMETER_INTEGER_ARRAY, integer_array_value=codes)
    request = SetParameters.Request(parameters=[Parameter(name='lost_commands', value=value)])
    return ros.call(SetParameters, '/virtual_parachute/set_parameters', request).results[0]


def test_round2_2_the_virtual_module_reproduces_a_dead_stream(ros, launch, tmp_path):
    """``stream_dead``: the stream stops and 0x13 is ignored; the driver polls and deploys."""
    link = str(tmp_path / 'vparachute')
    state = ros.subscribe(String, '/virtual_parachute/state')
    launch.start('virtual_parachute', parameters={'link': link, 'tilt_deg': 50.0}, ros=ros,
                 wait_service='/virtual_parachute/power_cycle')
    status = ros.subscribe(ParachuteStatus, '/parachute/status')
    launch.start('parachute_node', parameters={'port': link, 'blackbox_dir': str(tmp_path / 'bb')},
                 ros=ros, wait_service='/parachute/deploy')
    status.wait(lambda m: m.online and m.streaming, 15, what='online status')
    value = ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=True)
    request = SetParameters.Request(parameters=[Parameter(name='stream_dead', value=value)])
    assert ros.call(SetParameters, '/virtual_parachute/set_parameters',
                    request).results[0].successful
    state.wait(lambda m: json.loads(m.data)['stream_dead'], 5, what='the model: stream dead')
    status.wait(lambda m: m.online and not m.streaming and m.tilt_deg == 50, 10,
                what='polled status', start=len(status) - 1)
    reply = ros.call(Deploy, '/parachute/deploy',
                     Deploy.Request(confirm='DEPLOY', arm_if_locked=True))
    assert reply.success, reply.message
