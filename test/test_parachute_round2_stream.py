"""Round two, items 2 and 3 of the parachute: a dead status stream, and what a deploy knew.

The device core (`ParachuteSession`) against the virtual module on a pty, with the fake clock of
``test_parachute_core`` (its rig): the time-based rules move only when a test moves the clock;
the last test shows item 2 over ROS as a user sees it.
Item 2: a module that answers queries is online and can be deployed, whatever single fault
stops a part of its output (the stream, the heartbeat, an auxiliary query, a reply of the
re-read after a reboot). Item 3: a deploy whose module was seen triggered is a deployment, and
the source of a deployment reported as unknown is amended once the trigger record is read.
"""

from __future__ import annotations

from dataclasses import replace

from diagnostic_msgs.msg import DiagnosticStatus
from dps_parachute_ros import protocol as p
from parachute_rig import NODE, Rig as NodeRig
import pytest
from std_srvs.srv import Trigger
from test_parachute_core import in_thread, Rig
from uav_serial_common.process import wait_for
from uav_serial_drivers.msg import TriggerEvent
from uav_serial_drivers.srv import Deploy


@pytest.fixture
def rig(tmp_path):
    rig = Rig(tmp_path, attitude_threshold_deg=70)
    yield rig
    rig.close()


def quiet(rig, timeout=5.0):
    """Wait until no request of the session waits for a reply (before the clock jumps)."""
    wait_for(lambda: not rig.session._online.requests_in_flight, timeout,
             what='no request in flight')


def kill_stream(rig, tilt=50):
    """The module stops streaming and ignores 0x13 from now on; it answers everything else."""
    with rig.model():
        rig.sim.set_tilt(tilt)
        rig.sim.stream_dead = True


# -- item 2: a dead stream ---------------------------------------------------------------------

def test_round2_2_a_dead_stream_is_polled_and_the_module_stays_online_and_deployable(rig):
    rig.arm()
    kill_stream(rig)
    # Less than offline_timeout_s of silence: the driver asks, the module answers.
    rig.clock.advance(0.6)
    wait_for(lambda: rig.snap.stream_problem, 5, what='the stream judged dead')
    snap = rig.snap
    assert snap.online and not snap.streaming, snap
    assert 'polling the status' in snap.stream_problem
    assert snap.tilt_deg == 50  # read by the poll, not the 0.0 of a stream that stopped
    quiet(rig)
    for _ in range(2):  # never offline while it answers the polls (and ignores stream on)
        rig.clock.advance(1.1)
        rig.session.tick()
        assert rig.snap.online, rig.snap.offline_reason
        quiet(rig)
    check = rig.session.preflight_check()
    assert not check.ok and 'FAIL status stream: status stream dead' in check.message, \
        check.message
    assert rig.session.arm(True).ok
    result = rig.session.deploy('DEPLOY')
    assert result.ok and 'acknowledged' in result.message, result.message
    with rig.model():
        assert rig.sim.triggered


def test_round2_2_a_module_that_boots_with_a_dead_stream_is_initialized_and_deployed(rig):
    with rig.model():
        rig.sim.stream_dead = True
    mark = rig.wire.mark()
    rig.fresh()  # re-read although 0x13 goes unanswered
    wait_for(lambda: rig.snap.stream_problem, 5, what='the fallback to polling')
    assert rig.snap.online and not rig.snap.streaming
    assert p.encode_streaming(True) in rig.wire.since(mark)
    result = rig.session.deploy('DEPLOY', True)
    assert result.ok, result.message
    with rig.model():
        assert rig.sim.triggered and rig.sim.deployments == 1


def test_round2_2_a_stream_that_comes_back_is_used_again(rig):
    kill_stream(rig)
    rig.clock.advance(0.6)
    wait_for(lambda: rig.snap.stream_problem, 5, what='the stream judged dead')
    quiet(rig)
    with rig.model():
        rig.sim.stream_dead = False
    mark = rig.wire.mark()
    rig.clock.advance(2.1)  # the first attempt to restore it is due
    wait_for(lambda: rig.snap.streaming and not rig.snap.stream_problem, 5,
             what='the stream restored')
    assert p.encode_streaming(True) in rig.wire.since(mark)
    assert 'OK   status stream' in rig.session.preflight_check().message


@pytest.mark.parametrize('code', [p.CMD_HEARTBEAT, p.CMD_LIGHT_LEVEL],
                         ids=['heartbeat', 'aux_query'])
def test_round2_2_a_module_silent_to_one_query_stays_online_and_deployable(tmp_path, code):
    """Stream off: a heartbeat or an auxiliary query left unanswered is no offline verdict."""
    rig = Rig(tmp_path, stream_status=False)
    try:
        with rig.model():
            rig.sim.lost_commands = {code}
        quiet(rig)
        mark = rig.wire.mark()
        rig.clock.advance(10.5)  # the heartbeat and the aux poll are due
        wait_for(lambda: rig.wire.since(mark, code), 5, what='the unanswered query sent')
        rig.clock.advance(1.1)
        rig.session.tick()
        assert rig.snap.online, rig.snap.offline_reason
        quiet(rig)
        mark = rig.wire.mark()
        rig.clock.advance(1.1)  # the next poll: the status is asked first
        wait_for(lambda: rig.wire.since(mark, p.CMD_STATUS), 5, what='the status polled')
        quiet(rig)
        rig.session.tick()
        assert rig.snap.online, rig.snap.offline_reason
        result = rig.session.deploy('DEPLOY', True)
        assert result.ok, result.message
    finally:
        rig.close()


def test_round2_2_lost_replies_in_the_reread_after_a_reboot_do_not_refuse_a_deploy(rig):
    # Both attempts of the re-initialization's first read are lost: it fails, and is tried
    # again only a second later (by the clock). The deploy reads what it needs itself.
    # (Lost by their command, not as the next two replies: a loaded host let other replies
    # take those two drops, the re-read passed, and "not fresh" came and went unseen:
    # campaign s15a, run 2.)
    mark = rig.wire.mark()
    with rig.model():
        rig.sim.lost_commands = {p.CMD_BOOT_COUNT}
    rig.power_cycle()
    wait_for(lambda: len(rig.wire.since(mark, p.CMD_BOOT_COUNT)) >= 2, 5,
             what="both attempts of the re-read's boot count query")
    with rig.model():
        rig.sim.lost_commands = set()
    assert not rig.snap.fresh and not rig.snap.initialized
    result = rig.session.deploy('DEPLOY', True)
    assert result.ok, result.message
    with rig.model():
        assert rig.sim.triggered


def test_round2_2_a_module_silent_to_the_boot_count_query_is_deployed_after_a_reboot(rig):
    # Its re-initialization fails at its first read, again and again; the deploy asks for
    # what it needs (the status: armed and triggered) and goes ahead.
    with rig.model():
        rig.sim.lost_commands = {p.CMD_BOOT_COUNT}
    rig.power_cycle()
    wait_for(lambda: not rig.snap.fresh, 2, what='the reboot heartbeat seen')
    result = rig.session.deploy('DEPLOY', True)
    assert result.ok, result.message
    with rig.model():
        assert rig.sim.triggered


def test_round2_2_a_module_silent_to_the_armed_query_is_armed_and_deployed(rig):
    with rig.model():
        rig.sim.lost_commands = {p.CMD_ARMED}  # the arm is verified by the status instead
    result = rig.session.deploy('DEPLOY', True)
    assert result.ok, result.message
    with rig.model():
        assert rig.sim.triggered


def test_round2_2_an_offline_verdict_never_refuses_a_module_that_answers(rig):
    # A stale verdict (the module answered nothing for a while, then answers again): a deploy
    # asks before it refuses.
    rig.arm()
    quiet(rig)
    with rig.model():
        rig.sim.stream_dead = True
        rig.sim.lost_commands = set(range(256))
    rig.clock.advance(1.1)
    rig.session.tick()
    wait_for(lambda: not rig.snap.online, 5, what='offline')
    with rig.model():
        rig.sim.lost_commands = set()
    result = rig.session.deploy('DEPLOY')
    assert result.ok, result.message
    with rig.model():
        assert rig.sim.triggered


# -- item 3: what a deploy knew ------------------------------------------------------------------

def test_round2_3_a_deploy_seen_triggered_before_the_link_dropped_is_a_deployment(rig):
    rig.arm()
    # The ack's wait outlasts the unplug; the ack and the records are lost, the stream is not.
    rig.session.reconfigure(replace(rig.session.config, request_timeout_s=3.0))
    with rig.model():
        rig.sim.lost_commands = {p.CMD_TRIGGER_RECORDS}
    rig.runner.faults.drop_next = 1
    done = in_thread(rig.session.deploy, 'DEPLOY')
    wait_for(lambda: rig.snap.triggered, 3, what='TRIGGERED on the status stream')
    rig.runner.unplug()
    wait_for(lambda: done, 5, what='the deploy answered')
    result = done[0]
    assert result.ok, result.message
    assert 'UNKNOWN' not in result.message and 'TRIGGERED (via status' in result.message
    assert not rig.snap.deploy_outcome_unknown
    wait_for(lambda: not rig.snap.port_open, 3, what='the port closed')
    again = rig.session.deploy('DEPLOY')
    assert again.ok and 'already deployed' in again.message and 'UNKNOWN' not in again.message
    # Told at once, with what is known: the record could not be read.
    wait_for(lambda: rig.heard.events, 5, what='the trigger event')
    first = rig.heard.events[0]
    assert first.source == 0 and not first.amends and first.deployment_id == 1
    # Back: the record is read again and the event amended, for the same deployment.
    with rig.model():
        rig.sim.lost_commands = set()
    rig.runner.replug()
    wait_for(lambda: len(rig.heard.events) == 2, 10, what='the amended event')
    amended = rig.heard.events[1]
    assert amended.amends and amended.deployment_id == first.deployment_id
    assert amended.source == p.SOURCE_SERIAL and amended.record is not None
    assert [e.amends for e in rig.heard.events] == [False, True]  # one deployment
    outcomes = [(r['outcome'], r['success']) for r in rig.deploy_outcomes()]
    assert outcomes == [('deployed', True), ('already deployed', True)]


def test_round2_3_a_record_that_comes_later_amends_the_event_while_online(rig):
    rig.arm()
    with rig.model():
        rig.sim.lost_commands = {p.CMD_TRIGGER_RECORDS}  # a module slow to keep its record
        rig.sim.trigger_pwm()  # the flight controller deploys it
    wait_for(lambda: rig.heard.events, 10, what='the trigger event')
    assert rig.heard.events[0].source == 0
    with rig.model():
        rig.sim.lost_commands = set()
    quiet(rig)
    rig.clock.advance(1.1)  # the fetch is tried again, backing off
    wait_for(lambda: len(rig.heard.events) == 2, 5, what='the amended event')
    amended = rig.heard.events[1]
    assert amended.amends and amended.source == p.SOURCE_PWM
    assert amended.deployment_id == rig.heard.events[0].deployment_id
    wait_for(lambda: rig.snap.online, 5, what='online')  # the clock jumped past the stream
    assert rig.session.get_trigger_records().ok
    assert len(rig.heard.events) == 2  # amended once


# -- over ROS: what a user sees -------------------------------------------------------------------

def test_round2_2_over_ros_a_dead_stream_is_reported_and_the_module_armed_and_deployed(tmp_path):
    rig = NodeRig(tmp_path)
    failed = True
    try:
        rig.wait_ready()
        with rig.model():
            rig.sim.set_tilt(50)
            rig.sim.stream_dead = True
        rig.status.wait(lambda m: m.online and not m.streaming and m.tilt_deg == 50, 10,
                        what='~/status: online, polled (streaming false), tilt 50')
        rig.diagnostics.wait(lambda m: any(
            s.name == f'{NODE}: link' and s.level == DiagnosticStatus.WARN and
            'status stream dead' in s.message for s in m.status), 10,
            what='link diagnostics WARN: status stream dead')
        check = rig.call(Trigger, 'preflight_check')
        assert not check.success and 'FAIL status stream' in check.message, check.message
        for _ in range(3):
            rig.arm()
        reply = rig.call(Deploy, 'deploy', Deploy.Request(confirm='DEPLOY'))
        assert reply.success, reply.message
        event = rig.events.wait(lambda m: True, 5, what='the trigger event')
        assert event.source == TriggerEvent.SOURCE_SERIAL and event.deployment_id == 1
        assert not event.amends
        failed = False
    finally:
        rig.close(failed)
