"""parachute_node in the test's process against the virtual module on a pty (one node for it).

Tests that need a fresh module power-cycle it and wait for the node to re-initialize it; what
reaches the wire is seen through a tap on the runner.
"""

import json
import math
import time

from diagnostic_msgs.msg import DiagnosticStatus
from dps_parachute_ros import protocol as p
from parachute_rig import Rig
import pytest
from sensor_msgs.msg import BatteryState
from std_srvs.srv import SetBool, Trigger
from uav_serial_common.process import wait_for
from uav_serial_drivers.msg import TriggerEvent, TriggerRequest
from uav_serial_drivers.srv import (Confirmed, Deploy, GetParachuteConfig, GetTriggerRecords,
                                    SetAutoTriggers, SetThresholds)

DEPLOY_FRAME = bytes.fromhex('42 61 11 02 01 14')
CONFIRM_FRAME = bytes.fromhex('42 61 39 a5 01 df')


@pytest.fixture(scope='module')
def rig(tmp_path_factory, request):
    failed_before = request.session.testsfailed
    rig = Rig(tmp_path_factory.mktemp('parachute'), inproc=True)
    try:
        rig.wait_ready()
        yield rig
    finally:
        rig.close(request.session.testsfailed > failed_before)


@pytest.fixture(autouse=True)
def node_output_on_failure(request, rig):
    """Show the node's log since this test started when it fails."""
    start = len(rig.proc.output())
    yield
    report = getattr(request.node, 'rep_call', None)
    if report is not None and report.failed:
        print(f'--- parachute_node output during the test ---\n{rig.proc.output()[start:]}')


# ---------------------------------------------------------------------------------------------

def test_online_streaming_status_and_desired_settings_applied(rig):
    msg = rig.status.wait(lambda m: m.online and m.streaming and not math.isnan(m.tilt_deg),
                          5, what='a stream frame')
    assert msg.header.frame_id == 'parachute' and msg.accel_g == pytest.approx(1.0)
    config = rig.config.last
    assert config.attitude_threshold_deg == 70
    assert config.freefall_threshold_g == pytest.approx(0.4)
    assert config.freefall_time_s == pytest.approx(0.5)
    assert config.light_threshold_v == pytest.approx(1.5)
    assert config.auto_triggers_known and config.baud_rate == 115200
    with rig.model():
        assert (rig.sim.attitude_threshold_deg, rig.sim.freefall_threshold_raw,
                rig.sim.freefall_time_raw, rig.sim.light_threshold_raw) == (70, 4, 50, 15)


def test_battery_state_follows_rep_conventions(rig):
    msg = rig.battery.wait(lambda m: m.present and not math.isnan(m.voltage), 5,
                           what='battery state')
    for field in ('current', 'charge', 'capacity', 'design_capacity', 'percentage',
                  'temperature'):
        assert math.isnan(getattr(msg, field)), field
    assert msg.power_supply_status == BatteryState.POWER_SUPPLY_STATUS_CHARGING
    assert list(msg.cell_voltage) == [pytest.approx(msg.voltage)]
    assert msg.voltage == pytest.approx(4.2)


def test_arm_and_lock_round_trip(rig):
    mark = rig.wire.mark()
    assert 'armed' in rig.arm().message
    with rig.model():
        assert rig.sim.armed
    rig.status.wait(lambda m: m.armed, 3, what='armed status', start=len(rig.status) - 1)
    reply = rig.call(SetBool, 'arm', SetBool.Request(data=False))
    assert reply.success, reply.message
    with rig.model():
        assert not rig.sim.armed
    sent = rig.wire.since(mark)
    assert p.encode_arm(True) in sent and p.encode_arm(False) in sent
    assert p.encode_armed_query() in sent  # P7: verified by a query


def test_deploy_refusals_send_nothing(rig):
    rig.call(SetBool, 'arm', SetBool.Request(data=False))
    mark = rig.wire.mark()
    for token in ('deploy', 'DEPLOY ', ''):
        reply = rig.call(Deploy, 'deploy', Deploy.Request(confirm=token, arm_if_locked=True))
        assert not reply.success and 'DEPLOY' in reply.message
    reply = rig.call(Deploy, 'deploy', Deploy.Request(confirm='DEPLOY', arm_if_locked=False))
    assert not reply.success and 'locked' in reply.message
    reply = rig.call(Confirmed, 'shutdown_module', Confirmed.Request(confirm='shutdown'))
    assert not reply.success and 'SHUTDOWN' in reply.message
    # A probe request after the refusals: everything the node sent up to it is on the tap.
    rig.call(GetParachuteConfig, 'get_config')
    for code in (p.CMD_DEPLOY, p.CMD_ARM, p.CMD_SHUTDOWN):
        assert rig.wire.since(mark, code) == [], hex(code)
    with rig.model():
        assert not rig.sim.triggered and rig.sim.powered


def test_deploy_success_event_and_black_box(rig):
    rig.fresh()
    rig.arm()
    mark = rig.wire.mark()
    events_before = len(rig.events)
    reply = rig.call(Deploy, 'deploy', Deploy.Request(confirm='DEPLOY'))
    assert reply.success, reply.message
    assert reply.latency_ms > 0
    assert rig.wire.since(mark, p.CMD_DEPLOY) == [DEPLOY_FRAME]
    event = rig.events.wait(lambda m: True, 5, start=events_before, what='trigger event')
    assert event.source == TriggerEvent.SOURCE_SERIAL and event.source_name == 'serial'
    assert event.via == TriggerEvent.VIA_DEPLOY_ACK
    with rig.model():
        assert rig.sim.triggered and rig.sim.deployments == 1
    rig.status.wait(lambda m: m.triggered and not m.armed, 3, what='triggered status')
    rig.triggered.wait(lambda m: m.data, 3, what='~/triggered true')
    diag = rig.diagnostics.wait(lambda m: any(
        s.name == '/parachute: state' and s.level == DiagnosticStatus.ERROR for s in m.status),
        5, what='ERROR diagnostic while triggered')
    assert diag
    # The black box holds the frames both ways and the decision, synced before the reply.
    box = next((rig.tmp / 'bb').glob('parachute-*.jsonl'))
    records = [json.loads(line) for line in box.read_text().splitlines() if line]
    frames = {(r['dir'], r['hex']) for r in records if r['kind'] == 'frame'}
    assert ('tx', '42 61 11 02 01 14') in frames and ('rx', '41 75 11 01 01 13') in frames
    assert any(r['kind'] == 'decision' and r.get('what') == 'deploy acknowledged'
               for r in records)
    # The decision to send is recorded before the deploy frame itself.
    sending = next(i for i, r in enumerate(records) if r.get('what', '').startswith(
        'deploy: sending'))
    sent = next(i for i, r in enumerate(records)
                if r['kind'] == 'frame' and r['hex'] == '42 61 11 02 01 14')
    assert sending < sent
    # One event per deployment: the triggered flag and the new record add none.
    records_reply = rig.call(GetTriggerRecords, 'get_trigger_records')
    assert records_reply.success and records_reply.records[-1].source == 1
    assert len(rig.events) == events_before + 1


def test_unacknowledged_deploys_stop_before_the_third_frame_until_the_module_reboots(rig):
    rig.fresh()
    rig.arm()
    with rig.model():
        rig.sim.lost_commands = {p.CMD_DEPLOY}
        before = (rig.sim.deployments, rig.sim.failed_attempts_total)
    try:
        mark = rig.wire.mark()
        reply = rig.call(Deploy, 'deploy', Deploy.Request(confirm='DEPLOY'))
        assert not reply.success and 'NOT acknowledged after 2 attempts' in reply.message
        assert rig.wire.since(mark, p.CMD_DEPLOY) == [DEPLOY_FRAME] * 2
        # A second call must not send a third frame (P11: the module's protection mode).
        mark = rig.wire.mark()
        reply = rig.call(Deploy, 'deploy', Deploy.Request(confirm='DEPLOY'))
        assert not reply.success and '2 deploy frames in a row went unacknowledged' in \
            reply.message and 'reboot' in reply.message
        assert rig.wire.since(mark, p.CMD_DEPLOY) == []
    finally:
        with rig.model():
            rig.sim.lost_commands = set()
    with rig.model():
        assert (rig.sim.deployments, rig.sim.failed_attempts_total) == before
    # A module reboot clears the count: deploying works again.
    rig.fresh()
    rig.arm()
    reply = rig.call(Deploy, 'deploy', Deploy.Request(confirm='DEPLOY'))
    assert reply.success, reply.message


def test_deploy_arms_first_when_asked(rig):
    rig.fresh()
    mark = rig.wire.mark()
    reply = rig.call(Deploy, 'deploy', Deploy.Request(confirm='DEPLOY', arm_if_locked=True))
    assert reply.success, reply.message
    sent = [raw[2] for raw in rig.wire.since(mark) if raw[2] in (p.CMD_ARM, p.CMD_DEPLOY)]
    assert sent == [p.CMD_ARM, p.CMD_DEPLOY]


def provoke_trigger_request(rig):
    """Arm a module on external power and tilt it past its threshold: it asks the host."""
    rig.fresh()
    rig.arm()
    start = len(rig.requests)
    mark = rig.wire.mark()
    with rig.model():
        requested = rig.sim.requests_sent
        rig.sim.set_tilt(85)
        assert rig.sim.requests_sent == requested + 1
    return start, mark


@pytest.mark.parametrize('policy', ['confirm', 'deny'])
def test_trigger_request_confirm_and_deny(rig, policy):
    assert rig.set_param('trigger_request_policy', policy).successful
    try:
        start, mark = provoke_trigger_request(rig)
        msg = rig.requests.wait(lambda m: True, 3, start=start, what='trigger request message')
        assert msg.policy == policy
        if policy == 'confirm':
            assert msg.decision == TriggerRequest.CONFIRMED and msg.decision_name == 'confirmed'
            assert msg.latency_ms >= 0
            wait_for(lambda: CONFIRM_FRAME in rig.wire.since(mark), 2, what='confirmation')
            # Learnt from the status flag, or (a re-initialization after the rig's power cycle
            # still running on a loaded host) from the new record its end reads: both true.
            event = rig.events.wait(lambda m: m.via in (TriggerEvent.VIA_STATUS,
                                                        TriggerEvent.VIA_RECORD) and
                                    m.source == TriggerEvent.SOURCE_ATTITUDE, 5,
                                    what='attitude trigger event')
            assert event.record_known and event.record.source_name == 'attitude'
            with rig.model():
                assert rig.sim.triggered
        else:
            assert msg.decision == TriggerRequest.DENIED and math.isnan(msg.latency_ms)
            wait_for(lambda: rig.sim.requests_expired >= 1, 3, what='request window to end')
            assert CONFIRM_FRAME not in rig.wire.since(mark)
            with rig.model():
                assert not rig.sim.triggered
    finally:
        assert rig.set_param('trigger_request_policy', 'confirm').successful


@pytest.mark.parametrize('answer', [True, False, None])
def test_trigger_request_deferred(rig, answer):
    assert rig.set_param('trigger_request_policy', 'defer').successful
    if answer is not None:
        # The answer is a ROS call from this process: the longest wait the module's 1-s window
        # leaves, so that a loaded host's round trip still makes it (0.5 s: the rig's).
        assert rig.set_param('defer_timeout_s', 0.95).successful
    try:
        start, mark = provoke_trigger_request(rig)
        if answer is not None:
            # Answer as soon as the node holds the request (the call fails until it does).
            wait_for(lambda: rig.call(SetBool, 'answer_trigger_request',
                                      SetBool.Request(data=answer)).success, 3,
                     interval=0.005, what='the deferred request to be answerable')
        msg = rig.requests.wait(lambda m: True, 3, start=start, what='trigger request message')
        expected = {True: TriggerRequest.CONFIRMED, False: TriggerRequest.DENIED,
                    None: TriggerRequest.TIMED_OUT}[answer]
        assert msg.decision == expected, msg
        if answer:
            wait_for(lambda: rig.sim.triggered, 3, what='the module to deploy')
            assert CONFIRM_FRAME in rig.wire.since(mark)
        else:
            wait_for(lambda: rig.sim.requests_expired >= 1, 3, what='request window to end')
            assert CONFIRM_FRAME not in rig.wire.since(mark)
            assert not rig.sim.triggered
    finally:
        assert rig.set_param('trigger_request_policy', 'confirm').successful
        assert rig.set_param('defer_timeout_s', 0.5).successful


def test_policy_parameter_is_validated(rig):
    result = rig.set_param('trigger_request_policy', 'maybe')
    assert not result.successful and 'confirm' in result.reason
    result = rig.set_param('defer_timeout_s', 1.5)
    assert not result.successful


def test_reboot_reapplies_desired_settings(rig):
    with rig.model():
        rig.sim.attitude_threshold_deg = 45
        rig.sim.freefall_threshold_raw = 7
        rig.sim.freefall_time_raw = 200
        rig.sim.light_threshold_raw = 30
    rig.fresh()
    with rig.model():
        assert (rig.sim.attitude_threshold_deg, rig.sim.freefall_threshold_raw,
                rig.sim.freefall_time_raw, rig.sim.light_threshold_raw) == (70, 4, 50, 15)


def test_parameter_set_is_written_or_refused(rig):
    mark = rig.wire.mark()
    result = rig.set_param('attitude_threshold_deg', 75)
    assert result.successful, result.reason
    with rig.model():
        assert rig.sim.attitude_threshold_deg == 75
    assert p.encode_attitude_threshold_set(75) in rig.wire.since(mark)
    try:
        mark = rig.wire.mark()
        for bad in (95, 5):
            result = rig.set_param('attitude_threshold_deg', bad)
            assert not result.successful
        result = rig.set_param('freefall_threshold_g', 3.0)
        assert not result.successful
        rig.call(GetParachuteConfig, 'get_config')
        assert [raw for raw in rig.wire.since(mark) if raw[3] == p.CTRL_SET] == []
        with rig.model():
            assert rig.sim.attitude_threshold_deg == 75
    finally:
        assert rig.set_param('attitude_threshold_deg', 70).successful


def test_set_thresholds_refuses_out_of_range_before_sending(rig):
    nan = float('nan')
    mark = rig.wire.mark()
    for request in (SetThresholds.Request(attitude_deg=nan, freefall_g=2.0,
                                          freefall_time_s=nan, light_threshold_v=nan),
                    SetThresholds.Request(attitude_deg=100.0, freefall_g=nan,
                                          freefall_time_s=nan, light_threshold_v=nan),
                    SetThresholds.Request(attitude_deg=nan, freefall_g=nan,
                                          freefall_time_s=9.0, light_threshold_v=nan)):
        reply = rig.call(SetThresholds, 'set_thresholds', request)
        assert not reply.success and 'range' in reply.message
    rig.call(GetParachuteConfig, 'get_config')
    assert [raw for raw in rig.wire.since(mark) if raw[3] == p.CTRL_SET] == []
    reply = rig.call(SetThresholds, 'set_thresholds', SetThresholds.Request(
        attitude_deg=nan, freefall_g=nan, freefall_time_s=nan, light_threshold_v=1.5))
    assert reply.success and reply.config.light_threshold_v == pytest.approx(1.5)


def test_auto_triggers_streaming_zero_and_config(rig):
    reply = rig.call(SetAutoTriggers, 'set_auto_triggers',
                     SetAutoTriggers.Request(attitude_enabled=False, freefall_enabled=True))
    assert reply.success, reply.message
    assert not reply.config.attitude_trigger_enabled and reply.config.freefall_trigger_enabled
    with rig.model():
        assert not rig.sim.attitude_trigger_enabled and rig.sim.freefall_trigger_enabled
    reply = rig.call(SetAutoTriggers, 'set_auto_triggers',
                     SetAutoTriggers.Request(attitude_enabled=True, freefall_enabled=True))
    assert reply.success and reply.config.attitude_trigger_enabled
    assert rig.call(Trigger, 'zero_sensor').success
    reply = rig.call(GetParachuteConfig, 'get_config')
    assert reply.success and reply.config.valid and reply.config.boot_count == rig.sim.boot_count
    assert rig.call(SetBool, 'set_streaming', SetBool.Request(data=False)).success
    rig.status.wait(lambda m: m.online and not m.streaming, 3, what='polled status')
    assert rig.call(SetBool, 'set_streaming', SetBool.Request(data=True)).success
    rig.status.wait(lambda m: m.online and m.streaming, 3, what='streaming status')


def test_garbage_on_the_line_does_not_disturb(rig):
    start = len(rig.status)
    for _ in range(5):
        rig.runner.inject_garbage(bytes.fromhex('41 75 32 ff 00 42 61 13 00 41'))
        time.sleep(0.05)
    rig.status.wait(lambda m: True, 3, start=len(rig.status), what='status after noise')
    assert all(m.online for m in rig.status.messages[start:])
    assert rig.call(GetParachuteConfig, 'get_config').success


def test_free_fall_on_battery_deploys_and_leaves_a_record(rig):
    rig.fresh(external_power=False)
    rig.arm()
    start = len(rig.events)
    with rig.model():
        rig.sim.start_free_fall(0.8)  # longer than the desired free-fall time of 0.5 s
    event = rig.events.wait(lambda m: m.source & TriggerEvent.SOURCE_FREEFALL, 5, start=start,
                            what='free-fall trigger event')
    assert event.via == TriggerEvent.VIA_STATUS and event.record_known
    assert event.record.freefall_time_s == pytest.approx(0.5)
    reply = rig.call(GetTriggerRecords, 'get_trigger_records')
    assert reply.success
    last = reply.records[-1]
    assert last.source_name == 'freefall' and not last.charging and len(last.raw) == 16
    with rig.model():
        rig.sim.set_external_power(True)


def test_a_silent_module_goes_offline_and_comes_back(rig):
    start = len(rig.status)
    with rig.model():
        rig.sim.power_off()
    rig.status.wait(lambda m: not m.online, 3, start=start, what='offline status')
    # A desired setting cannot be confirmed by a module that does not answer: refused.
    mark = rig.wire.mark()
    result = rig.set_param('attitude_threshold_deg', 75)
    assert not result.successful and 'offline' in result.reason, result.reason
    assert p.encode_attitude_threshold_set(75) not in rig.wire.since(mark)
    start = len(rig.status)
    with rig.model():
        rig.sim.power_on()
    rig.status.wait(lambda m: m.online and m.streaming, 10, start=start,
                    what='online and streaming again')
    with rig.model():
        assert rig.sim.attitude_threshold_deg == 70


def test_unplug_goes_offline_and_replug_recovers(rig):
    start = len(rig.status)
    diag_start = len(rig.diagnostics)
    rig.runner.unplug()
    rig.status.wait(lambda m: not m.online, 2, start=start, what='offline status')
    rig.diagnostics.wait(lambda m: any(
        s.name == '/parachute: link' and s.level == DiagnosticStatus.ERROR for s in m.status),
        2, start=diag_start, what='link ERROR diagnostic')
    reply = rig.call(Deploy, 'deploy', Deploy.Request(confirm='DEPLOY', arm_if_locked=True))
    assert not reply.success and 'offline' in reply.message
    start = len(rig.status)
    rig.runner.replug()
    rig.status.wait(lambda m: m.online and m.streaming, 10, start=start,
                    what='online again after replug')
