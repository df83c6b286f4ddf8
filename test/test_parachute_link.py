"""DPS-S link on a real pty: matching, concurrency, unsolicited frames, black box."""

import json
import os
import select
import threading
import time

import pytest

from dps_parachute_ros import protocol as p
from dps_parachute_ros.blackbox import BlackBox
from dps_parachute_ros.link import LinkTimeout, ParachuteLink, RECORDS_QUIET_S
from dps_parachute_ros.simulation import VirtualParachute
from dps_parachute_ros.virtual_node import create_runner
from support import ask_again
from uav_serial_common.process import wait_for, wait_scale


@pytest.fixture
def rig(tmp_path):
    sim = VirtualParachute(now=time.monotonic())
    runner = create_runner(sim, str(tmp_path / 'vpara'), baud=115200).start()
    wire = []
    runner.add_tap(lambda d, data, t: wire.append((d, data)))
    unsolicited = []
    box = BlackBox(str(tmp_path / 'bb'))
    link = ParachuteLink(runner.path, 115200, unsolicited.append, blackbox=box)
    link.start()
    assert link.serial.wait_port_open(5 * wait_scale())
    yield sim, runner, link, unsolicited, wire, box
    link.stop()
    runner.stop()
    box.close()


def test_typed_request_and_reply(rig):
    sim, runner, link, _, _, _ = rig
    assert link.request(p.encode_attitude_threshold_query()).degrees == 60
    assert link.request(p.encode_boot_count_query()).count == 1
    assert isinstance(link.request(p.encode_status_query()), p.Status)


def test_cell_voltage_coded_0x35_is_a_voltage_not_a_record(rig):
    sim, runner, link, _, _, _ = rig
    with runner.locked():
        sim.set_external_power(False)
        sim.cell_voltage_v = 3.8
    reply = link.request(p.encode_cell_voltage_query())
    assert isinstance(reply, p.CellVoltage) and reply.code == 0x35
    assert reply.volts == pytest.approx(3.8)


def test_trigger_records_are_collected(rig):
    sim, runner, link, _, _, _ = rig
    link.request(p.encode_arm(True))
    assert link.request(p.encode_deploy()).success
    # An answer cut short (the module's frames more than 0.2 s apart: a stalled host, campaign
    # of 2026-11-27) says so (`complete` False); a caller asks again.
    records, _ = ask_again(link.query_records, lambda r: not r.complete)
    assert len(records) == 8 and records.complete
    assert records[0].serial_trigger and all(r.is_empty for r in records[1:])


def test_unsolicited_frames_go_to_the_handler(rig):
    sim, runner, link, unsolicited, _, _ = rig
    link.request(p.encode_streaming(True))
    wait_for(lambda: any(isinstance(m, p.Status) for m in unsolicited), 3, what='stream frame')
    with runner.locked():
        sim.power_cycle()
    wait_for(lambda: any(isinstance(m, p.Heartbeat) for m in unsolicited), 3,
             what='power-up heartbeat')


def test_trigger_request_reaches_the_handler_with_either_header(rig):
    sim, runner, link, unsolicited, _, _ = rig
    for header in (p.MODULE_HEADER, p.HOST_HEADER):
        runner.inject_garbage(p.encode_trigger_request(header))
        wait_for(lambda: any(isinstance(m, p.TriggerRequest) and m.header == header
                             for m in unsolicited), 3, what='trigger request')


def test_a_deploy_does_not_wait_behind_a_timing_out_request(rig):
    sim, runner, link, _, _, _ = rig
    link.request(p.encode_arm(True))
    runner.faults.drop_next = 1
    errors = []

    def slow():
        try:
            link.request(p.encode_light_level_query(), timeout=1.0)
        except LinkTimeout as exc:
            errors.append(exc)

    thread = threading.Thread(target=slow)
    thread.start()
    time.sleep(0.05)  # the light query is now waiting for its (dropped) reply
    start = time.monotonic()
    assert link.request(p.encode_deploy()).success
    fast = time.monotonic() - start
    thread.join()
    assert errors, 'the light query should have timed out'
    assert fast < 0.5  # far below the 1 s the light query waits


def test_timeout_after_retries(rig):
    sim, runner, link, _, wire, _ = rig
    runner.faults.drop_next = 2
    before = sum(1 for d, data in wire if d == 'rx')
    with pytest.raises(LinkTimeout):
        link.request(p.encode_boot_count_query(), timeout=0.2, retries=1)
    wait_for(lambda: sum(1 for d, _ in wire if d == 'rx') - before == 2, 2,
             what='exactly two attempts on the wire')
    assert link.timeouts == 1


def test_blackbox_records_frames_both_ways(rig):
    sim, runner, link, _, _, box = rig
    link.request(p.encode_boot_count_query())
    assert box.sync()
    lines = [json.loads(line) for line in open(box.path)]
    frames = [(r['dir'], r['hex']) for r in lines if r['kind'] == 'frame']
    assert ('tx', '42 61 23 01 00 24') in frames
    assert ('rx', '41 75 23 01 01 25') in frames
    assert all('t' in r and 'mono' in r for r in lines)


def test_blackbox_one_file_per_run_in_an_expanded_directory(tmp_path, monkeypatch):
    monkeypatch.setenv('HOME', str(tmp_path))
    first = BlackBox('~/bb/nested')
    first.record('state', armed=True)
    first.close()
    second = BlackBox('~/bb/nested')
    second.record('decision', what='x')
    assert second.sync()
    assert os.path.dirname(first.path) == str(tmp_path / 'bb' / 'nested')
    files = sorted(os.listdir(tmp_path / 'bb' / 'nested'))
    assert len(files) == 2
    second.close()
    assert json.loads(open(first.path).readline())['armed'] is True


def test_issue22_5_records_end_on_a_gap_the_reader_saw_not_on_a_late_caller_or_reader(tmp_path):
    """The records list ends on a quiet line, measured from the reader's own time of the
    last record's bytes: a reader held between frames (a loaded machine) is no quiet gap.

    The module (this test, on a raw pty) answers the records query with seven records, a
    status frame and the eighth record at once; the reader is held in the status frame's
    handler for four quiet gaps while the eighth record waits unread.
    """
    master, slave = os.openpty()
    held = threading.Event()
    release = threading.Event()

    def on_message(msg):
        if isinstance(msg, p.Status):
            held.set()
            release.wait(4 * RECORDS_QUIET_S)  # the reader is late, the line is not quiet

    link = ParachuteLink(os.ttyname(slave), 115200, on_message)
    link.start()
    try:
        assert link.serial.wait_port_open(5 * wait_scale())
        records = [p.encode_trigger_record(1, k, p.SOURCE_SERIAL, 60, 5, 30, True, False, 20,
                                           180) for k in range(1, 9)]
        answer = b''.join(records[:7]) + p.encode_status_frame(3, 10, True, True) + records[7]
        got = []
        query = threading.Thread(target=lambda: got.append(link.query_records()))
        query.start()
        os.set_blocking(master, True)
        asked = b''
        while p.encode_trigger_records_query() not in asked:
            asked += os.read(master, 64)
        os.write(master, answer)
        assert held.wait(5 * wait_scale()), 'the status frame never reached its handler'
        query.join(4 * RECORDS_QUIET_S)  # a list ended behind the reader's back ends now
        release.set()
        query.join(10)
        assert not query.is_alive()
        assert [r.uptime_s for r in got[0]] == list(range(1, 9))
    finally:
        release.set()
        link.stop()
        os.close(master)
        os.close(slave)


def records_module(master, stop, answer):
    """A module on the pty's `master` side: `answer(k, records)` for the k-th records query.

    The eight records of answer k have uptime k. Not started; it ends when `stop` is set.
    """
    def run():
        asked, answers = b'', 0
        while not stop.is_set():
            if not select.select([master], [], [], 0.05)[0]:
                continue  # (no blocking read: the test joins this thread before closing)
            asked += os.read(master, 64)
            while p.encode_trigger_records_query() in asked:
                asked = asked.split(p.encode_trigger_records_query(), 1)[1]
                answers += 1
                answer(answers, [p.encode_trigger_record(1, answers, p.SOURCE_SERIAL, 60, 5, 30,
                                                         True, False, 20, 180)
                                 for _ in range(8)])
    return threading.Thread(target=run, daemon=True)


def close_module(stop, device, link, master, slave):
    """Stop the module thread and the link, and close the pty."""
    stop.set()
    if device.is_alive():
        device.join(5.0)
    link.stop()
    os.close(master)
    os.close(slave)


def test_an_answer_cut_by_a_reboot_leaves_no_tail_for_the_next_query_to_wait_for(tmp_path):
    """The module reboots while it answers a records query (a campaign run: the driver's query
    met the test's reboot on a loaded host). A power-up does not go on with the answer, so the
    next query (the re-read after the reboot) must not wait a timeout for its tail: the driver
    stayed "not initialized" for 1 s after the reboot.

    The module (this test, on a raw pty) answers the first query with three records and its
    power-up heartbeat, the second with eight records; the listener, as the session does, tells
    the link of the reboot.
    """
    master, slave = os.openpty()
    heartbeats = []

    def on_message(msg):
        if isinstance(msg, p.Heartbeat):
            heartbeats.append(msg)
            link.void_answers()
    link = ParachuteLink(os.ttyname(slave), 115200, on_message)
    link.start()
    os.set_blocking(master, True)
    stop = threading.Event()

    def answer(k, records):
        if k == 1:
            os.write(master, b''.join(records[:3]) + p.encode_module_heartbeat())
        else:
            os.write(master, b''.join(records))
    device = records_module(master, stop, answer)
    answers = []
    try:
        assert link.serial.wait_port_open(5 * wait_scale())
        device.start()
        # A long timeout: a tail left owed would hold the next query that long.
        first = link.query_records(timeout=60.0)
        assert [r.uptime_s for r in first] == [1, 1, 1] and not first.complete
        assert len(heartbeats) == 1
        asker = threading.Thread(target=lambda: answers.append(link.query_records()),
                                 daemon=True)
        asker.start()
        wait_for(lambda: answers, 10.0, what='the second answer, not held for a tail')
        assert [r.uptime_s for r in answers[0]] == [2] * 8 and answers[0].complete
    finally:
        close_module(stop, device, link, master, slave)


def test_issue22_a_record_query_lets_the_tail_of_an_answer_cut_short_pass_first(tmp_path):
    """An answer paused past the quiet gap ends the list early (cut short: not complete); its
    rest comes later. A query right after it waited for nothing: it began its own list with
    that tail, and with eight frames of two answers called it complete. It lets the tail pass
    first, so each list holds only its own answer's records.

    The module (this test, on a raw pty) answers each query with three records, a pause of
    twice the quiet gap, then five more; the records of answer k have uptime k.
    """
    master, slave = os.openpty()
    link = ParachuteLink(os.ttyname(slave), 115200, lambda msg: None)
    link.start()
    os.set_blocking(master, True)
    stop = threading.Event()

    def answer(k, records):
        os.write(master, b''.join(records[:3]))
        if not stop.wait(2 * RECORDS_QUIET_S):
            os.write(master, b''.join(records[3:]))
    device = records_module(master, stop, answer)
    try:
        assert link.serial.wait_port_open(5 * wait_scale())
        device.start()
        first = link.query_records()
        second = link.query_records()
        assert [r.uptime_s for r in first] == [1, 1, 1] and not first.complete
        assert {r.uptime_s for r in second} == {2}, [r.uptime_s for r in second]
    finally:
        close_module(stop, device, link, master, slave)
