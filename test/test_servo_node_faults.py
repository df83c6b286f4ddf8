"""servo_bus_node when things go wrong: a servo vanishes, stalls, overheats; noise; unplugging.

One node process with custom joint names serves the module.
"""

import math

from diagnostic_msgs.msg import DiagnosticStatus
import pytest
from uav_serial_common.process import wait_for
from servo_rig import start_rig, stop_rig
from uav_serial_drivers.srv import ScanBus, SetTorque, WriteRegister

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR


@pytest.fixture(scope='module')
def rig(tmp_path_factory):
    rig = start_rig(tmp_path_factory.mktemp('servo_faults'), 'servo_faults',
                    parameters={'joint_names': ['pan', 'tilt', 'roll']})
    yield rig
    stop_rig(rig)


def all_online(msg):
    return len(msg.servos) == 3 and all(s.online for s in msg.servos)


def test_custom_joint_names_are_published(rig):
    msg = rig.joints.wait(lambda m: len(m.name) == 3, 5)
    assert list(msg.name) == ['pan', 'tilt', 'roll']
    rig.diag('/servo_bus: tilt (id 2)', lambda s: s.level == OK)


def test_a_removed_servo_goes_offline_while_the_others_keep_publishing(rig):
    with rig.locked():
        rig.sim.remove_servo(3)
    start = len(rig.states)
    st = rig.state(3, start=start, pred=lambda s: not s.online, what='roll offline')
    assert st.name == 'roll' and st.error_count >= 3
    status = rig.diag('/servo_bus: roll (id 3)', lambda s: s.level == ERROR,
                      start=len(rig.diags))
    assert 'roll' in status.message and 'offline' in status.message
    rig.diag('/servo_bus: bus', lambda s: s.level == WARN and 'roll (id 3)' in s.message)
    start = len(rig.joints)
    for k in range(5):
        msg = rig.joints.wait(lambda m: True, 5, start=start + k)
        assert list(msg.name) == ['pan', 'tilt']
    with rig.locked():
        rig.sim.add_servo(3)
    rig.state(3, start=len(rig.states), pred=lambda s: s.online, what='roll back online')


def test_stall_trips_overload_and_diagnostics_warn_naming_the_servo(rig):
    resp = rig.call(WriteRegister, 'write_register', id=1, register_name='stall_protection_time',
                    value=0)
    assert resp.success, resp.message
    assert rig.call(SetTorque, 'set_torque', ids=[1], enable=True).success
    with rig.locked():
        rig.sim.stall(1)
    st = rig.state(1, start=len(rig.states), pred=lambda s: s.overload, what='overload')
    assert st.status & 0x20 and st.name == 'pan'
    status = rig.diag('/servo_bus: pan (id 1)', lambda s: s.level == WARN, start=len(rig.diags))
    assert 'overload' in status.message and 'pan' in status.message
    with rig.locked():
        rig.sim.stall(1, False)
    # Torque on again acknowledges the overload (S21).
    assert rig.call(SetTorque, 'set_torque', ids=[1], enable=True).success
    rig.state(1, start=len(rig.states), pred=lambda s: not s.overload, what='overload cleared')
    rig.diag('/servo_bus: pan (id 1)', lambda s: s.level == OK, start=len(rig.diags))
    assert rig.call(SetTorque, 'set_torque', ids=[1], enable=False).success
    rig.call(WriteRegister, 'write_register', id=1, register_name='stall_protection_time',
             value=3)


def test_over_temperature_warns(rig):
    with rig.locked():
        rig.sim.overheat(2, 85.0)
    # The status bit comes with every reply, the temperature with the next telemetry read.
    rig.state(2, start=len(rig.states), pred=lambda s: s.over_temperature and
              s.temperature_c >= 80, what='over-temperature at 85 degC')
    status = rig.diag('/servo_bus: tilt (id 2)', lambda s: s.level == WARN, start=len(rig.diags))
    assert 'over-temperature' in status.message
    with rig.locked():
        rig.sim.cool(2)
        rig.sim_servo(2).temperature_c = 25.0
    rig.state(2, start=len(rig.states), pred=lambda s: not s.over_temperature, what='cooled')


def test_garbage_on_the_line_is_skipped(rig):
    noise = bytes([0xFF, 0xF5, 0x01, 0x04, 0x00, 0xFF, 0xFF, 0xF5, 0x09, 0x42, 0x13, 0xFF])
    for _ in range(10):
        rig.dev.runner.inject_garbage(noise)
        rig.joints.wait(lambda m: True, 5, start=len(rig.joints))
    start = len(rig.states)
    msg = rig.states.wait(all_online, 5, start=start + 5, what='all online after the noise')
    assert all(not math.isnan(s.position_rad) for s in msg.servos)
    with rig.locked():
        want = rig.sim_servo(2).position_ticks
    assert msg.servos[1].position_ticks == want


def test_a_lost_reply_is_read_again_at_once_and_costs_the_servo_nothing(rig):
    retries = bus_value(rig.diag('/servo_bus: bus', lambda s: True, start=len(rig.diags)),
                        'retries')
    # The READ is sent again within the same cycle: no failed transaction, no data gap. A
    # device process stalled past the margin on a loaded host fails a transaction of its own,
    # truly (campaign s11f, run 10), so a drop that met one is dropped again, up to three
    # times: a driver that did not read again at once costs the servo an error every time.
    costs = []
    for _ in range(3):
        errors, after = drop_one_reply(rig)
        if after == errors:
            break
        costs.append((errors, after))
    else:
        pytest.fail(f'every lost reply cost a servo an error: {costs}')
    # (At least one: a device stalled past the margin meanwhile adds its own, truly, and the
    # diagnostics, once a second, may show both at once.)
    rig.diag('/servo_bus: bus', lambda s: bus_value(s, 'retries') >= retries + 1,
             start=len(rig.diags))


def drop_one_reply(rig):
    """Drop the device's next reply; return the servos' error counts before and after."""
    msg = rig.states.wait(all_online, 5, start=len(rig.states), what='all online')
    errors = [s.error_count for s in msg.servos]
    dropped = rig.dev.runner.replies_dropped
    rig.dev.runner.faults.drop_next = 1
    wait_for(lambda: rig.dev.runner.replies_dropped == dropped + 1, 5, what='a reply dropped')
    start = len(rig.states)
    msg = rig.states.wait(all_online, 5, start=start + 3, what='states after the drop')
    return errors, [s.error_count for s in msg.servos]


def bus_value(status, key):
    return int({v.key: v.value for v in status.values}[key])


def test_two_servos_answering_to_one_id_are_reported_as_a_duplicate_id(rig):
    # Their replies collide (S24): mostly garbled, so the servo may show offline first.
    with rig.locked():
        rig.sim.add_servo(2, allow_duplicate=True)
    try:
        # One diagnostics message says it all: the servo's status, the bus's, and the servos
        # with ids of their own not suspected.
        def said(array):
            by_name = {s.name: s for s in array.status}
            tilt, bus = by_name.get('/servo_bus: tilt (id 2)'), by_name.get('/servo_bus: bus')
            pan = by_name.get('/servo_bus: pan (id 1)')
            return (tilt is not None and tilt.level == ERROR and 'duplicate id' in tilt.message
                    and bus is not None and bus.level == ERROR and pan is not None
                    and pan.level == OK)
        array = rig.diags.wait(said, 5.0, what='a duplicate id in the diagnostics',
                               start=len(rig.diags))
        by_name = {s.name: s for s in array.status}
        assert '~/set_id' in by_name['/servo_bus: tilt (id 2)'].message
        assert 'id(s) 2' in by_name['/servo_bus: bus'].message
        scan = rig.call(ScanBus, 'scan', first_id=1, last_id=5)
        assert scan.success and list(scan.ids) == [1, 2, 3]
        assert 'more than one servo answers to id(s) 2:' in scan.message, scan.message
    finally:
        with rig.locked():
            rig.sim.servos.pop()
    rig.diag('/servo_bus: tilt (id 2)', lambda s: s.level == OK, timeout=10,
             start=len(rig.diags))


def test_unplug_and_replug_recover_without_a_restart(rig):
    rig.dev.runner.unplug()
    status = rig.diag('/servo_bus: bus', lambda s: s.level == ERROR, start=len(rig.diags))
    assert status.hardware_id == rig.dev.path
    rig.state(1, start=len(rig.states), pred=lambda s: not s.online, what='offline unplugged')
    rig.dev.runner.replug()
    rig.states.wait(all_online, 10, start=len(rig.states), what='all online after replug')
    status = rig.diag('/servo_bus: bus', lambda s: s.level == OK, start=len(rig.diags))
    values = {v.key: v.value for v in status.values}
    assert int(values['reconnects']) >= 1
    assert rig.node.alive()
