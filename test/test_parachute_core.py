"""The parachute's device core (ParachuteSession) against the virtual module: rules, in seconds.

No ROS and no processes: the real simulation (`VirtualParachute`) on a real pty through
`VirtualDeviceRunner` at baud 0, opened by pyserial through the real link, and a fake clock for
the time-based rules (the test moves it; the module keeps its own real time). Tests named
``test_safety_<n>_...`` are the rules of issue 10, item <n>.
"""

from __future__ import annotations

from dataclasses import replace
import os
import subprocess
import sys
import threading
import time

from hypothesis import assume, example, given, settings
from hypothesis import strategies as st
import pytest

from dps_parachute_ros import protocol as p
from dps_parachute_ros.blackbox import BlackBox
from dps_parachute_ros.session import HELD_RETRY_S, ParachuteSession
from dps_parachute_ros.simulation import VirtualParachute
from dps_parachute_ros.settings_rule import conditions, order, Trigger, would_deploy
from dps_parachute_ros.state import Listener, Outcome, SessionConfig, SETTINGS
from dps_parachute_ros.virtual_node import create_runner
from parachute_rig import blackbox_records, Wire
from model_runs import EXAMPLES, PHASES
from support import ask_again, FakeClock
from uav_serial_common.process import wait_for, wait_scale

DEPLOY = p.encode_deploy()
CONFIRM = p.encode_trigger_confirm()
TIMEOUT_S = 0.5
"""Request timeout of the session under test (1 s on the real module, P12): fast tests."""


class Heard(Listener):
    """Everything the session reported."""

    def __init__(self) -> None:
        self.events, self.decisions, self.logs, self.triggered = [], [], [], []

    def on_deployment(self, event):
        self.events.append(event)

    def on_trigger_request(self, decision):
        self.decisions.append(decision)

    def on_log(self, level, text):
        self.logs.append((level, text))

    def on_triggered(self, triggered):
        self.triggered.append(triggered)


class MonotonicClock(FakeClock):
    """The real monotonic clock, moved on by ``advance`` too (a rig's helpers do): for a test
    of a thread that sleeps until a deadline on the session's clock."""

    def __init__(self) -> None:
        super().__init__(0.0)  # (the offset)

    def __call__(self) -> float:
        with self._lock:
            return time.monotonic() + self.t


class Rig:
    def __init__(self, tmp, blackbox=None, baud=0, setup=None, tap=None, clock=None, **config):
        self.tmp = tmp
        self.sim = VirtualParachute(now=time.monotonic() - 1.0)
        self.sim.step(time.monotonic())  # its power-up heartbeats are in the past
        if setup is not None:
            setup(self.sim)  # the module as the driver finds it
        # Baud 0: no wire time. (Wire faults that delay replies need a baud: the pty ignores
        # a start time at baud 0.)
        self.runner = create_runner(self.sim, str(tmp / 'vpara'), baud=baud).start()
        self.wire = Wire(self.runner)
        if tap is not None:  # on the wire from the first byte the session sends
            self.runner.add_tap(lambda direction, data, t: tap(self, direction, data))
        self.clock = clock or FakeClock()
        self.heard = Heard()
        config.setdefault('blackbox_dir', str(tmp / 'bb'))
        self.config = SessionConfig(port=self.runner.path, request_timeout_s=TIMEOUT_S, **config)
        self.session = ParachuteSession(self.config, self.heard, self.clock, blackbox=blackbox)
        self.session.start()
        self.wait_ready()

    @property
    def snap(self):
        return self.session.snapshot

    def model(self):
        return self.runner.locked()

    def wait_ready(self, boot=None, timeout=5.0):
        wait_for(lambda: self.snap.online and self.snap.initialized and self.snap.fresh and
                 (boot is None or self.snap.boot_count == boot), timeout,
                 what=f'the session initialized (boot {boot})')

    def power_cycle(self):
        # A power cycle takes time: more than the 0.2 s that group power-up heartbeats (D3).
        self.clock.advance(0.5)
        with self.model():
            self.sim.power_cycle()
            return self.sim.boot_count

    def fresh(self):
        self.wait_ready(self.power_cycle())

    def arm(self):
        result = self.session.arm(True)
        assert result.ok, result.message

    def records(self):
        assert self.session.blackbox.sync(2.0)
        return blackbox_records(self.tmp / 'bb')

    def deploy_outcomes(self):
        return [r for r in self.records() if r['kind'] == 'decision' and r['what'] == 'deploy']

    def restart(self, **config):
        """Stop the session and start a new one on the same module: a driver respawn."""
        self.session.stop()
        self.config = replace(self.config, **config)
        self.heard = Heard()
        self.session = ParachuteSession(self.config, self.heard, self.clock)
        self.session.start()

    def close(self):
        self.session.stop()
        self.runner.stop()


@pytest.fixture
def rig(tmp_path):
    rig = Rig(tmp_path, attitude_threshold_deg=70)
    yield rig
    rig.close()


@pytest.fixture
def timed_rig(tmp_path):
    """A rig with wire timing (115200 baud), for tests that delay the module's replies."""
    rig = Rig(tmp_path, baud=115200)
    yield rig
    rig.close()


def in_thread(fn, *args):
    """Run fn(*args) in a thread; return a list that receives its result."""
    out = []
    thread = threading.Thread(target=lambda: out.append(fn(*args)), daemon=True)
    thread.start()
    return out


# -- deploy rules -----------------------------------------------------------------------------

def test_deploy_refusals_send_nothing(rig):
    mark = rig.wire.mark()
    for token in ('deploy', 'DEPLOY ', ''):
        result = rig.session.deploy(token, True)
        assert result.outcome is Outcome.REFUSED and "'DEPLOY'" in result.message  # the reason
    result = rig.session.deploy('DEPLOY', False)
    assert result.outcome is Outcome.REFUSED and 'locked' in result.message
    rig.runner.unplug()
    wait_for(lambda: not rig.snap.online, 3, what='offline')
    result = rig.session.deploy('DEPLOY', True)
    assert result.outcome is Outcome.REFUSED and 'offline' in result.message
    assert rig.wire.since(mark, p.CMD_DEPLOY) == [] and rig.wire.since(mark, p.CMD_ARM) == []


def test_deploy_arms_first_when_asked_and_reports_one_event(rig):
    mark = rig.wire.mark()
    result = rig.session.deploy('DEPLOY', True)
    assert result.outcome is Outcome.DONE and result.latency_ms is not None, result.message
    sent = [raw[2] for raw in rig.wire.since(mark) if raw[2] in (p.CMD_ARM, p.CMD_DEPLOY)]
    assert sent == [p.CMD_ARM, p.CMD_DEPLOY]
    wait_for(lambda: rig.heard.events, 3, what='trigger event')
    assert [(e.source, e.via) for e in rig.heard.events] == [(p.SOURCE_SERIAL, 'deploy_ack')]
    with rig.model():
        assert rig.sim.triggered and rig.sim.deployments == 1
    records = rig.records()
    assert any(r.get('what') == 'deploy acknowledged' for r in records)


def test_unacknowledged_deploys_stop_before_a_third_frame_until_a_reboot(rig):
    rig.arm()
    with rig.model():
        rig.sim.lost_commands = {p.CMD_DEPLOY}
    mark = rig.wire.mark()
    result = rig.session.deploy('DEPLOY')
    assert result.outcome is Outcome.FAILED, result.message
    assert 'did NOT deploy' in result.message  # the module said so, when asked
    result = rig.session.deploy('DEPLOY')
    assert result.outcome is Outcome.REFUSED, result.message
    assert '2 deploy frames in a row went unacknowledged' in result.message  # why
    assert rig.wire.since(mark, p.CMD_DEPLOY) == [DEPLOY] * 2
    with rig.model():
        rig.sim.lost_commands = set()
    rig.fresh()
    rig.arm()
    assert rig.session.deploy('DEPLOY').ok


# -- online / offline -------------------------------------------------------------------------

def test_online_offline_judgement(rig):
    assert rig.snap.streaming
    # The poll after the initialization is through first: a request still in flight when the
    # power goes makes the verdict the unanswered request's (next test), not the stream's.
    wait_for(lambda: rig.snap.voltage_v is not None, 5, what='the first poll answered')
    with rig.model():
        rig.sim.power_off()
    rig.session.tick()
    assert rig.snap.online  # silence shorter than offline_timeout_s is no verdict
    rig.clock.advance(1.1)
    rig.session.tick()
    assert not rig.snap.online and 'no status frame' in rig.snap.offline_reason
    rig.clock.advance(10.0)
    rig.session.tick()
    assert not rig.snap.online  # back only with a frame
    with rig.model():
        rig.sim.power_on()
    rig.wait_ready(boot=2)


def test_an_unanswered_request_makes_the_module_offline(tmp_path):
    rig = Rig(tmp_path, stream_status=False)
    try:
        with rig.model():
            rig.sim.lost_commands = set(range(256))  # hears nothing any more
        mark = rig.wire.mark()
        done = in_thread(rig.session.get_config)
        # The config's own first query: the silence of a poll (light, charging, voltage) alone
        # does not make the module offline (D2), and one may be on the wire first.
        first = next(iter(SETTINGS.values())).encode_query()
        wait_for(lambda: first in rig.wire.since(mark), 2, what='the config query on the wire')
        # A reply to a poll sent before the module went deaf may still come in after the query
        # left (a loaded host): a request counts only if no frame came after it. So time goes
        # on until one does: each step is 1.1 s of silence after every request then in flight.

        def silence_judged() -> bool:
            rig.clock.advance(1.1)
            rig.session.tick()
            return not rig.snap.online

        wait_for(silence_judged, 5, interval=0.1, what='the module judged offline')
        assert 'no reply within 1.0 s' in rig.snap.offline_reason
        wait_for(lambda: done, 5, what='get_config to give up')
        assert not done[0].ok
    finally:
        rig.close()


def test_round2_22_10_a_module_silent_since_a_request_that_gave_up_is_offline(tmp_path):
    """D2: offline once a request sent after the last frame has gone unanswered for
    offline_timeout_s. The request itself gave up sooner (request timeout 0.5 s, offline after
    1 s): the module stays silent, and stays "online" no longer than that."""
    rig = Rig(tmp_path, stream_status=False)
    try:
        with rig.model():
            rig.sim.lost_commands = set(range(256))  # hears nothing any more

        def silence_judged() -> bool:
            # (A reply to a poll sent before the module went deaf may come in after the
            # request left: then it does not count, and the next request's silence does.)
            result = rig.session.get_config()
            assert not result.ok and 'no reply' in result.message, result.message
            assert rig.snap.online  # the fake clock stood still: not 1 s of silence yet
            rig.clock.advance(1.1)
            rig.session.tick()
            return not rig.snap.online

        wait_for(silence_judged, 10, interval=0.0, what='the silent module judged offline')
        assert 'no reply within 1.0 s' in rig.snap.offline_reason
        with rig.model():
            rig.sim.lost_commands = set()
        rig.session.set_streaming(True)  # a frame again: online
        wait_for(lambda: rig.snap.online, 5, what='online again with a frame')
    finally:
        rig.close()


# -- settings ---------------------------------------------------------------------------------

def test_settings_are_reapplied_after_a_reboot(rig):
    with rig.model():
        rig.sim.attitude_threshold_deg = 45
    rig.fresh()
    with rig.model():
        assert rig.sim.attitude_threshold_deg == 70
    assert rig.snap.attitude_threshold_raw == 70 and rig.snap.mismatch == ()


def test_a_parameter_set_is_written_all_or_nothing(rig):
    with rig.model():
        rig.sim.lost_commands = {p.CMD_FREEFALL_THRESHOLD}
    ok, reason = rig.session.commit_desired({'attitude_threshold_deg': 75,
                                             'freefall_threshold_g': 0.3})
    assert not ok and 'freefall_threshold_g' in reason and 'put back attitude_threshold_deg' \
        in reason, reason
    with rig.model():
        assert rig.sim.attitude_threshold_deg == 70 and rig.sim.freefall_threshold_raw == 5
        rig.sim.lost_commands = set()
    ok, reason = rig.session.commit_desired({'attitude_threshold_deg': 75,
                                             'freefall_threshold_g': 0.3})
    assert ok, reason
    with rig.model():
        assert rig.sim.attitude_threshold_deg == 75 and rig.sim.freefall_threshold_raw == 3


def test_round2_22_9_a_refused_set_puts_back_a_write_whose_acknowledgement_was_lost(rig):
    """The module took the free-fall threshold but its acknowledgements were lost: the set is
    refused, and a refused set changes nothing (D4), so that write is put back too."""
    write = SETTINGS['freefall_threshold_g'].encode_set(0.3)

    def lose_ack(direction, data, t):
        if direction == 'rx' and write in data:
            rig.runner.faults.drop_next = 1
    rig.runner.add_tap(lose_ack)
    ok, reason = rig.session.commit_desired({'attitude_threshold_deg': 75,
                                             'freefall_threshold_g': 0.3})
    assert not ok and 'put back' in reason, reason
    with rig.model():
        assert rig.sim.freefall_threshold_raw == 5 and rig.sim.attitude_threshold_deg == 70
    assert 'freefall_threshold_g' in reason.split('put back')[1], reason
    assert 'could NOT' not in reason, reason


# -- trigger-request policy -------------------------------------------------------------------

def ask(rig):
    """Arm the module on external power and tilt it past its threshold: it asks the host."""
    rig.arm()
    with rig.model():
        asked = rig.sim.requests_sent
        rig.sim.set_tilt(85)
        assert rig.sim.requests_sent == asked + 1


def policy(rig, name):
    rig.session.reconfigure(SessionConfig.from_values({**rig.config.__dict__,
                                                       'trigger_request_policy': name}))


def held_request(rig):
    """Make the module ask under the defer policy; return the wire mark from before it asked."""
    policy(rig, 'defer')
    mark = rig.wire.mark()
    ask(rig)
    wait_for(lambda: rig.snap.pending_request, 3, what='the request held')
    return mark


def assert_never_confirmed(rig, mark):
    """The module gave up its request: no confirm went out since ``mark``, it did not deploy."""
    wait_for(lambda: rig.sim.requests_expired, 3, what='the module to give up')
    assert CONFIRM not in rig.wire.since(mark) and not rig.sim.triggered


@pytest.mark.parametrize('name', ['confirm', 'deny'])
def test_trigger_request_confirm_and_deny(rig, name):
    policy(rig, name)
    mark = rig.wire.mark()
    ask(rig)
    wait_for(lambda: rig.heard.decisions, 3, what='a decision')
    decision = rig.heard.decisions[-1]
    assert decision.policy == name
    if name == 'confirm':
        assert decision.decision == 'confirmed' and decision.latency_ms is not None
        wait_for(lambda: rig.sim.triggered, 3, what='the module to deploy')
        assert CONFIRM in rig.wire.since(mark)
    else:
        assert decision.decision == 'denied' and decision.latency_ms is None
        assert_never_confirmed(rig, mark)


def test_deferred_request_times_out_by_the_clock(rig):
    mark = held_request(rig)
    rig.clock.advance(0.5)
    rig.session.tick()
    assert rig.snap.pending_request and not rig.heard.decisions  # 0.8 s not over yet
    rig.clock.advance(0.31)
    rig.session.tick()
    assert [d.decision for d in rig.heard.decisions] == ['timed_out']
    assert not rig.session.answer_trigger_request(True).ok  # nothing pending any more
    assert_never_confirmed(rig, mark)


def test_round2_22_2_a_deferred_request_is_decided_by_the_monitor_its_deadline_woke(
        tmp_path, monkeypatch):
    """The defer deadline reaches the monitor: a request nobody answers is decided by then.

    On the real clock, with every other wake-up of the monitor far beyond the wait (its longest
    sleep and the online judgement's deadlines an hour away), only the core's `SetTimer` can
    have it decide the request within the wait. (A guard: before it woke the monitor by the
    deadline, ``wake()`` ran the duty at once, whose next deadline held the core's: never
    late either. Without the wake, or with it on another clock, this fails.)
    """
    from dps_parachute_ros import session as session_module
    monkeypatch.setattr(session_module, 'IDLE_WAKE_S', 3600.0)
    rig = Rig(tmp_path, clock=MonotonicClock(), attitude_threshold_deg=70,
              offline_timeout_s=3600.0, defer_timeout_s=0.3)
    try:
        mark = held_request(rig)
        wait_for(lambda: rig.heard.decisions, 10,
                 what='the deferred request decided at its deadline')
        assert [d.decision for d in rig.heard.decisions] == ['timed_out']
        assert not rig.snap.pending_request
        assert not rig.session.answer_trigger_request(True).ok  # nothing pending any more
        assert_never_confirmed(rig, mark)
    finally:
        rig.close()


def test_deferred_request_answered_true_deploys(rig):
    held_request(rig)
    result = rig.session.answer_trigger_request(True)
    assert result.ok and 'armed: it deploys' in result.message, result.message
    assert rig.heard.decisions[-1].decision == 'confirmed'
    wait_for(lambda: rig.sim.triggered, 3, what='the module to deploy')
    wait_for(lambda: rig.heard.events, 3, what='trigger event')
    assert rig.heard.events[0].source == p.SOURCE_ATTITUDE


# -- safety rules (issue 10) ------------------------------------------------------------------

@pytest.mark.parametrize('fault', ['drop_next', 'corrupt_next'])
def test_safety_2_a_lost_deploy_ack_is_reported_as_deployed_and_never_retried(rig, fault):
    rig.arm()
    mark = rig.wire.mark()
    setattr(rig.runner.faults, fault, 1)  # the module deploys; its acknowledgement is lost
    result = rig.session.deploy('DEPLOY')
    assert result.ok, result.message
    assert 'reports triggered' in result.message and 'acknowledgement was lost' in \
        result.message
    assert 'did NOT deploy' not in result.message
    # It asked before any retry: one deploy frame, then the triggered query.
    assert rig.wire.since(mark, p.CMD_DEPLOY) == [DEPLOY]
    assert p.encode_triggered_query() in rig.wire.since(mark)
    with rig.model():
        assert rig.sim.deployments == 1 and rig.sim.failed_attempts_total == 0
    wait_for(lambda: rig.heard.events, 3, what='one trigger event')
    rig.session.get_trigger_records()  # whatever the worker still does with the record
    assert len(rig.heard.events) == 1 and rig.heard.events[0].record is not None
    deploys = rig.deploy_outcomes()
    assert [(r['outcome'], r['success']) for r in deploys] == [('deployed', True)]


def unplug_when_deploy_arrives(rig):
    """Pull the cable the moment the module receives a deploy frame: no reply gets back.

    The tap runs before the module reads the chunk, so the session may see the cable gone
    before the module has taken the frame: `deploy_taken(rig)` waits for that.
    """
    def tap(direction, data, t):
        if direction == 'rx' and DEPLOY in data:
            rig.deploy_chunk = rig.runner.chunks_handled + 1
            rig.runner.port.unplug()
    rig.deploy_chunk = None
    rig.runner.add_tap(tap)


def deploy_taken(rig):
    """Wait until the module has read the chunk with the deploy frame the cable was pulled at."""
    wait_for(lambda: rig.deploy_chunk is not None and
             rig.runner.chunks_handled >= rig.deploy_chunk, 5,
             what='the module to take the deploy frame')


def reboot_when_deploy_arrives(rig, once=False):
    """Power-cycle the module the moment it receives a deploy frame (`once`: the first only)."""
    def tap(direction, data, t):
        if direction == 'rx' and DEPLOY in data and not (once and rig.sim.boot_count > 1):
            rig.clock.advance(0.5)
            rig.sim.power_cycle()  # runner thread: the model's only user right now
    rig.runner.add_tap(tap)


def test_safety_3_a_deploy_cut_short_by_the_link_is_unknown_then_resolved(rig):
    rig.arm()
    unplug_when_deploy_arrives(rig)
    result = rig.session.deploy('DEPLOY')
    assert result.outcome is Outcome.UNKNOWN and 'link dropped' in result.message
    assert 'did NOT deploy' not in result.message and 'refused' not in result.message
    assert rig.snap.deploy_outcome_unknown and rig.snap.unacked_deploys == 1
    deploy_taken(rig)
    with rig.model():
        assert rig.sim.triggered  # it did deploy
    rig.runner.replug()
    rig.wait_ready()
    # Once the module answers again the driver reads the triggered state and reports it.
    wait_for(lambda: rig.heard.events, 3, what='the deployment reported after reconnecting')
    assert not rig.snap.deploy_outcome_unknown and rig.snap.triggered
    deploys = rig.deploy_outcomes()
    assert [r['outcome'] for r in deploys] == ['unknown', 'deployed']
    assert 'success' not in deploys[0]  # never a refusal for an unknown outcome
    assert len(rig.heard.events) == 1


def test_safety_3_every_deploy_frame_that_left_unacknowledged_counts(rig):
    rig.arm()
    unplug_when_deploy_arrives(rig)
    with rig.model():
        rig.sim.lost_commands = {p.CMD_DEPLOY}  # lost on the way in: no deployment
    mark = rig.wire.mark()
    answers = []
    for _ in range(4):
        answers.append(rig.session.deploy('DEPLOY'))
        rig.runner.replug()
        rig.wait_ready()
    assert rig.wire.since(mark, p.CMD_DEPLOY) == [DEPLOY] * 2
    assert ['UNKNOWN' in a.message for a in answers] == [True, True, False, False]
    assert all('2 deploy frames in a row went unacknowledged' in a.message
               for a in answers[2:])
    # Read after reconnecting: it did not deploy.
    assert not rig.snap.deploy_outcome_unknown and not rig.snap.triggered
    outcomes = [r['outcome'] for r in rig.deploy_outcomes()]
    assert outcomes == ['unknown', 'not deployed', 'unknown', 'not deployed', 'refused',
                        'refused']


def test_safety_4_a_policy_change_settles_a_pending_request_at_once(rig):
    mark = held_request(rig)
    policy(rig, 'deny')
    assert [(d.decision, d.policy) for d in rig.heard.decisions] == [('denied', 'deny')]
    assert 'policy changed to deny' in rig.heard.decisions[0].reason
    assert not rig.snap.pending_request
    assert not rig.session.answer_trigger_request(True).ok  # nothing left to answer
    assert_never_confirmed(rig, mark)


def test_safety_4_a_change_to_confirm_confirms_within_the_window(rig):
    held_request(rig)
    policy(rig, 'confirm')
    assert rig.heard.decisions[-1].decision == 'confirmed'
    wait_for(lambda: rig.sim.triggered, 3, what='the module to deploy')


def test_safety_4_a_change_to_confirm_after_the_window_confirms_nothing(rig):
    mark = held_request(rig)
    rig.clock.advance(1.0)  # the module's 1 s is over (the defer deadline not yet judged)
    policy(rig, 'confirm')
    decision = rig.heard.decisions[-1]
    assert decision.decision == 'timed_out' and "1 s window has passed" in decision.reason
    assert CONFIRM not in rig.wire.since(mark)


def test_safety_5_answer_true_to_a_locked_module_does_not_claim_a_deployment(rig):
    mark = held_request(rig)
    assert rig.session.arm(False).ok
    result = rig.session.answer_trigger_request(True)
    assert (result.outcome, result.cause) == (Outcome.REFUSED, 'locked'), result
    assert 'deploys' not in result.message  # claims no deployment
    decision = rig.heard.decisions[-1]
    assert decision.decision == 'denied' and 'locked' in decision.reason
    assert_never_confirmed(rig, mark)


def test_safety_6_concurrent_deploys_send_one_frame_and_never_rearm(rig):
    mark = rig.wire.mark()
    results = []
    threads = [threading.Thread(target=lambda: results.append(
        rig.session.deploy('DEPLOY', True))) for _ in range(10)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(20)
    assert len(results) == 10 and all(r.ok for r in results), [r.message for r in results]
    assert sum('already deployed' in r.message for r in results) == 9
    assert rig.wire.since(mark, p.CMD_DEPLOY) == [DEPLOY]
    assert rig.wire.since(mark, p.CMD_ARM) == [p.encode_arm(True)]
    with rig.model():
        assert rig.sim.deployments == 1 and not rig.sim.protection
        assert rig.sim.failed_attempts_total == 0
    result = rig.session.arm(True)
    assert (result.outcome, result.cause) == (Outcome.REFUSED, 'triggered'), result
    assert rig.wire.since(mark, p.CMD_ARM) == [p.encode_arm(True)]


def test_safety_7_a_deploy_right_after_a_reboot_never_goes_out_on_old_knowledge(timed_rig):
    rig = timed_rig
    rig.arm()
    assert rig.snap.armed
    rig.runner.faults.reply_delay_s = 0.15  # the re-read takes a while
    mark = rig.wire.mark()
    boot = rig.power_cycle()
    wait_for(lambda: not rig.snap.fresh, 2, what='the reboot heartbeat seen')
    result = rig.session.deploy('DEPLOY')
    assert result.outcome is Outcome.REFUSED, result.message
    assert rig.wire.since(mark, p.CMD_DEPLOY) == []
    # A module that does not answer the re-read within the wait: refused, with the reason.
    rig.runner.faults.reply_delay_s = 0.0
    with rig.model():
        rig.sim.lost_commands = {p.CMD_STREAMING, p.CMD_ARMED, p.CMD_STATUS}
    rig.power_cycle()
    wait_for(lambda: not rig.snap.fresh, 2, what='the reboot heartbeat seen')
    result = rig.session.deploy('DEPLOY', True)
    assert result.outcome is Outcome.REFUSED and 'has not been re-read' in result.message, \
        result.message  # the reason: not re-read
    assert rig.wire.since(mark, p.CMD_DEPLOY) == [] and rig.wire.since(mark, p.CMD_ARM) == []
    with rig.model():
        rig.sim.lost_commands = set()
    rig.clock.advance(1.0)  # the failed initialization is tried again a second later
    rig.wait_ready(boot + 1, timeout=10)
    assert rig.session.deploy('DEPLOY', True).ok


def test_an_arm_read_back_after_a_heartbeat_in_its_gate_is_what_the_driver_knows(tmp_path):
    # Campaign s11a, run 5 (its black box): while the arm's gate read the status, a heartbeat
    # (the power-up's late second, handled as a possible reboot) came, with a status frame the
    # module sent before the arm reached it (locked). The arm was read back armed after both,
    # and said so, but the driver dropped that read-back as of an older power-up and kept
    # "locked": the deploy that followed was refused ("the module is locked").
    gate = threading.Event()

    def tap(rig, direction, data):
        if direction == 'rx' and gate.is_set() and p.encode_status_query() in data:
            gate.clear()
            rig.runner.inject_garbage(p.encode_module_heartbeat()
                                      + p.encode_status_frame(0, 10, False, False))
    rig = Rig(tmp_path, tap=tap)
    try:
        assert rig.snap.armed is False and rig.snap.fresh
        # The re-read that the heartbeat starts does not end (its triggered query is lost):
        # only the arm's own read-back can tell the driver that the module is armed.
        with rig.model():
            rig.sim.lost_commands = {p.CMD_TRIGGERED}
        gate.set()
        result = rig.session.arm(True)
        assert not gate.is_set(), 'the gate read no status'
        assert result.outcome is Outcome.DONE, result.message
        assert rig.snap.armed is True and rig.sim.armed
        mark = rig.wire.mark()
        result = rig.session.deploy('DEPLOY')
        assert result.outcome is Outcome.DONE, result.message
        assert rig.wire.since(mark, p.CMD_DEPLOY) == [p.encode_deploy()]
        events = [r.get('event') for r in rig.records() if r['kind'] == 'state']
        assert 'module reboot (unsolicited heartbeat)' in events, events
    finally:
        rig.close()


def test_an_arm_whose_read_back_a_heartbeat_overtook_is_unknown_until_read_again(tmp_path):
    # A heartbeat (a reboot, as far as the driver can tell) that comes before the answer to
    # the arm's read-back: the module may have rebooted after answering, and a reboot locks
    # it. Not "armed": unknown, and the re-read that the heartbeat starts tells.
    armed = {'sent': False}

    def tap(rig, direction, data):
        if direction != 'rx':
            return
        if p.encode_arm(True) in data:
            armed['sent'] = True
        elif armed['sent'] and p.encode_armed_query() in data:
            armed['sent'] = False
            rig.runner.inject_garbage(p.encode_module_heartbeat())
    rig = Rig(tmp_path, tap=tap)
    try:
        result = rig.session.arm(True)
        assert (result.outcome, result.cause) == (Outcome.UNKNOWN, 'rebooted'), result.message
        rig.wait_ready()
        assert rig.sim.armed and rig.snap.armed is True, rig.snap
    finally:
        rig.close()


def test_an_arm_not_read_back_leaves_the_armed_state_unknown_and_reads_it_again(tmp_path):
    # The arm frame left and neither the armed query nor the status answered: not "locked"
    # (a deploy would be refused on a guess, or go on one), unknown, until the module is read
    # afresh.
    def tap(rig, direction, data):
        if direction == 'rx' and p.encode_arm(True) in data:
            rig.sim.lost_commands = {p.CMD_ARMED, p.CMD_STATUS}
    rig = Rig(tmp_path, tap=tap, stream_status=False)  # (a stream frame answers the status)
    try:
        result = rig.session.arm(True)
        assert (result.outcome, result.cause) == (Outcome.UNKNOWN, 'no_reply'), result.message
        assert rig.snap.armed is None and not rig.snap.fresh
        with rig.model():
            rig.sim.lost_commands = set()
        rig.clock.advance(1.0)  # a re-read the lost replies cut short is tried again 1 s later
        rig.wait_ready()
        assert rig.sim.armed and rig.snap.armed is True
        result = rig.session.deploy('DEPLOY')
        assert result.outcome is Outcome.DONE, result.message
    finally:
        rig.close()


def test_an_armed_state_read_before_an_arm_frame_never_undoes_its_read_back(tmp_path):
    # A re-read asks armed, then triggered, and takes both at once. An arm went out between
    # the two (the triggered query's reply lost: the re-read asks again after its timeout;
    # the status stream, on meanwhile, let the arm go): the armed state the re-read took was
    # older than the arm's own read-back, and undid it.
    rereading, arming = threading.Event(), []

    def tap(rig, direction, data):
        if direction == 'rx' and rereading.is_set() and p.encode_triggered_query() in data:
            rereading.clear()
            rig.runner.faults.drop_next = 1
            arming.append(threading.Thread(target=lambda: arming.append(
                rig.session.arm(True))))
            arming[0].start()
    rig = Rig(tmp_path, tap=tap)
    try:
        wait_for(lambda: rig.snap.streaming, 5, what='the status stream')
        mark = rig.wire.mark()
        rereading.set()
        rig.runner.inject_garbage(p.encode_module_heartbeat())  # a reboot, as far as it knows
        wait_for(lambda: len(arming) == 2, 5, what='the arm during the re-read')
        arming[0].join(5)
        assert arming[1].outcome is Outcome.DONE, arming[1].message
        rig.wait_ready()
        # The arm went out between the re-read's armed query and its triggered query's retry.
        codes = [frame[2] for frame in rig.wire.since(mark)
                 if frame[2] in (p.CMD_ARMED, p.CMD_TRIGGERED, p.CMD_ARM)]
        assert codes[:4] == [p.CMD_ARMED, p.CMD_TRIGGERED, p.CMD_ARM, p.CMD_ARMED], codes
        assert rig.sim.armed and rig.snap.armed is True, rig.snap
    finally:
        rig.close()


def test_safety_7_a_reboot_during_a_deploy_stops_its_retry(rig):
    rig.arm()
    with rig.model():
        rig.sim.lost_commands = {p.CMD_DEPLOY}  # the frame is lost: no acknowledgement

    reboot_when_deploy_arrives(rig)
    mark = rig.wire.mark()
    result = rig.session.deploy('DEPLOY')
    assert result.outcome is Outcome.FAILED and 'did NOT deploy' in result.message, \
        result.message
    assert rig.wire.since(mark, p.CMD_DEPLOY) == [DEPLOY]  # no retry to the rebooted module
    with rig.model():
        assert rig.sim.failed_attempts_total == 0 and not rig.sim.triggered


def test_round2_22_2_a_deploy_whose_module_rebooted_after_it_deployed_is_a_deployment(rig):
    """The session's deploy is DeployCore's: the frame deploys the module, its acknowledgement
    is lost, and the module reboots as the driver asks whether it is triggered ("not
    triggered" then speaks of the new power-up). The trigger records settle it: deployed."""
    rig.arm()
    triggered_query = p.encode_triggered_query()

    def tap(direction, data, t):
        if direction == 'rx' and DEPLOY in data:
            rig.runner.faults.drop_next = 1  # its acknowledgement
        elif direction == 'rx' and triggered_query in data and rig.sim.triggered:
            rig.sim.power_cycle()  # runner thread: the model's only user right now
    rig.runner.add_tap(tap)
    mark = rig.wire.mark()
    result = rig.session.deploy('DEPLOY')
    assert result.ok and result.message.startswith('deployed'), result.message
    assert rig.wire.since(mark, p.CMD_DEPLOY) == [DEPLOY]
    with rig.model():
        assert rig.sim.deployments == 1 and rig.sim.boot_count == 2


def test_safety_8_a_late_ack_and_a_reconnect_make_one_trigger_event(timed_rig):
    rig = timed_rig
    rig.arm()
    rig.runner.faults.reply_delay_s = TIMEOUT_S + 0.2  # the ack arrives after the timeout
    result = rig.session.deploy('DEPLOY')
    assert result.ok, result.message
    assert any('late deploy acknowledgement' in text for _, text in rig.heard.logs)
    wait_for(lambda: rig.heard.events, 3, what='the trigger event')
    rig.runner.faults.reply_delay_s = 0.0
    # An offline -> online re-initialization reads the trigger record again.
    rig.runner.unplug()
    wait_for(lambda: not rig.snap.online, 3, what='offline')
    rig.runner.replug()
    rig.wait_ready()
    assert rig.session.get_trigger_records().value[-1].serial_trigger
    assert [(e.source, e.via) for e in rig.heard.events] == [(p.SOURCE_SERIAL, 'deploy_ack')]


def flown(flights):
    """A module setup: deployed (PWM) in each of `flights` earlier power-ups."""
    def setup(sim):
        for _ in range(flights):
            sim.armed = True
            assert sim.trigger_pwm()
            sim.power_cycle()
        sim.advance(0.1)  # their power-up heartbeats are in the past
    return setup


class CutRecordAnswers:
    """A tap: the next `n` trigger-record answers lose their last frame (corrupted)."""

    def __init__(self, n):
        self.n = n

    def __call__(self, rig, direction, data):
        if direction == 'rx' and self.n and p.encode_trigger_records_query() in data:
            self.n -= 1
            rig.runner.faults.corrupt_next = 1


def test_round2_22_6_an_old_record_missing_from_the_first_answer_is_no_new_deployment(
        tmp_path):
    """A loaded host cut the first record answer short; the full answer after a reconnect
    holds a record of an earlier power-up. It was there before this run: no trigger event.
    A deployment while the cable was out is still reported, once."""
    cut = CutRecordAnswers(1)
    rig = Rig(tmp_path, setup=flown(p.RECORD_SLOTS), tap=cut)
    try:
        boot = rig.snap.boot_count
        assert cut.n == 0
        rig.runner.unplug()
        wait_for(lambda: not rig.snap.online, 3, what='offline')
        rig.runner.replug()
        rig.wait_ready(boot)
        assert rig.heard.events == []
        rig.runner.unplug()
        wait_for(lambda: not rig.snap.online, 3, what='offline')
        with rig.model():
            rig.sim.armed = True
            assert rig.sim.trigger_pwm()  # fired while nobody watched, and switched off
            rig.sim.power_cycle()
        rig.runner.replug()
        rig.wait_ready(boot + 1)
        wait_for(lambda: rig.heard.events, 3, what='the deployment reported')
        assert [(e.source, e.via) for e in rig.heard.events] == [(p.SOURCE_PWM, 'record')]
    finally:
        rig.close()


def test_round2_22_8_an_unknown_deploy_is_not_settled_by_a_record_answer_cut_short(tmp_path):
    """The deploy's frame fired the module, the link dropped, the module was switched off and
    on. Its record is the last frame of the answer: while that frame comes corrupted, the
    outcome stays unknown ("no deployment in that boot" would be false); read whole, deployed.
    """
    cut = CutRecordAnswers(0)
    rig = Rig(tmp_path, setup=flown(p.RECORD_SLOTS - 1), tap=cut)
    try:
        rig.arm()
        unplug_when_deploy_arrives(rig)
        assert rig.session.deploy('DEPLOY').outcome is Outcome.UNKNOWN
        deploy_taken(rig)
        with rig.model():
            assert rig.sim.triggered
            rig.sim.power_cycle()
        cut.n = 10
        rig.runner.replug()
        rig.wait_ready()
        wait_for(lambda: any('cut short' in text for _, text in rig.heard.logs) or
                 not rig.snap.deploy_outcome_unknown, 5, what='the records read')
        assert rig.snap.deploy_outcome_unknown
        assert [r['outcome'] for r in rig.deploy_outcomes()] == ['unknown']
        result = rig.session.get_trigger_records()
        assert 'cut short' in result.message and len(result.value) == p.RECORD_SLOTS - 1
        cut.n = 0
        rig.runner.unplug()
        wait_for(lambda: not rig.snap.online, 3, what='offline')
        rig.runner.replug()
        wait_for(lambda: not rig.snap.deploy_outcome_unknown, 5, what='the deploy settled')
        assert [r['outcome'] for r in rig.deploy_outcomes()] == ['unknown', 'deployed']
    finally:
        rig.close()


def test_safety_9_a_setting_that_would_deploy_at_once_is_refused_while_armed(rig):
    assert rig.session.set_auto_triggers(False, True).ok
    rig.arm()
    with rig.model():
        rig.sim.set_tilt(30)
        asked = rig.sim.requests_sent
    # Harmless while the attitude trigger is off.
    assert rig.session.set_thresholds({'attitude_threshold_deg': 20}).ok
    result = rig.session.set_auto_triggers(True, True)
    assert not result.ok and 'would deploy now: tilt 30° ≥ attitude threshold 20°' in \
        result.message and 'lock first' in result.message, result.message
    assert rig.session.set_thresholds({'attitude_threshold_deg': 60}).ok
    assert rig.session.set_auto_triggers(True, True).ok
    for attempt in ({'attitude_threshold_deg': 25}, {'attitude_threshold_deg': 30}):
        result = rig.session.set_thresholds(attempt)
        assert not result.ok and 'would deploy now' in result.message
    ok, reason = rig.session.commit_desired({'attitude_threshold_deg': 30})
    assert not ok and 'would deploy now' in reason
    # Free fall: |a| already below the new threshold.
    with rig.model():
        rig.sim.set_accel(0.4)
    result = rig.session.set_thresholds({'freefall_threshold_g': 0.5})
    assert not result.ok and 'acceleration 0.4 g < free-fall threshold 0.5 g' in result.message
    with rig.model():
        assert rig.sim.attitude_threshold_deg == 60 and rig.sim.freefall_threshold_raw == 5
        assert rig.sim.requests_sent == asked and not rig.sim.triggered
    # Locked, nothing can deploy: the same change is fine.
    assert rig.session.arm(False).ok
    assert rig.session.set_thresholds({'attitude_threshold_deg': 20}).ok


def test_safety_11_a_full_disk_never_stops_a_deploy_and_is_never_silent(tmp_path):
    # /dev/full: every write fails with ENOSPC, for real.
    box = BlackBox(str(tmp_path), path='/dev/full')
    rig = Rig(tmp_path, blackbox=box)
    try:
        policy(rig, 'confirm')
        rig.arm()
        assert rig.session.deploy('DEPLOY').ok
        assert not box.sync(1.0)
        status = box.status()
        assert not status.writing and status.lost > 0
        assert status.error == 'No space left on device'
        problem = rig.session.blackbox_problem()
        assert problem.startswith('cannot write: No space left on device;') and \
            problem.endswith('records lost')
        wait_for(lambda: box.status().lost > status.lost, 3, what='more records lost')
        said = [text for level, text in rig.heard.logs if 'black box' in text]
        assert len(said) == 1 and said[0].startswith('black box: cannot write: No space left')
        check = rig.session.preflight_check()
        assert not check.ok and 'FAIL black box writable: cannot write: No space left' in \
            check.message
    finally:
        rig.close()


def test_safety_11_an_unusable_blackbox_dir_runs_without_it_and_recovers(tmp_path):
    blocker = tmp_path / 'blocker'
    blocker.write_text('a regular file where a directory should be')
    directory = blocker / 'bb'
    box = BlackBox(str(directory), reopen_period_s=0.1)
    rig = Rig(tmp_path, blackbox=box, blackbox_dir=str(directory))
    try:
        rig.arm()
        assert rig.session.deploy('DEPLOY').ok
        problem = rig.session.blackbox_problem()
        assert f"blackbox_dir '{directory}'" in problem and 'Not a directory' in problem
        blocker.unlink()
        wait_for(lambda: box.status().writing, 5, what='the black box writing again')
        assert box.sync(2.0) and os.path.dirname(box.status().path) == str(directory)
        assert box.status().lost > 0 and rig.session.blackbox_problem() == ''
        assert any('writing again' in text for _, text in rig.heard.logs)
    finally:
        rig.close()


def test_safety_12_the_blackbox_directory_stays_within_its_bound(tmp_path):
    directory = tmp_path / 'bb'
    directory.mkdir()
    old = []
    for n in range(5):
        path = directory / f'parachute-2020010{n}T000000Z-{100 + n}.jsonl'
        path.write_bytes(b'x' * 40_000)
        os.utime(path, (1e9 + n, 1e9 + n))
        old.append(path)
    other = directory / 'notes.txt'
    other.write_bytes(b'y' * 100_000)
    box = BlackBox(str(directory), max_bytes=100_000)
    try:
        # Oldest first until the runs fit: 5 x 40 kB -> 2 x 40 kB; other files are not ours.
        assert [p.exists() for p in old] == [False, False, False, True, True]
        assert other.exists() and box.status().removed_runs == 3
        for i in range(3000):  # this run alone grows past the bound: kept, and said
            box.record('frame', dir='rx', hex='41 75 32 07 0a 00 01 44', i=i)
        assert box.sync(5.0)
        box.set_max_bytes(100_000)
        wait_for(lambda: not old[3].exists() and not old[4].exists(), 3,
                 what='the other runs removed')
        status = box.status()
        assert status.over_budget and os.path.exists(status.path)
        assert status.run_bytes > 100_000
    finally:
        box.close()


PREFLIGHT_LINES = [
    'online', 'armed', 'not triggered', 'not in protection', 'settings as desired',
    'auto triggers as desired', 'auto triggers on', 'trigger requests confirmed',
    'no trigger condition met', 'bay closed', 'battery', 'link clean', 'status stream',
    'black box writable']


def test_safety_21_preflight_check_reads_afresh_and_lists_every_check(rig):
    rig.arm()
    mark = rig.wire.mark()
    result = rig.session.preflight_check()
    assert result.ok, result.message
    lines = result.message.splitlines()
    assert all(line.startswith('OK   ') for line in lines)
    assert [line.split(':')[0][5:] for line in lines] == PREFLIGHT_LINES
    sent = rig.wire.since(mark)
    assert sent and all(raw[3] == p.CTRL_QUERY for raw in sent), [r.hex(' ') for r in sent]
    # Behind the driver's back: locked, a setting changed, on a weak battery.
    with rig.model():
        rig.sim.armed = False
        rig.sim.attitude_threshold_deg = 50
        rig.sim.set_external_power(False)
        rig.sim.cell_voltage_v = 3.3
    result = rig.session.preflight_check()
    assert result.outcome is Outcome.FAILED
    lines = result.message.splitlines()
    fails = [line for line in lines if line.startswith('FAIL')]
    assert lines[:len(fails)] == fails  # failures first
    assert {line.split(':')[0] for line in fails} == {
        'FAIL armed', 'FAIL settings as desired', 'FAIL battery'}
    assert 'attitude_threshold_deg: want 70, module 50' in result.message
    assert '3.30 V on battery, below 3.5 V' in result.message
    rig.runner.unplug()
    wait_for(lambda: not rig.snap.port_open, 3, what='the port closed')
    result = rig.session.preflight_check()
    assert not result.ok and result.message.startswith('FAIL')
    assert 'not checked' in result.message and 'OK   black box writable' in result.message


def test_the_core_and_everything_below_it_import_no_ros():
    code = ('import sys\n'
            'import dps_parachute_ros.session, dps_parachute_ros.simulation\n'
            "ros = sorted(m for m in sys.modules if m.split('.')[0] in "
            "('rclpy', 'rcl_interfaces', 'uav_serial_drivers') or m.endswith('_msgs'))\n"
            'print(ros)\n')
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            timeout=60, cwd=os.path.dirname(os.path.dirname(__file__)))
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == '[]'


def test_safety_3_an_unknown_deploy_settled_after_a_reboot_by_the_trigger_records(rig):
    """The module deployed, then rebooted while the link was down: its flag is clear again."""
    rig.arm()
    unplug_when_deploy_arrives(rig)
    assert 'UNKNOWN' in rig.session.deploy('DEPLOY').message
    deploy_taken(rig)
    with rig.model():
        assert rig.sim.triggered
        rig.sim.power_cycle()  # re-packed and switched on again while nobody watched
        assert not rig.sim.triggered
    rig.runner.replug()
    rig.wait_ready()
    wait_for(lambda: not rig.snap.deploy_outcome_unknown, 5, what='the unknown deploy settled')
    deploys = rig.deploy_outcomes()
    assert [r['outcome'] for r in deploys] == ['unknown', 'deployed']
    assert 'rebooted since' in deploys[1]['resolved']
    wait_for(lambda: rig.heard.events, 3, what='the deployment reported')
    assert len(rig.heard.events) == 1


def test_safety_3_an_unknown_deploy_that_did_not_fire_stays_not_deployed_across_a_reboot(rig):
    rig.arm()
    unplug_when_deploy_arrives(rig)
    with rig.model():
        rig.sim.lost_commands = {p.CMD_DEPLOY}  # never reached the module
    assert 'UNKNOWN' in rig.session.deploy('DEPLOY').message
    deploy_taken(rig)  # (and lost)
    with rig.model():
        rig.sim.lost_commands = set()
        rig.sim.power_cycle()
    rig.runner.replug()
    rig.wait_ready()
    wait_for(lambda: not rig.snap.deploy_outcome_unknown, 5, what='the unknown deploy settled')
    assert [r['outcome'] for r in rig.deploy_outcomes()] == ['unknown', 'not deployed']
    assert not rig.heard.events


def test_safety_3_6_concurrent_deploys_cut_by_the_link_a_policy_change_and_a_reboot(rig):
    """The faults of items 3, 4, 6 and 7 at once, as a harsh flight would combine them.

    Ten deploy calls race; the cable goes the moment the first deploy frame reaches the module;
    the trigger-request policy changes while they are answered; the module deployed and is
    power-cycled while unplugged. One frame left, no answer says it did not deploy, and after
    the replug the trigger records settle it as one deployment.
    """
    rig.arm()
    mark = rig.wire.mark()
    unplug_when_deploy_arrives(rig)
    results = []
    threads = [threading.Thread(target=lambda: results.append(
        rig.session.deploy('DEPLOY', True))) for _ in range(10)]
    for thread in threads:
        thread.start()
    rig.session.reconfigure(SessionConfig.from_values({**rig.config.__dict__,
                                                       'trigger_request_policy': 'deny'}))
    for thread in threads:
        thread.join(20)
    assert len(results) == 10
    messages = [r.message for r in results]
    assert not any(r.ok for r in results), messages  # nobody saw an acknowledgement
    # Calls that found the module gone sent nothing, and say so, but none may read as "it did
    # not deploy": every answer names the unknown outcome of the frame that left.
    assert not any('did NOT deploy' in m for m in messages), messages
    assert all('UNKNOWN' in m for m in messages), messages
    assert rig.wire.since(mark, p.CMD_DEPLOY) == [DEPLOY]
    deploy_taken(rig)
    with rig.model():
        assert rig.sim.deployments == 1 and rig.sim.triggered
        rig.sim.power_cycle()
    rig.runner.replug()
    rig.wait_ready()
    wait_for(lambda: not rig.snap.deploy_outcome_unknown, 5, what='the unknown deploy settled')
    assert rig.snap.policy == 'deny'
    assert rig.wire.since(mark, p.CMD_DEPLOY) == [DEPLOY]  # no retry after the reboot
    wait_for(lambda: rig.heard.events, 3, what='the deployment reported')
    assert len(rig.heard.events) == 1
    # Switched off and on after the deployment is the README's "re-pack it and switch it off
    # and on": the policy still in force is the one set mid-request, and arming is allowed.
    # (The power-up's second heartbeat taken late by a loaded host, D3, during the read-back:
    # UNKNOWN, cause rebooted, truly; a user arms again. Campaign s12f, run 1.)
    armed, _ = ask_again(lambda: rig.session.arm(True), lambda r: r.cause == 'rebooted')
    assert armed.ok, armed


def concurrent_deploys(rig, n=5):
    """Start `n` deploy calls (arm_if_locked) at once; return their results once all answered."""
    results = []
    threads = [threading.Thread(target=lambda: results.append(
        rig.session.deploy('DEPLOY', True))) for _ in range(n)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(20)
    assert len(results) == n
    return results


def test_safety_3_6_repeated_unplugs_during_concurrent_deploys_never_pass_the_frame_guard(rig):
    """Items 3 and 6 over and over: each round five deploy calls race and the cable goes as a
    deploy frame arrives (a frame lost on the way in: nothing deploys). Two frames in all, then
    every call is refused by the guard, however often the cable comes back; a reboot lifts it."""
    rig.arm()
    flaky = [True]

    def tap(direction, data, t):
        if flaky[0] and direction == 'rx' and DEPLOY in data:
            rig.runner.port.unplug()
    rig.runner.add_tap(tap)
    with rig.model():
        rig.sim.lost_commands = {p.CMD_DEPLOY}
    mark = rig.wire.mark()
    rounds = []
    for _ in range(4):
        rounds.append(concurrent_deploys(rig))
        rig.runner.replug()
        rig.wait_ready()
        wait_for(lambda: not rig.snap.deploy_outcome_unknown, 5, what='the outcome settled')
    assert rig.wire.since(mark, p.CMD_DEPLOY) == [DEPLOY] * 2
    assert rig.wire.since(mark, p.CMD_ARM) == []  # still armed: never re-armed
    for results in rounds[:2]:
        messages = [r.message for r in results]
        assert not any(r.ok for r in results), messages
        assert not any('did NOT deploy' in m for m in messages), messages
        assert all('UNKNOWN' in m for m in messages), messages
    for results in rounds[2:]:
        assert all('2 deploy frames in a row went unacknowledged' in r.message
                   for r in results), [r.message for r in results]
    assert not rig.snap.triggered and not rig.heard.events
    with rig.model():
        assert rig.sim.deployments == 0 and not rig.sim.protection
        rig.sim.lost_commands = set()
    flaky[0] = False
    rig.fresh()
    results = concurrent_deploys(rig)
    assert all(r.ok for r in results), [r.message for r in results]
    assert rig.wire.since(mark, p.CMD_DEPLOY) == [DEPLOY] * 3
    wait_for(lambda: rig.heard.events, 3, what='the deployment reported')
    assert len(rig.heard.events) == 1


def test_safety_7_11_a_full_disk_and_a_reboot_during_a_deploy(tmp_path):
    """Items 7 and 11 at once: the black box cannot write a byte (ENOSPC) and the module reboots
    as the deploy frame arrives. The answer is the module's truth, the next deploy re-arms the
    rebooted module and goes out, and the lost records are counted and said once."""
    box = BlackBox(str(tmp_path), path='/dev/full')
    rig = Rig(tmp_path, blackbox=box)
    try:
        rig.arm()
        with rig.model():
            rig.sim.lost_commands = {p.CMD_DEPLOY}
        reboot_when_deploy_arrives(rig, once=True)
        mark = rig.wire.mark()
        result = rig.session.deploy('DEPLOY')
        assert result.outcome is Outcome.FAILED and 'did NOT deploy' in result.message, \
            result.message
        with rig.model():
            rig.sim.lost_commands = set()
        rig.wait_ready(boot=2)
        result = rig.session.deploy('DEPLOY', True)
        assert result.ok, result.message
        assert rig.wire.since(mark, p.CMD_DEPLOY) == [DEPLOY] * 2
        with rig.model():
            assert rig.sim.deployments == 1 and rig.sim.failed_attempts_total == 0
        wait_for(lambda: rig.heard.events, 3, what='the deployment reported')
        assert len(rig.heard.events) == 1
        assert not box.sync(1.0) and box.status().lost > 0
        assert rig.session.blackbox_problem().startswith('cannot write: No space left')
        said = [text for level, text in rig.heard.logs if 'black box' in text]
        assert len(said) == 1, said
    finally:
        rig.close()


def test_safety_4_5_a_pending_request_across_an_unplug_is_never_confirmed(rig):
    mark = held_request(rig)
    rig.runner.unplug()
    wait_for(lambda: not rig.snap.online, 3, what='offline')
    result = rig.session.answer_trigger_request(True)
    assert (result.outcome, result.cause) == (Outcome.REFUSED, 'offline'), result
    assert 'deploys' not in result.message  # claims no deployment
    assert rig.heard.decisions[-1].decision != 'confirmed'
    rig.runner.replug()
    rig.wait_ready()
    assert CONFIRM not in rig.wire.since(mark)
    with rig.model():
        assert not rig.sim.triggered


def test_safety_5_7_a_pending_request_across_a_reboot_claims_no_deployment(rig):
    """The module asked, then power-cycled (it boots locked, its question gone): an answer true
    must not say "it deploys" on the armed state read before the reboot."""
    mark = held_request(rig)
    boot = rig.power_cycle()
    wait_for(lambda: rig.heard.decisions, 3, what='the request settled by the reboot')
    decision = rig.heard.decisions[-1]
    assert decision.decision == 'denied' and 'rebooted' in decision.reason, decision
    assert not rig.snap.pending_request
    result = rig.session.answer_trigger_request(True)
    assert (result.outcome, result.cause) == (Outcome.REFUSED, 'not_pending'), result
    rig.wait_ready(boot)
    with rig.model():
        assert not rig.sim.triggered and not rig.sim.armed
    assert CONFIRM not in rig.wire.since(mark)


# -- issue 22 item 7: the trigger-request policy's findings (test/test_trigger_model.py) --------

class HeldGate:
    """A release gate that holds every release until the test lets it go (a slow motor stop)."""

    def __init__(self) -> None:
        self.entered = threading.Event()
        self.go = threading.Event()

    def available(self, route):
        return True

    def before_release(self, route, t_request=None):
        self.entered.set()
        self.go.wait(10.0)


def gated(rig):
    gate = HeldGate()
    rig.session.release_gate = gate
    return gate


def rebooted_while_held(rig, gate):
    """Power-cycle the module while `gate` holds a release; return when the driver saw it."""
    assert gate.entered.wait(5.0 * wait_scale()), 'the release gate was never called'
    logs = len(rig.heard.logs)
    boot = rig.power_cycle()
    wait_for(lambda: any('rebooted' in text for _, text in rig.heard.logs[logs:]), 5,
             what='the reboot seen')
    return boot


def test_round2_22_7_a_reboot_while_the_gate_is_passed_confirms_nothing(rig):
    """Found by the trigger-request model: under confirm with a release gate, the module
    rebooted while the gate waited, and the confirmation went out after it anyway (decided
    'confirmed'): a rebooted module has forgotten its question, so the confirm answers nobody,
    or a newer request nobody decided on."""
    gate = gated(rig)
    mark = rig.wire.mark()
    ask(rig)
    boot = rebooted_while_held(rig, gate)
    gate.go.set()
    wait_for(lambda: rig.heard.decisions, 5, what='a decision')
    rig.wait_ready(boot)
    assert [d.decision for d in rig.heard.decisions] == ['denied'], rig.heard.decisions
    assert 'rebooted' in rig.heard.decisions[0].reason
    assert CONFIRM not in rig.wire.since(mark)


def test_round2_22_7_a_change_to_deny_while_the_gate_is_passed_confirms_nothing(rig):
    """Found by the model: the policy set to deny while the gate waited, and the confirmation
    left after it under deny."""
    gate = gated(rig)
    mark = rig.wire.mark()
    ask(rig)
    assert gate.entered.wait(5.0 * wait_scale())
    policy(rig, 'deny')
    gate.go.set()
    wait_for(lambda: rig.heard.decisions, 5, what='a decision')
    assert [(d.decision, d.policy) for d in rig.heard.decisions] == [('denied', 'deny')]
    assert_never_confirmed(rig, mark)


def test_round2_22_7_a_gate_that_outlasts_the_modules_window_confirms_nothing(rig):
    """Found by the model: a gate that returned after the module's 1 s window (a loaded host)
    was followed by the confirmation, decided 'confirmed' with a latency over 1 s."""
    gate = gated(rig)
    mark = rig.wire.mark()
    ask(rig)
    assert gate.entered.wait(5.0 * wait_scale())
    rig.clock.advance(1.0)
    gate.go.set()
    wait_for(lambda: rig.heard.decisions, 5, what='a decision')
    assert [d.decision for d in rig.heard.decisions] == ['timed_out'], rig.heard.decisions
    assert_never_confirmed(rig, mark)


def test_round2_22_7_an_answer_whose_gate_outlasts_a_reboot_is_not_confirmed(rig):
    """Found by the model: ~/answer_trigger_request true read the module's state, then waited
    for the gate, during which the module rebooted; it confirmed anyway and answered "sent"."""
    mark = held_request(rig)
    gate = gated(rig)
    out = in_thread(rig.session.answer_trigger_request, True)
    rebooted_while_held(rig, gate)
    gate.go.set()
    wait_for(lambda: out, 5, what='the answer')
    result = out[0]
    assert (result.outcome, result.cause) == (Outcome.REFUSED, 'rebooted'), result
    assert [d.decision for d in rig.heard.decisions] == ['denied'], rig.heard.decisions
    assert CONFIRM not in rig.wire.since(mark)


def test_round2_22_7_an_answer_after_the_defer_deadline_confirms_nothing(rig):
    """Found by the model: an answer true after defer_timeout_s, before the monitor's tick
    denied the request (a loaded host), confirmed it."""
    mark = held_request(rig)
    rig.clock.advance(0.85)  # past its 0.8 s deadline, within the module's 1 s
    result = rig.session.answer_trigger_request(True)
    assert not result.ok and result.outcome == Outcome.REFUSED, result
    assert [d.decision for d in rig.heard.decisions] == ['timed_out'], rig.heard.decisions
    assert_never_confirmed(rig, mark)


def test_round2_22_7_a_policy_change_never_waits_for_the_release_gate(rig):
    """A change to confirm settles a held request through the release gate: the parameter
    callback waited for the gate (up to release_gate_timeout_s, on the executor) before."""
    mark = held_request(rig)
    gate = gated(rig)
    done = []
    threading.Thread(target=lambda: done.append(policy(rig, 'confirm')), daemon=True).start()
    assert gate.entered.wait(5.0 * wait_scale())
    wait_for(lambda: done, 5, what='the parameter change to return while the gate waits')
    assert not rig.heard.decisions  # (decided when the gate is passed)
    gate.go.set()
    wait_for(lambda: rig.heard.decisions, 5, what='a decision')
    assert rig.heard.decisions[-1].decision == 'confirmed'
    wait_for(lambda: rig.sim.triggered, 3, what='the module to deploy')
    assert CONFIRM in rig.wire.since(mark)


# -- round two (issue 21) ---------------------------------------------------------------------

def armed_and_banked(rig, tilt=30):
    """Arm, raise the attitude threshold to 70 by the service, bank: return the requests so far."""
    rig.arm()
    assert rig.session.set_thresholds({'attitude_threshold_deg': 70}).ok
    with rig.model():
        rig.sim.set_tilt(tilt)
        return rig.sim.requests_sent


def assert_not_fired(rig, asked, threshold=70):
    with rig.model():
        assert rig.sim.attitude_threshold_deg == threshold
        assert not rig.sim.triggered and rig.sim.requests_sent == asked
        assert rig.sim.deployments == 0


def assert_held(rig, name, reason):
    wait_for(lambda: rig.snap.initialized and rig.snap.held, 5, what='the setting held back')
    assert len(rig.snap.held) == 1 and rig.snap.held[0].startswith(name), rig.snap.held
    assert reason in rig.snap.held[0], rig.snap.held
    assert any(line.startswith(name) and 'not written' in line and reason in line
               for line in rig.snap.mismatch), rig.snap.mismatch
    assert any(level == 'warn' and name in text and reason in text
               for level, text in rig.heard.logs), rig.heard.logs
    withheld = [r for r in rig.records()
                if r['kind'] == 'decision' and r['what'] == 'settings write withheld']
    assert withheld and reason in withheld[-1]['reason'], withheld


def test_round2_1_a_restart_never_writes_a_setting_that_would_deploy(tmp_path):
    """Issue 21 item 1: attitude_threshold_deg 20, armed, raised to 70 by the service, banked
    30°, the driver respawns with the same parameters: 20 is held back (log, mismatch with the
    reason, black box), and written once the tilt came down; the parachute never fires."""
    rig = Rig(tmp_path, attitude_threshold_deg=20)
    try:
        asked = armed_and_banked(rig)
        mark = rig.wire.mark()
        rig.restart()
        rig.wait_ready()
        assert_not_fired(rig, asked)
        assert_held(rig, 'attitude_threshold_deg', 'tilt 30° ≥ attitude threshold 20°')
        assert rig.wire.since(mark, p.CMD_ATTITUDE_THRESHOLD) == \
            [p.encode_attitude_threshold_query()] * len(rig.wire.since(
                mark, p.CMD_ATTITUDE_THRESHOLD))  # queries only, no set
        assert_not_fired(rig, asked)
        # Still banked: a status frame never lets it through.
        rig.clock.advance(HELD_RETRY_S)
        time.sleep(0.3)
        assert_not_fired(rig, asked)
        # The airframe levels: written at the next status, the module stays armed and quiet.
        with rig.model():
            rig.sim.set_tilt(5)
        rig.clock.advance(HELD_RETRY_S)
        wait_for(lambda: rig.snap.attitude_threshold_raw == 20 and not rig.snap.held, 5,
                 what='the held setting written once the tilt came down')
        assert rig.snap.mismatch == ()
        assert_not_fired(rig, asked, threshold=20)
        with rig.model():
            assert rig.sim.armed
    finally:
        rig.close()


def test_round2_1_a_reconnect_holds_a_setting_until_the_module_is_locked(tmp_path):
    """The re-initialization after a reconnect (and after a reboot, the same path) passes the
    rule too; locking the module lets the held setting through."""
    rig = Rig(tmp_path, attitude_threshold_deg=20)
    try:
        asked = armed_and_banked(rig)
        rig.runner.unplug()
        wait_for(lambda: not rig.snap.port_open, 3, what='the port closed')
        rig.runner.replug()
        rig.wait_ready()
        assert_not_fired(rig, asked)
        assert_held(rig, 'attitude_threshold_deg', 'tilt 30° ≥ attitude threshold 20°')
        rig.clock.advance(HELD_RETRY_S)
        assert rig.session.arm(False).ok
        wait_for(lambda: rig.snap.attitude_threshold_raw == 20 and not rig.snap.held, 5,
                 what='the held setting written once the module was locked')
        assert_not_fired(rig, asked, threshold=20)
    finally:
        rig.close()


def test_round2_1_a_set_is_written_in_an_order_that_never_fires(rig):
    """Disable the attitude trigger and lower its threshold in one parameter set while armed
    and banked: the disable goes first, so no moment of the write meets a trigger condition;
    the same set at a driver restart."""
    asked = armed_and_banked(rig)
    ok, reason = rig.session.commit_desired({'attitude_threshold_deg': 20,
                                             'attitude_trigger': 'disable'})
    assert ok, reason
    assert_not_fired(rig, asked, threshold=20)
    with rig.model():
        assert not rig.sim.attitude_trigger_enabled
        rig.sim.attitude_threshold_deg = 70
        rig.sim.attitude_trigger_enabled = True
    rig.restart(attitude_threshold_deg=20, attitude_trigger='disable')
    rig.wait_ready()
    wait_for(lambda: rig.snap.attitude_threshold_raw == 20, 5, what='the settings written')
    assert rig.snap.held == () and rig.snap.mismatch == ()
    assert_not_fired(rig, asked, threshold=20)


def flag_queries(rig, mark):
    return [raw for raw in rig.wire.since(mark, p.CMD_ATTITUDE_TRIGGER)
            if raw[3] == p.CTRL_QUERY]


def test_round2_1_the_flag_query_goes_out_once_per_run_and_never_when_it_could_fire(tmp_path):
    """P14: a firmware may read the flag query as "enable the attitude trigger". Sent at most
    once per run while unanswered (D5: get_config and re-initializations used to repeat it),
    and never while enabling the attitude trigger would deploy the armed module at once."""
    def silent_to_flags(sim):
        sim.lost_commands = {p.CMD_ATTITUDE_TRIGGER}
    rig = Rig(tmp_path, setup=silent_to_flags)
    try:
        assert len(flag_queries(rig, 0)) == 1
        assert rig.snap.attitude_trigger_enabled is None
        assert rig.session.get_config().ok
        rig.runner.unplug()
        wait_for(lambda: not rig.snap.port_open, 3, what='the port closed')
        rig.runner.replug()
        rig.wait_ready()
        assert rig.session.get_config().ok
        assert len(flag_queries(rig, 0)) == 1
        # A new run, the module armed and banked beyond its threshold with the attitude
        # trigger off: the query could turn it on and fire; it is not sent.
        with rig.model():
            rig.sim.lost_commands = set()
            rig.sim.attitude_trigger_enabled = False
        rig.arm()
        with rig.model():
            rig.sim.set_tilt(75)
            asked = rig.sim.requests_sent
        mark = rig.wire.mark()
        rig.restart()
        rig.wait_ready()
        assert flag_queries(rig, mark) == []
        assert rig.snap.attitude_trigger_enabled is None
        assert any('flag query not sent' in text for _, text in rig.heard.logs), rig.heard.logs
        with rig.model():
            assert rig.sim.requests_sent == asked and not rig.sim.triggered
    finally:
        rig.close()


def preflight_fails(rig):
    """Run the preflight check; return its FAIL lines as {name: detail}."""
    result = rig.session.preflight_check()
    fails = dict(line[5:].split(': ', 1) for line in result.message.splitlines()
                 if line.startswith('FAIL'))
    assert result.ok == (not fails), result.message
    return fails


def test_round2_4_preflight_fails_under_deny_and_with_the_bay_open(rig):
    """Issue 21 item 4: GO under trigger_request_policy deny and with bay_open true; both are
    FAIL lines with the reason now, and only they."""
    rig.arm()
    assert preflight_fails(rig) == {}
    policy(rig, 'deny')
    fails = preflight_fails(rig)
    assert list(fails) == ['trigger requests confirmed'], fails
    assert 'deny' in fails['trigger requests confirmed'] and \
        'does not deploy on its own' in fails['trigger requests confirmed']
    policy(rig, 'defer')
    assert preflight_fails(rig) == {}  # someone may answer: said in its OK line
    policy(rig, 'confirm')
    with rig.model():
        rig.sim.set_light(3.0)  # above the module's 1.2 V light threshold
    fails = preflight_fails(rig)
    assert list(fails) == ['bay closed'], fails
    assert 'BAY OPEN: light 3.0 V > light threshold 1.2 V' in fails['bay closed']
    assert rig.snap.bay_open
    with rig.model():
        rig.sim.set_light(None)
    assert preflight_fails(rig) == {}


def test_round2_4_preflight_fails_on_every_state_that_keeps_the_parachute_in(tmp_path):
    """The other states the driver knows that stop a deployment: both auto triggers off, a
    trigger condition met now (arming would fire), a desired setting held back (item 1), a
    link that just had errors."""
    rig = Rig(tmp_path, attitude_threshold_deg=20)
    try:
        rig.arm()
        assert rig.session.set_auto_triggers(False, False).ok
        fails = preflight_fails(rig)
        assert list(fails) == ['auto triggers on'], fails
        assert 'attitude OFF, free fall OFF' in fails['auto triggers on']
        assert rig.session.set_auto_triggers(True, True).ok
        # Locked and banked beyond the threshold: arming now would fire it.
        assert rig.session.arm(False).ok
        with rig.model():
            rig.sim.set_tilt(30)
        fails = preflight_fails(rig)
        assert set(fails) == {'armed', 'no trigger condition met'}, fails
        assert 'tilt 30° ≥ attitude threshold 20°: arming now fires the parachute' in \
            fails['no trigger condition met']
        # Armed at 70, banked 30, a respawn holds 20 back: the settings line says so.
        with rig.model():
            rig.sim.set_tilt(0)
        rig.arm()
        asked = armed_and_banked(rig)
        rig.restart()
        rig.wait_ready()
        wait_for(lambda: rig.snap.held, 5, what='the setting held back')
        fails = preflight_fails(rig)
        assert list(fails) == ['settings as desired'], fails
        assert 'attitude_threshold_deg: want 20, module 70 (not written: would deploy now' in \
            fails['settings as desired']
        with rig.model():
            assert rig.sim.requests_sent == asked and not rig.sim.triggered
            rig.sim.set_tilt(0)
        rig.clock.advance(HELD_RETRY_S)
        wait_for(lambda: not rig.snap.held, 5, what='the held setting written')
        rig.clock.advance(11.0)
        # The jump leaves the stream silent on the driver's clock until its next frame.
        wait_for(lambda: rig.session._stream_check(rig.session.config)[0], 5,
                 what='a status frame after the clock jump')
        assert preflight_fails(rig) == {}
        # Noise on the line: a no-go until the link has been clean for 10 s.
        rig.runner.inject_garbage(bytes([0x41, 0x75, 0x23, 0x01, 0x05, 0x00]))  # bad sum
        wait_for(lambda: rig.session.link_info()['checksum_errors'], 5,
                 what='the checksum error counted')
        fails = preflight_fails(rig)
        assert list(fails) == ['link clean'], fails
        rig.clock.advance(11.0)
        wait_for(lambda: rig.session._stream_check(rig.session.config)[0], 5,
                 what='a status frame after the clock jump')
        assert preflight_fails(rig) == {}
    finally:
        rig.close()


def test_round2_1_arming_a_module_that_meets_a_trigger_condition_is_refused(rig):
    """The same rule on the arm path (P21: arming beyond a threshold fires at once): ~/arm is
    refused with nothing sent; ~/deploy with arm_if_locked still arms and deploys."""
    with rig.model():
        rig.sim.set_tilt(75)  # the threshold is 70
        asked = rig.sim.requests_sent
    mark = rig.wire.mark()
    result = rig.session.arm(True)
    assert not result.ok and 'would deploy now: tilt 75° ≥ attitude threshold 70°' in \
        result.message, result.message
    assert rig.wire.since(mark, p.CMD_ARM) == []
    with rig.model():
        assert not rig.sim.armed and rig.sim.requests_sent == asked
        rig.sim.set_tilt(0)
        rig.sim.set_accel(0.3)  # below the 0.5 g free-fall threshold
    result = rig.session.arm(True)
    assert not result.ok and 'acceleration 0.3 g < free-fall threshold 0.5 g' in \
        result.message, result.message
    assert rig.session.set_auto_triggers(True, False).ok
    rig.arm()  # the free-fall trigger is off: nothing fires
    with rig.model():
        assert rig.sim.armed and rig.sim.requests_sent == asked and not rig.sim.triggered
    assert rig.session.arm(False).ok
    with rig.model():
        rig.sim.set_accel(1.0)
        rig.sim.set_tilt(75)
    policy(rig, 'deny')  # the module's own request is not what deploys it here
    result = rig.session.deploy('DEPLOY', arm_if_locked=True)
    assert result.ok, result.message
    with rig.model():
        assert rig.sim.triggered


def test_round2_1_the_two_frame_guard_holds_across_a_driver_restart(rig):
    """Found auditing the rules' paths: the P11 guard (never a third deploy frame without an
    acknowledgement in one power-up) was kept in memory, so a respawned driver sent two more to
    the same power-up of the module (four in a row: protection blocks its own detection)."""
    rig.arm()
    with rig.model():
        rig.sim.lost_commands = {p.CMD_DEPLOY}  # no frame reaches it: no acknowledgement
    result = rig.session.deploy('DEPLOY')
    assert not result.ok and 'did NOT deploy' in result.message, result.message
    rig.restart()
    rig.wait_ready()
    mark = rig.wire.mark()
    result = rig.session.deploy('DEPLOY')
    assert not result.ok and 'a third could put the module into protection' in \
        result.message, result.message
    assert rig.wire.since(mark, p.CMD_DEPLOY) == []
    assert 'FAIL not in protection' in rig.session.preflight_check().message
    assert any('earlier run of the driver' in text for _, text in rig.heard.logs)
    # A power-up of the module clears its count, and the driver's.
    with rig.model():
        rig.sim.lost_commands = set()
    rig.fresh()
    assert rig.snap.failed_deploys == 0
    rig.arm()
    assert rig.session.deploy('DEPLOY').ok


def test_round2_1_a_confirmation_after_a_reconnect_claims_nothing_on_old_knowledge(rig):
    """Found auditing "never on old knowledge" (D15): deploy and arm wait for the re-read, but
    answering a held request true right after a reconnect, before the module was read again,
    said "the module was armed: it deploys" from the armed state read before the unplug."""
    mark = held_request(rig)
    rig.runner.unplug()
    wait_for(lambda: not rig.snap.port_open, 3, what='the port closed')
    with rig.model():
        rig.sim.streaming = False  # no status frame re-reads it ...
        # ... and the re-initialization stalls at the armed query (nor does a status poll tell)
        rig.sim.lost_commands = {p.CMD_STREAMING, p.CMD_ARMED, p.CMD_STATUS}
    rig.runner.replug()
    wait_for(lambda: rig.snap.online and rig.wire.since(mark, p.CMD_ARMED), 5,
             what='online again, initializing')
    assert not rig.snap.fresh and rig.snap.armed  # as read before the unplug
    # The module's 1 s has passed (so the confirmation cannot fire it, whatever it says) ...
    wait_for(lambda: not rig.sim.pending_request, 3, what='the module to give up')
    assert not rig.snap.fresh  # ... and the driver has still not read it again
    result = rig.session.answer_trigger_request(True)
    assert result.ok and 'was armed' not in result.message and 'not known' in \
        result.message, result.message
    assert 'was armed' not in rig.heard.decisions[-1].reason
    with rig.model():
        assert not rig.sim.triggered  # its 1 s window had passed: it did not


_STEP = st.one_of(
    st.tuples(st.just('attitude_threshold_deg'), st.integers(10, 90)),
    st.tuples(st.just('freefall_threshold_g'), st.integers(1, 9).map(lambda raw: raw / 10)),
    st.tuples(st.just('freefall_time_s'), st.integers(1, 255).map(lambda raw: raw / 100)),
    st.tuples(st.sampled_from(['attitude', 'freefall']), st.booleans()),
    st.tuples(st.just('armed'), st.just(True)))


def _frame(step):
    name, value = step
    if name == 'armed':
        return p.encode_arm(True)
    if name == 'attitude':
        return p.encode_attitude_trigger(value)
    if name == 'freefall':
        return p.encode_freefall_trigger(value)
    return SETTINGS[name].encode_set(value)


@settings(max_examples=EXAMPLES, deadline=None, database=None, phases=PHASES)
@given(attitude=st.integers(10, 90), freefall=st.integers(1, 9), freefall_time=st.integers(1, 255),
       attitude_on=st.booleans(), freefall_on=st.booleans(), armed=st.booleans(),
       tilt=st.integers(0, 95), accel=st.integers(0, 20), steps=st.lists(_STEP, max_size=4))
@example(attitude=70, freefall=5, freefall_time=160, attitude_on=True, freefall_on=True,
         armed=True, tilt=30, accel=10, steps=[('attitude_threshold_deg', 20),
                                               ('attitude', False)])  # issue 21 item 1
def _no_write_the_rule_lets_through_fires_the_module(
        attitude, freefall, freefall_time, attitude_on, freefall_on, armed, tilt, accel, steps):
    """The settings rule as an invariant, against the module model itself (P21): whatever
    settings, flags, tilt and |a|, a sequence of writes (and an arm) that the rule lets
    through, in the order the driver writes it, never makes the module ask or fire, even after
    the longest free-fall time."""
    _RULE_RUNS.append(steps)
    trigger = Trigger(attitude, freefall, attitude_on, freefall_on)
    # A module already meeting a condition while armed has fired before any write of ours.
    assume(not (armed and conditions(trigger, tilt, accel / 10)))
    ordered = order(steps)
    if would_deploy(trigger, armed, False, tilt, accel / 10, ordered):
        return
    sim = VirtualParachute()
    sim.step(1.0)
    sim.attitude_threshold_deg, sim.freefall_threshold_raw = attitude, freefall
    sim.freefall_time_raw = freefall_time
    sim.attitude_trigger_enabled, sim.freefall_trigger_enabled = attitude_on, freefall_on
    sim.set_tilt(tilt)
    sim.set_accel(accel / 10)
    sim.armed = armed
    now = 1.0
    for step in ordered:
        now += 0.01
        sim.receive(_frame(step), now)
    sim.step(now + 3.0)
    assert sim.requests_sent == 0 and not sim.triggered and sim.deployments == 0, ordered


_RULE_RUNS = []


def test_round2_1_no_write_the_rule_lets_through_fires_the_module():
    """The settings rule over ``UAV_MODEL_EXAMPLES`` generated modules and write sequences."""
    _RULE_RUNS.clear()
    _no_write_the_rule_lets_through_fires_the_module()
    print(f'model_sequences_parachute_settings={len(_RULE_RUNS)} model_violations=0')
    assert len(_RULE_RUNS) >= EXAMPLES
