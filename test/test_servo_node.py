"""servo_bus_node against the simulated bus: joint states, commands, torque, registers, ids.

One node process serves the whole module; each test leaves the bus as it found it or uses
servos the others do not rely on.
"""

import math
import time

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.protocol import Instruction
from desheng_servo_ros.state import LOOP_READS
import pytest
from uav_serial_common.process import wait_for
from servo_rig import start_rig, stop_rig
from std_srvs.srv import Trigger
from support import ask_again, stamp_s
from uav_serial_drivers.msg import ServoCommand
from uav_serial_drivers.srv import (FactoryReset, GoToPreset, ReadRegister, ScanBus, SetId,
                                    SetTorque, WritePositions, WriteRegister)


@pytest.fixture(scope='module')
def rig(tmp_path_factory):
    rig = start_rig(tmp_path_factory.mktemp('servo_node'), 'servo_node')
    yield rig
    stop_rig(rig)


def ticks(rad):
    return int(round(2048 + rad * 4096 / (2 * math.pi)))


def sim_positions(rig, ids):
    with rig.locked():
        return [rig.sim_servo(i).position_ticks for i in ids]


def torque(rig, ids, enable):
    resp = rig.call(SetTorque, 'set_torque', ids=ids, enable=enable)
    assert resp.success, resp.message
    return resp


def test_a_healthy_start_logs_no_warning(rig):
    # Issue 11: it used to log "[WARN] ... is not open" right after "opened ...": a warning
    # that means nothing teaches users to ignore warnings.
    rig.joints.wait(lambda m: len(m.name) == 3, 5, what='joint_states of every servo')
    output = rig.node.output()
    assert 'opened' in output
    assert '[WARN]' not in output and '[ERROR]' not in output, output


def test_joint_states_are_in_rad_for_every_online_servo(rig):
    with rig.locked():
        rig.sim.move_by_hand(1, 3072)
        rig.sim.move_by_hand(2, 1024)
    start = len(rig.joints)
    msg = rig.joints.wait(lambda m: len(m.position) == 3 and
                          abs(m.position[0] - math.pi / 2) < 1e-9, 5, start=start,
                          what='servo_1 at +pi/2')
    assert list(msg.name) == ['servo_1', 'servo_2', 'servo_3']
    assert msg.position[1] == pytest.approx(-math.pi / 2)
    assert msg.position[2] == pytest.approx(0.0)
    assert len(msg.velocity) == 3 and msg.header.frame_id == 'servo_bus'
    with rig.locked():
        rig.sim.move_by_hand(1, 2048)
        rig.sim.move_by_hand(2, 2048)


def test_servo_states_list_every_servo_with_telemetry(rig):
    start = len(rig.states)
    msg = rig.states.wait(lambda m: len(m.servos) == 3 and all(
        not math.isnan(s.temperature_c) for s in m.servos), 5, start=start)
    assert [s.id for s in msg.servos] == [1, 2, 3]
    assert [s.name for s in msg.servos] == ['servo_1', 'servo_2', 'servo_3']
    for s in msg.servos:
        assert s.online and s.temperature_c == pytest.approx(25, abs=2)
        assert not (s.overload or s.over_temperature or s.voltage_fault)
    rig.diag('/servo_bus: bus', lambda s: s.level == b'\x00' and '3/3' in s.message)


def test_the_bus_diagnostics_say_what_the_port_is_and_the_reply_margin(rig):
    status = rig.diag('/servo_bus: bus', lambda s: any(v.key == 'latency timer action'
                                                       for v in s.values))
    values = {v.key: v.value for v in status.values}
    assert 'pseudo-terminal' in values['latency timer action']
    assert values['udev rule'] == 'not needed'
    # The rig sets response_timeout_ms; the derived margin is tested in test_servo_core.
    assert values['reply margin [ms]'] == '250.0 (response_timeout_ms)'
    log = rig.node.output()
    assert log.count('serial port latency:') == 1 and 'pseudo-terminal' in log


def test_joint_states_are_stamped_when_their_positions_were_read(rig):
    # Stamped with the arrival of the cycle's oldest reply, before it was published and
    # received; servo_states of the same cycle carry the same stamp.
    start_j, start_s = len(rig.joints), len(rig.states)
    rig.joints.wait(lambda m: len(m.name) == 3, 5, start=start_j + 5)
    rig.states.wait(lambda m: True, 5, start=start_s + 5)
    now = time.time()
    joints = rig.joints.messages[start_j:]
    states = rig.states.messages[start_s:]
    assert all(stamp_s(m) <= now for m in joints + states)
    assert [stamp_s(m) for m in joints] == sorted(stamp_s(m) for m in joints)
    assert {stamp_s(m) for m in joints} & {stamp_s(m) for m in states}


def test_command_is_one_sync_write_and_the_servos_reach_their_targets(rig):
    torque(rig, [1, 2], True)
    mark = rig.wire.mark()
    pub = rig.ros.publisher(ServoCommand, '/servo_bus/command')
    pub.publish(ServoCommand(ids=[1, 2], positions=[0.5, -0.25], move_time_ms=100))
    want = [ticks(0.5), ticks(-0.25)]
    wait_for(lambda: sim_positions(rig, [1, 2]) == want, 5, what='servos at their targets')
    sent = rig.wire.commands(mark)
    assert [r.raw for r in sent] == [
        proto.encode_sync_write_positions([(1, want[0], 100), (2, want[1], 100)])]
    start = len(rig.joints)
    rig.joints.wait(lambda m: m.position[0] == pytest.approx(0.5, abs=0.002) and
                    m.position[1] == pytest.approx(-0.25, abs=0.002), 5, start=start)
    # By name, default move time (0 = fastest): the same frame layout.
    mark = rig.wire.mark()
    pub.publish(ServoCommand(names=['servo_2', 'servo_1'], positions=[0.0, 0.0]))
    wait_for(lambda: sim_positions(rig, [1, 2]) == [2048, 2048], 5, what='back at 0 rad')
    assert [r.raw for r in rig.wire.commands(mark)] == [
        proto.encode_sync_write_positions([(2, 2048, 0), (1, 2048, 0)])]
    torque(rig, [1, 2], False)


def test_bad_commands_put_nothing_on_the_wire(rig):
    pub = rig.ros.publisher(ServoCommand, '/servo_bus/command')
    mark = rig.wire.mark()
    for bad in (ServoCommand(names=['nope'], positions=[0.0]),
                ServoCommand(ids=[9], positions=[0.0]),
                ServoCommand(names=['servo_1'], ids=[1], positions=[0.0]),
                ServoCommand(positions=[0.0]),
                ServoCommand(ids=[1, 2], positions=[0.0]),
                ServoCommand(ids=[1], positions=[math.pi]),
                ServoCommand(ids=[1], positions=[float('nan')]),
                ServoCommand(ids=[1], positions=[0.0], move_time_ms=70000)):
        pub.publish(bad)
    # A good command after the bad ones: once it is on the wire, the bad ones were handled.
    pub.publish(ServoCommand(ids=[3], positions=[0.0], move_time_ms=5))
    wait_for(lambda: rig.wire.commands(mark), 5, what='the good command')
    assert [r.raw for r in rig.wire.commands(mark)] == [
        proto.encode_sync_write_positions([(3, 2048, 5)])]


def test_write_positions_refuses_out_of_range_before_the_wire(rig):
    mark = rig.wire.mark()
    resp = rig.call(WritePositions, 'write_positions', names=['servo_2'], positions=[3.5])
    assert not resp.success
    assert 'servo_2' in resp.message and '3.5' in resp.message and '-3.1416' in resp.message
    resp = rig.call(WritePositions, 'write_positions', ids=[1, 1], positions=[0.0, 0.0])
    assert not resp.success and 'twice' in resp.message
    assert rig.wire.commands(mark) == []


def test_staged_move_is_reg_writes_then_one_action(rig):
    torque(rig, [1, 3], True)
    seen = {}

    def tap(direction, data, t):
        # Runs on the device thread before the model handles `data`: the state before ACTION.
        if direction == 'rx' and proto.encode_action() in data and 'at_action' not in seen:
            seen['at_action'] = [(s.position_ticks, s.pending is not None)
                                 for s in (rig.sim_servo(1), rig.sim_servo(3))]
    rig.dev.runner.add_tap(tap)
    mark = rig.wire.mark()
    resp = rig.call(WritePositions, 'write_positions', ids=[1, 3], positions=[1.0, -1.0],
                    move_time_ms=50, staged=True)
    assert resp.success, resp.message
    want = [ticks(1.0), ticks(-1.0)]
    wait_for(lambda: sim_positions(rig, [1, 3]) == want, 5, what='staged move done')
    sent = rig.wire.commands(mark)
    assert [(r.instruction, r.servo_id) for r in sent] == [
        (Instruction.REG_WRITE, 1), (Instruction.REG_WRITE, 3), (Instruction.ACTION, 254)]
    assert sent[0].raw == proto.encode_reg_write_position(1, want[0], 50)
    assert seen['at_action'] == [(2048, True), (2048, True)]
    rig.call(WritePositions, 'write_positions', ids=[1, 3], positions=[0.0, 0.0])
    wait_for(lambda: sim_positions(rig, [1, 3]) == [2048, 2048], 5, what='back at 0')
    torque(rig, [1, 3], False)


def test_set_torque_verifies_and_emergency_stop_is_one_broadcast(rig):
    resp = torque(rig, [], True)
    assert 'read-back' in resp.message
    with rig.locked():
        assert all(rig.sim_servo(i).torque_enabled for i in (1, 2, 3))
    rig.state(2, start=len(rig.states), pred=lambda s: s.torque_enabled, what='torque shown')
    mark = rig.wire.mark()
    resp = rig.call(Trigger, 'emergency_stop')
    assert resp.success, resp.message
    # A broadcast gets no reply: the service may answer before the device has read the frame.
    wait_for(lambda: rig.wire.commands(mark), 5, what='the emergency stop on the wire')
    assert [r.raw for r in rig.wire.commands(mark)] == [proto.encode_write(254, 0x28, b'\x00')]

    def limp():
        with rig.locked():
            return not any(rig.sim_servo(i).torque_enabled for i in (1, 2, 3))
    wait_for(limp, 5, what='every servo limp')
    resp = rig.call(SetTorque, 'set_torque', ids=[42], enable=True)
    assert not resp.success and '42' in resp.message


def test_read_register_by_name_and_by_address(rig):
    resp = rig.call(ReadRegister, 'read_register', id=2, register_name='firmware_version')
    assert resp.success and resp.text == 'v1.28' and list(resp.data) == [1, 28]
    resp = rig.call(ReadRegister, 'read_register', id=2, register_name='temperature')
    assert resp.success and resp.text.endswith('degC') and 20 <= resp.value <= 30
    with rig.locked():
        rig.sim.move_by_hand(2, 1234)
    resp = rig.call(ReadRegister, 'read_register', id=2, address=0x38, length=2)
    assert resp.success and resp.value == 1234 and list(resp.data) == [0x04, 0xD2]
    resp = rig.call(ReadRegister, 'read_register', id=2, address=0x38, length=4)
    assert resp.success and 'present_position=1234' in resp.text
    with rig.locked():
        rig.sim.move_by_hand(2, 2048)


def test_a_register_read_of_a_loop_reads_length_answers_its_own_bytes(rig):
    # A reply names its servo and its length, not its address: ~/read_register of 8 bytes goes
    # as a READ of a length the read loop never uses (whose late 8-byte reply, position to
    # temperature, would otherwise pass for registers 0x10..0x17), and answers the 8 asked for.
    loop_lengths = {n for _, n in LOOP_READS}
    for address in (0x10, 0xF8):
        with rig.locked():
            expected = list(rig.sim_servo(2).read(address, 8))
        mark = rig.wire.mark()
        resp = rig.call(ReadRegister, 'read_register', id=2, address=address, length=8)
        assert resp.success, resp.message
        assert list(resp.data) == expected
        reads = [tuple(r.params) for r in rig.wire.commands(mark)
                 if r.instruction == Instruction.READ and r.servo_id == 2]
        assert reads and not {n for _, n in reads} & loop_lengths, reads


def test_write_register_by_name_reads_back(rig):
    resp = rig.call(WriteRegister, 'write_register', id=3, register_name='stall_protection_time',
                    value=5)
    assert resp.success, resp.message
    with rig.locked():
        assert rig.sim_servo(3).register('stall_protection_time') == 5
    resp = rig.call(WriteRegister, 'write_register', id=3, register_name='stall_protection_time',
                    value=3)
    assert resp.success, resp.message


def test_register_refusals_put_nothing_on_the_wire(rig):
    mark = rig.wire.mark()
    for fields in (dict(id=1, register_name='present_position', value=5),
                   dict(id=1, register_name='run_time', value=70000),
                   dict(id=1, register_name='center_offset', value=-40000),
                   dict(id=1, register_name='no_such_register', value=1),
                   dict(id=0, register_name='run_time', value=1),
                   dict(id=1, register_name='id', value=9)):
        resp = rig.call(WriteRegister, 'write_register', **fields)
        assert not resp.success and resp.message.startswith('refused'), (fields, resp.message)
    resp = rig.call(WriteRegister, 'write_register', id=1, register_name='present_position',
                    value=5)
    assert 'read-only' in resp.message
    resp = rig.call(WriteRegister, 'write_register', id=1, register_name='run_tme', value=5)
    assert 'run_time' in resp.message  # the closest match is suggested
    for fields in (dict(id=1, register_name='run_preset_1'), dict(id=1, register_name='nope'),
                   dict(id=254, register_name='temperature'), dict(id=1, address=0xF0, length=32),
                   dict(id=1, address=0x38, length=0)):
        resp = rig.call(ReadRegister, 'read_register', **fields)
        assert not resp.success, fields
    assert rig.wire.commands(mark) == []


def test_scan_finds_exactly_the_sims_ids_with_their_firmware(rig):
    resp = rig.call(ScanBus, 'scan', first_id=1, last_id=8)
    assert resp.success, resp.message
    assert list(resp.ids) == [1, 2, 3]
    assert list(resp.firmware_versions) == ['v1.28'] * 3
    resp = rig.call(ScanBus, 'scan', first_id=5, last_id=4)
    assert not resp.success


def test_go_to_preset_runs_the_stored_position(rig):
    torque(rig, [2], True)
    with rig.locked():
        rig.sim.move_by_hand(2, 3000)
    mark = rig.wire.mark()
    resp = rig.call(GoToPreset, 'go_to_preset', ids=[2], preset=1)
    assert resp.success, resp.message
    wait_for(lambda: sim_positions(rig, [2]) == [2048], 5, what='servo 2 at preset 1')
    assert [r.raw for r in rig.wire.commands(mark)] == [proto.encode_write(2, 0x3C)]
    mark = rig.wire.mark()
    assert not rig.call(GoToPreset, 'go_to_preset', ids=[2], preset=4).success
    assert rig.wire.commands(mark) == []
    torque(rig, [2], False)


def test_set_id_is_refused_when_the_new_id_answers(rig):
    # Id 9 is not in servo_ids (a configured id is refused before the wire, safety item 15)
    # but a servo answers there.
    with rig.locked():
        rig.sim.add_servo(9)
    try:
        mark = rig.wire.mark()
        resp = rig.call(SetId, 'set_id', id=1, new_id=9)
        assert not resp.success and 'already answers' in resp.message
        # Nothing but the PING of 9 (twice if the first reply was late: the second tells).
        sent = [r.raw for r in rig.wire.commands(mark)]
        assert sent in ([proto.encode_ping(9)], [proto.encode_ping(9)] * 2), sent
        assert rig.sim.ids == [1, 2, 3, 9]
    finally:
        with rig.locked():
            rig.sim.remove_servo(9)


def set_id(rig, old, new):
    """Call ~/set_id as a user would on a loaded host; return its response.

    Its probe READs each wait a patient margin, which a device stalled longer overruns: before
    the change the answer is "cannot be told; nothing changed. Try again" (a user does), after
    it "answers at id N, but whether it is alone there was not seen". Both are true.
    """
    resp, _ = ask_again(lambda: rig.call(SetId, 'set_id', id=old, new_id=new),
                        lambda r: not r.success and 'nothing changed. Try again' in r.message)
    assert resp.success or f'answers at id {new}, but whether it is alone there was not seen' \
        in resp.message, resp.message
    return resp


def test_set_id_moves_a_servo_and_the_node_follows(rig):
    set_id(rig, 3, 9)
    assert sorted(rig.sim.ids) == [1, 2, 9]
    st = rig.state(9, start=len(rig.states), pred=lambda s: s.online, what='servo 9 online')
    assert st.name == 'servo_9'
    set_id(rig, 9, 3)
    rig.state(3, start=len(rig.states), pred=lambda s: s.online, what='servo 3 back')


def test_factory_reset_needs_the_token(rig):
    rig.call(WriteRegister, 'write_register', id=1, register_name='stall_protection_time',
             value=7)
    mark = rig.wire.mark()
    for token in ('', 'reset', 'RESET '):
        resp = rig.call(FactoryReset, 'factory_reset', id=1, confirm=token)
        assert not resp.success and 'RESET' in resp.message
    assert rig.wire.commands(mark) == []
    resp = rig.call(FactoryReset, 'factory_reset', id=1, confirm='RESET')
    assert resp.success, resp.message
    assert proto.encode_reset(1) in [r.raw for r in rig.wire.commands(mark)]
    with rig.locked():
        assert rig.sim_servo(1).register('stall_protection_time') == 3
