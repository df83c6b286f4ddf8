"""The servo bus's runtime on a pty: the schedule the model searches, stepped on every path.

Issue 22 item 2 (``desheng_servo_ros/bus_runtime.py``): the reader thread steps each reply, a
DeadlineTimer the deadlines and cycles, callers their commands and calls; the actions are
carried out by handlers. Against the virtual bus (``VirtualServoBus``) in real time; every
wait is on a condition with a generous timeout.
"""

import threading
import time

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.bus_runtime import BusRuntime
from desheng_servo_ros.protocol import Instruction
from desheng_servo_ros.schedule import TORQUE_OFF_ALL
from desheng_servo_ros.units import Joint
from desheng_servo_ros.virtual_node import VirtualServoBus
import pytest
from servo_rig import Wire
from uav_serial_common.process import wait_for

MARGIN_S = 0.25  # a loaded host's stalls are not lost replies (test_servo_link's reasoning)


@pytest.fixture
def bus(tmp_path):
    dev = VirtualServoBus(str(tmp_path / 'bus'), [1, 2, 3], seed=1).start()
    wire = Wire(dev.runner)
    reads, cycles = [], []
    runtime = BusRuntime(dev.path, 115200, [Joint(i, f'j{i}') for i in (1, 2, 3)],
                         publish_rate_hz=100.0, margin_s=MARGIN_S, max_retries=1,
                         on_read=reads.append, on_cycle=cycles.append)
    runtime.start()
    yield dev, wire, runtime, reads, cycles
    runtime.stop()
    dev.stop()


def test_round2_22_servo_runtime_reads_every_servo_from_the_reader_thread(bus):
    _, _, runtime, reads, cycles = bus
    wait_for(lambda: sum(c.reads for c in cycles) >= 5, 20, what='five read cycles')
    answered = {r.servo_id for r in list(reads) if r.reply is not None}
    assert answered == {1, 2, 3}
    assert all(s.online for s in runtime.schedule.servos)
    # No thread of its own beyond the port's reader and the timer.
    names = {t.name for t in threading.enumerate()}
    assert 'servo-bus-timer' in names
    assert not {'servo-read-loop', 'servo-commands', 'servo-reporter'} & names


def test_round2_22_servo_runtime_a_command_and_a_stop_take_the_bus_through_the_schedule(bus):
    dev, wire, runtime, _, cycles = bus
    wait_for(lambda: cycles, 20, what='a read cycle')
    mark = wire.mark()
    runtime.command([(2, 3000, 0)])
    wait_for(lambda: any(r.instruction == Instruction.SYNC_WRITE
                         for r in wire.commands(mark)), 10, what='the SYNC WRITE on the wire')
    answer = runtime.emergency_stop(timeout=10)
    assert answer is not None and answer.ok
    with dev.runner.locked():
        assert not any(dev.sim.servo(i).torque_enabled for i in (1, 2, 3))


def test_round2_22_servo_runtime_a_held_bus_reads_nothing_and_takes_a_transaction(bus):
    _, wire, runtime, reads, cycles = bus
    wait_for(lambda: cycles, 20, what='a read cycle')
    with runtime.held(timeout=10) as granted:
        assert granted
        before = len(reads)
        reply = runtime.transact(proto.encode_ping(3), 3, 0, retries=2, timeout=10)
        assert reply is not None and reply.servo_id == 3
        time.sleep(0.1)  # ten cycles' worth of time: not one READ while held
        assert len(reads) == before
    wait_for(lambda: len(reads) > before, 10, what='reads again after the release')


def test_round2_22_servo_runtime_torque_off_is_the_last_frame_of_its_stop(bus):
    dev, wire, runtime, _, cycles = bus
    wait_for(lambda: cycles, 20, what='a read cycle')
    runtime.command([(1, 100, 0)])
    runtime.stop()
    assert runtime.last_frame == TORQUE_OFF_ALL
    # Written last; the virtual bus takes it after its wire time (and the device thread's).
    wait_for(lambda: wire.requests() and wire.requests()[-1].raw == TORQUE_OFF_ALL, 20,
             what='torque off on the bus')
    count = len(wire.requests())
    runtime.command([(1, 200, 0)])  # after the stop: nothing more
    assert runtime.last_frame == TORQUE_OFF_ALL
    assert len(wire.requests()) == count


def test_round2_22_servo_runtime_reads_again_after_an_unplug(bus):
    dev, _, runtime, reads, cycles = bus
    wait_for(lambda: cycles, 20, what='a read cycle')
    dev.runner.unplug()
    wait_for(lambda: not runtime.port_open, 20, what='the port closed')
    # The port's flag drops before the reader thread steps LinkDown: wait for the judgement.
    wait_for(lambda: not any(s.online for s in runtime.schedule.servos), 20,
             what='every servo offline')
    dev.runner.replug()
    wait_for(lambda: runtime.port_open, 20, what='the port open again')
    mark = len(reads)
    wait_for(lambda: {r.servo_id for r in reads[mark:] if r.reply is not None} == {1, 2, 3},
             20, what='every servo read again')


def test_round2_22_servo_runtime_a_stop_goes_ahead_of_a_command_flood(bus):
    _, wire, runtime, _, cycles = bus
    wait_for(lambda: cycles, 20, what='a read cycle')
    mark = wire.mark()
    for k in range(50):
        runtime.command([(i, 1000 + k, 0) for i in (1, 2, 3)])
    answer = runtime.emergency_stop(timeout=10)
    assert answer is not None and answer.ok

    def stops() -> list:
        return [k for k, r in enumerate(wire.commands(mark))
                if r.instruction == Instruction.WRITE and r.servo_id == proto.BROADCAST_ID]
    stop = wait_for(stops, 10, what='the torque off on the wire')
    # What of the flood was still queued was dropped by the stop: none of it follows it.
    time.sleep(0.1)
    after = wire.commands(mark)[stop[0] + 1:]
    assert not [r for r in after if r.instruction == Instruction.SYNC_WRITE]
