"""virtual_servo_bus and servo_bus_node together as processes from the installed package."""

from sensor_msgs.msg import JointState
from std_srvs.srv import SetBool, Trigger
from uav_serial_drivers.msg import ServoStateArray
from uav_serial_drivers.srv import SimServoFault


def test_virtual_bus_and_driver_run_together(ros, launch, tmp_path):
    link = str(tmp_path / 'vservobus')
    launch.start('virtual_servo_bus', parameters={'link': link, 'servo_ids': [4, 7]}, ros=ros,
                 wait_service='/virtual_servo_bus/set_fault')
    joints = ros.subscribe(JointState, '/joint_states')
    states = ros.subscribe(ServoStateArray, '/servo_bus/servo_states')
    # servo_ids empty: the driver scans 1..250 at start and finds the virtual bus's servos.
    launch.start('servo_bus_node', parameters={'port': link}, ros=ros,
                 wait_service='/servo_bus/emergency_stop')
    msg = joints.wait(lambda m: len(m.name) == 2, 30, what='both servos found by the scan')
    assert list(msg.name) == ['servo_4', 'servo_7']

    resp = ros.call(SimServoFault, '/virtual_servo_bus/set_fault',
                    SimServoFault.Request(id=7, fault='remove'))
    assert resp.success, resp.message
    states.wait(lambda m: [s.online for s in m.servos] == [True, False], 10, start=len(states),
                what='servo 7 offline')
    resp = ros.call(SimServoFault, '/virtual_servo_bus/set_fault',
                    SimServoFault.Request(id=7, fault='add'))
    assert resp.success, resp.message
    bad = ros.call(SimServoFault, '/virtual_servo_bus/set_fault',
                   SimServoFault.Request(id=4, fault='melt', active=True))
    assert not bad.success and 'unknown fault' in bad.message

    resp = ros.call(SimServoFault, '/virtual_servo_bus/set_fault',
                    SimServoFault.Request(id=4, fault='overheat', active=True))
    assert resp.success
    states.wait(lambda m: m.servos[0].over_temperature, 10, start=len(states))
    ros.call(SimServoFault, '/virtual_servo_bus/set_fault',
             SimServoFault.Request(id=4, fault='clear'))

    assert ros.call(SetBool, '/virtual_servo_bus/disconnect', SetBool.Request(data=True)).success
    states.wait(lambda m: not any(s.online for s in m.servos), 10, start=len(states),
                what='offline while unplugged')
    assert ros.call(SetBool, '/virtual_servo_bus/disconnect', SetBool.Request(data=False)).success
    assert ros.call(Trigger, '/virtual_servo_bus/inject_garbage').success
    states.wait(lambda m: all(s.online for s in m.servos) and not m.servos[0].over_temperature,
                10, start=len(states), what='both online again after replug')
