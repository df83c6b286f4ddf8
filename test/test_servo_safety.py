"""Safety items 13-18 of the servo bus, through servo_bus_node as a process and the virtual bus.

Each test is named after its item (issue 10). The rules behind them are tested in the core tests
(test_servo_core.py); these prove that no message, unplugging or flood gets past the node.
"""

import json
import math
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.protocol import Instruction
from desheng_servo_ros.schedule import COMMAND_BURST
import pytest
from servo_rig import LOOP_READS, start_rig, stop_rig
from std_srvs.srv import Trigger
from support import stamp_s
from uav_serial_common.process import wait_for
from uav_serial_drivers.msg import ServoCommand
from uav_serial_drivers.srv import (FactoryReset, GoToPreset, ReadRegister, ScanBus, SetId,
                                    SetTorque, WritePositions, WriteRegister)

HERE = Path(__file__).resolve().parent


@pytest.fixture
def rig(tmp_path, request):
    rig = start_rig(tmp_path, request.node.name[:40])
    yield rig
    stop_rig(rig)


def assert_alive_and_reading(rig, what):
    assert rig.node.alive(), f'the node died ({what}):\n{rig.node.output()}'
    start = len(rig.joints)
    rig.joints.wait(lambda m: len(m.name) == 3, 10, start=start + 3,
                    what=f'joint_states of every servo after {what}')
    output = rig.node.output()
    assert 'Traceback' not in output and 'fatal' not in output, output


def test_safety_13_absurd_values_are_refused_and_the_node_lives(rig):
    pub = rig.ros.publisher(ServoCommand, '/servo_bus/command')
    mark = rig.wire.mark()
    for bad in ([1e308], [-1e308], [math.inf], [-math.inf], [math.nan], [4.0], [-1e300],
                [1.7976931348623157e308]):
        pub.publish(ServoCommand(ids=[1], positions=bad))
    for ms in (-2, -(2 ** 31), 2 ** 31 - 1, 65536):
        pub.publish(ServoCommand(ids=[1], positions=[0.0], move_time_ms=ms))
    pub.publish(ServoCommand(ids=[1] * 10000, positions=[0.0] * 10000))
    pub.publish(ServoCommand(names=['servo_1'] * 10000, positions=[1e308] * 10000))
    pub.publish(ServoCommand(names=['x' * 100000], positions=[0.0]))
    for fields in (dict(ids=[1], positions=[1e308]), dict(ids=[2], positions=[-math.inf]),
                   dict(ids=[3], positions=[math.nan], staged=True),
                   dict(ids=[1], positions=[0.0], move_time_ms=-(2 ** 31)),
                   dict(names=[f'n{k}' for k in range(10000)], positions=[0.0] * 10000)):
        resp = rig.call(WritePositions, 'write_positions', **fields)
        assert not resp.success and resp.message.startswith('refused'), resp.message[:300]
    for srv, name, fields in (
            (WriteRegister, 'write_register', dict(id=1, register_name='run_time',
                                                   value=2 ** 63 - 1)),
            (WriteRegister, 'write_register', dict(id=1, register_name='center_offset',
                                                   value=-(2 ** 63))),
            (ReadRegister, 'read_register', dict(id=1, address=255, length=255)),
            (ReadRegister, 'read_register', dict(id=255, register_name='x' * 10000)),
            (GoToPreset, 'go_to_preset', dict(ids=[1], preset=255)),
            (SetTorque, 'set_torque', dict(ids=[0] * 10000, enable=True)),
            (ScanBus, 'scan', dict(first_id=0, last_id=255)),
            (SetId, 'set_id', dict(id=255, new_id=0)),
            (FactoryReset, 'factory_reset', dict(id=255, confirm='RESET'))):
        resp = rig.call(srv, name, **fields)
        assert not resp.success and len(resp.message) < 600, (name, resp.message[:300])
    # A good command after all that still moves servo 3: everything before it was handled.
    pub.publish(ServoCommand(ids=[3], positions=[0.25], move_time_ms=7))
    wanted = proto.encode_sync_write_positions([(3, 2048 + 163, 7)])
    wait_for(lambda: wanted in [r.raw for r in rig.wire.commands(mark)], 10,
             what='the good command on the wire')
    assert [r.raw for r in rig.wire.commands(mark)] == [wanted]
    assert_alive_and_reading(rig, 'absurd values')


def unplug_cycles(rig, n, rng, unplugged_s, plugged_s=(0.0, 0.0)):
    """Pull the cable `n` times, each for a random time in `unplugged_s`; after each replug wait
    until the driver has reopened the port (set its baud), then a random time in `plugged_s`."""
    port = rig.dev.runner.port
    for _ in range(n):
        rig.dev.runner.unplug()
        time.sleep(rng.uniform(*unplugged_s))
        rig.dev.runner.replug()
        wait_for(lambda: port.line_baud() == 115200, 5, interval=0.0002,
                 what='the driver to reopen the port')
        time.sleep(rng.uniform(*plugged_s))


def test_safety_14_quick_unplug_replug_cycles_never_stop_the_joint_states(rig):
    # A flaky connector: the cable goes again right after the driver has reopened the port
    # (it has set its baud on the pty), while it flushes stale input before its first READ; a
    # vanished pty answers that tcflush with termios.error.
    rig.joints.wait(lambda m: len(m.name) == 3, 5, what='joint_states before the cycles')
    unplug_cycles(rig, 12, random.Random(14), unplugged_s=(0.0, 0.02))
    rig.dev.runner.unplug()
    time.sleep(0.05)
    rig.dev.runner.replug()
    assert_alive_and_reading(rig, '12 quick unplug/replug cycles')
    start = len(rig.joints)
    rig.joints.wait(lambda m: len(m.name) == 3, 10, start=start + 20,
                    what='joint_states going on')
    assert 'read loop stopped' not in rig.node.output()


def test_safety_15_set_id_onto_an_offline_configured_id_is_refused(rig):
    # Online first: a start-up state (nothing read yet) also says servo 3 is not online, and
    # was taken for the removal's (campaign s14a, run 1).
    online = rig.states.wait(lambda m: any(s.id == 3 and s.online for s in m.servos), 10,
                             what='servo_3 online')
    with rig.locked():
        rig.sim.remove_servo(3)
    offline = rig.states.wait(lambda m: any(s.id == 3 and not s.online for s in m.servos), 5,
                              what='servo_3 offline',
                              start=rig.states.messages.index(online) + 1)
    mark = rig.wire.mark()
    resp = rig.call(SetId, 'set_id', id=2, new_id=3)
    assert not resp.success and 'servo_3' in resp.message and 'servo_ids' in resp.message
    assert rig.wire.commands(mark) == []
    assert rig.sim.ids == [1, 2]
    # Published since servo_3 was offline (by their stamps: on a loaded host a joint_states of
    # before can reach this process after the call, campaign s10c run 6).
    since = stamp_s(offline)
    start = len(rig.joints)
    for _ in range(5):
        msg = rig.joints.wait(lambda m: stamp_s(m) >= since, 5, start=start)
        start = rig.joints.messages.index(msg) + 1
        assert len(set(msg.name)) == len(msg.name) and list(msg.name) == ['servo_1', 'servo_2']


def test_safety_16_set_id_is_refused_when_two_servos_answer_at_the_old_id(rig):
    # The driver's own advice used to destroy an id: reset servo 2 (it goes to the factory id 1,
    # where servo 1 is), then set_id 1 -> 5 renamed both.
    with rig.locked():
        rig.sim.move_by_hand(2, 1000)
    resp = rig.call(FactoryReset, 'factory_reset', id=2, confirm='RESET')
    assert resp.success
    assert 'WARNING' in resp.message and 'factory id 1' in resp.message, resp.message
    assert 'servo_1' in resp.message
    assert rig.sim.ids == [1, 1, 3]
    mark = rig.wire.mark()
    resp = rig.call(SetId, 'set_id', id=1, new_id=5)
    assert not resp.success and 'more than one servo answers at id 1' in resp.message
    assert [r for r in rig.wire.commands(mark) if r.instruction == Instruction.WRITE] == []
    assert rig.sim.ids == [1, 1, 3]


def test_safety_16_set_id_across_an_unplug_finds_out_what_the_servo_did(rig):
    write_id = proto.encode_write(3, 0x05, bytes([9]))

    def tap(direction, data, t):
        if direction == 'rx' and write_id in data:
            rig.dev.runner.unplug(duration_s=0.3)  # the cable back 0.3 s later
    rig.dev.runner.add_tap(tap)
    resp = rig.call(SetId, 'set_id', id=3, new_id=9)
    if resp.success:
        assert 'now answers at id 9' in resp.message, resp.message
        assert 'acknowledgement was lost' in resp.message
    else:
        # Found at id 9 all the same; the probe that tells whether it is alone there waits a
        # patient margin per READ, which a host stalled longer than that overruns: then the
        # answer is that this was not seen, truly (campaign s10f). Not a refusal, not a failure.
        assert 'servo 3 answers at id 9, but whether it is alone there was not seen' in \
            resp.message, resp.message
    assert sorted(rig.sim.ids) == [1, 2, 9]
    start = len(rig.joints)
    msg = rig.joints.wait(lambda m: 'servo_9' in m.name, 10, start=start,
                          what='joint_states naming servo_9')
    assert list(msg.name) == ['servo_1', 'servo_2', 'servo_9']


def flood(rig, rate_hz, seconds, ids='1,2'):
    """Publish commands from a process of its own; return its report and the joint_states rate
    over the flood (its first second left out), from the driver's own publication stamps."""
    start = len(rig.joints)
    done = subprocess.run([sys.executable, str(HERE / 'flood_commands.py'), str(rate_hz),
                           str(seconds), ids], capture_output=True, text=True, timeout=90)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report['acked'], 'the driver did not take the last commands within 30 s'
    lo, hi = report['t_start_wall'] + 1.0, report['t_last_wall']
    during = [m for m in rig.joints.messages[start:]
              if lo <= stamp_s(m) <= hi]
    return report, len(during) / (hi - lo)


def wait_newest_on_wire(rig, report, mark):
    """Wait until the flood's newest command (servos 1 and 2) is the last SYNC_WRITE on the
    wire since `mark`; return that frame."""
    ticks = [int(round(2048 + p * 4096 / (2 * math.pi))) for p in report['last']]
    wanted = proto.encode_sync_write_positions([(1, ticks[0], 0), (2, ticks[1], 0)])

    def last_command():
        syncs = [r for r in rig.wire.commands(mark) if r.instruction == Instruction.SYNC_WRITE]
        return syncs[-1].raw if syncs else None
    wait_for(lambda: last_command() == wanted, 5, what='the newest command on the wire')
    return wanted


def test_safety_17_a_command_flood_keeps_the_reads_going_and_the_newest_command_wins(rig):
    times = []

    def tap(direction, data, t):
        if direction == 'rx':
            times.append((t, bytes(data)))
    rig.dev.runner.add_tap(tap)
    # 1000 messages a second cost rclpy's executor most of a core whatever the driver does with
    # them. So "their rate" is the read rate under the same message load: a flood of commands
    # the driver refuses (an unknown id) puts nothing on the bus.
    # (Seconds, not minutes: the long floods and the read ratio they keep are bench/'s.)
    _, refused_rate = flood(rig, 1000, 3, ids='9,2')
    mark = rig.wire.mark()
    report, rate = flood(rig, 1000, 5)
    print(f'joint_states: {refused_rate:.1f} Hz under refused commands, {rate:.1f} Hz under '
          f'{report["sent"]} commands')
    wanted = wait_newest_on_wire(rig, report, mark)
    syncs = [r for r in rig.wire.commands(mark) if r.instruction == Instruction.SYNC_WRITE]
    assert len(syncs) < report['sent']
    # How soon after the driver had it: not seen from here. The publisher's last sample
    # acknowledged is in the driver's reader, not yet taken by its executor, which a loaded host
    # leaves behind a 1000-message flood (91 READs, 1.3 s, once: campaign s13d, run 4). So the
    # READs between the two are printed, not judged: "on the wire within one read cycle of the
    # driver having it" is the bus schedule's invariant, searched in virtual time
    # (test_servo_model), and test_servo_core's with the runtime on a pty.
    arrived = next(t for t, data in reversed(times) if wanted in data)
    reads = []
    for t, data in times:
        if report['t_acked'] <= t <= arrived:
            reads.extend(r for r in proto.StreamDecoder('request').feed(data)
                         if r.instruction == Instruction.READ and tuple(r.params) in LOOP_READS)
    print(f'the newest command on the wire {arrived - report["t_last"]:.3f} s after its '
          f'publication, {arrived - report["t_acked"]:.3f} s and {len(reads)} READs after its '
          'acknowledgement')
    # The reads keep their share of the bus: at most two command batches per read cycle (three
    # READs), counted on the wire over the flood. The read rate it keeps is a timing goal: the
    # ratio above is printed (bench/), not judged here; beside a busy loop the load of the two
    # windows differs (9.4 Hz against 26.3 Hz once).
    decoder = proto.StreamDecoder('request')
    on_wire = [r for t, data in times if report['t_start'] <= t <= report['t_last']
               for r in decoder.feed(data)]
    loop_reads = sum(r.instruction == Instruction.READ and tuple(r.params) in LOOP_READS
                     for r in on_wire)
    batches = sum(r.instruction == Instruction.SYNC_WRITE for r in on_wire)
    print(f'over the flood: {loop_reads} READs of the read loop, {batches} command batches')
    assert loop_reads >= 3 * 3, loop_reads
    assert batches <= 2 * (loop_reads // 3 + 1) + COMMAND_BURST, (batches, loop_reads)
    assert_alive_and_reading(rig, 'the command flood')


def test_round2_22_6_the_newest_command_of_a_flood_arrives_when_the_driver_stalls_at_its_end(
        rig):
    """The driver's process does not run for 2 s while the flood ends (a loaded host does that):
    the last commands reach it afterwards and the newest is on the wire. The flood's publisher
    used to leave 0.5 s after its last message, and the samples the driver had not taken by then
    were never sent again (test_safety_17 saw an older command last, beside a busy loop)."""
    mark = rig.wire.mark()
    flood = subprocess.Popen([sys.executable, str(HERE / 'flood_commands.py'), '1000', '3'],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_for(lambda: any(r.instruction == Instruction.SYNC_WRITE
                             for r in rig.wire.commands(mark)), 15, what='the flood on the wire')
        time.sleep(2.5)
        os.kill(rig.node.pid, signal.SIGSTOP)
        try:
            time.sleep(2.0)
        finally:
            os.kill(rig.node.pid, signal.SIGCONT)
        out, err = flood.communicate(timeout=90)
    finally:
        if flood.poll() is None:
            flood.kill()
            flood.wait()
    assert flood.returncode == 0, err
    report = json.loads(out.strip().splitlines()[-1])
    assert report['acked'], 'the driver did not take the last commands within 30 s'
    wait_newest_on_wire(rig, report, mark)
    assert_alive_and_reading(rig, 'a stall at the end of a command flood')


def test_safety_14_17_a_command_flood_through_unplug_cycles(rig):
    """Items 14 and 17 at once: 500 commands a second while the cable comes and goes. The node
    lives, the reads come back after every replug, and the newest command reaches the wire."""
    rig.joints.wait(lambda m: len(m.name) == 3, 5, what='joint_states before the flood')
    mark = rig.wire.mark()
    flood = subprocess.Popen([sys.executable, str(HERE / 'flood_commands.py'), '500', '6'],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_for(lambda: any(r.instruction == Instruction.SYNC_WRITE
                             for r in rig.wire.commands(mark)), 15, what='the flood on the wire')
        unplug_cycles(rig, 8, random.Random(1417), unplugged_s=(0.01, 0.15),
                      plugged_s=(0.0, 0.15))
        replugged, replugged_at = rig.wire.mark(), time.monotonic()
        out, err = flood.communicate(timeout=90)
    finally:
        if flood.poll() is None:
            flood.kill()
            flood.wait()
    assert flood.returncode == 0, err
    report = json.loads(out.strip().splitlines()[-1])
    assert report['acked'], 'the driver did not take the last commands within 30 s'
    # After the last replug when the flood outlived the cycles (their reopens take longer on a
    # loaded host, campaign of 2026-11-27); else since the flood began: a command the driver
    # took before the last replug went out before it, or after it from the queue.
    wait_newest_on_wire(rig, report, replugged if report['t_last'] > replugged_at else mark)
    assert_alive_and_reading(rig, 'a command flood through 8 unplug/replug cycles')
    assert 'read loop stopped' not in rig.node.output()


def test_safety_18_unknown_names_by_the_thousand_get_a_bounded_answer_and_log_line(rig):
    names = [f'no_such_joint_{k}' for k in range(10000)]
    resp = rig.call(WritePositions, 'write_positions', names=names, positions=[0.0] * 10000)
    assert not resp.success and len(resp.message) < 300, len(resp.message)
    assert "'no_such_joint_0'" in resp.message and 'and 9995 more' in resp.message
    pub = rig.ros.publisher(ServoCommand, '/servo_bus/command')
    pub.publish(ServoCommand(names=names, positions=[0.0] * 10000))
    wait_for(lambda: '~/command refused' in rig.node.output(), 10, what='the refusal logged')
    line = next(line for line in rig.node.output().splitlines() if '~/command refused' in line)
    assert len(line) < 700 and 'and 9995 more' in line, line[:800]
    assert rig.call(Trigger, 'emergency_stop').success
