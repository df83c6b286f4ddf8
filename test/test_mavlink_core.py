"""The autopilot link's core (parachute_mavlink_ros.core): pure, on a clock the test turns."""

from __future__ import annotations

from typing import List

from parachute_mavlink_ros import core as c
import pytest

AP = c.Heartbeat(1, 1, 2, 12)   # a PX4 quadrotor, system 1


class Clock:
    """A core on a test clock; every action it returned, with its time."""

    def __init__(self, **config) -> None:
        self.now = 100.0
        self.core = c.LinkCore(c.CoreConfig(**config), self.now)
        self.actions: List[tuple] = []
        self.advance(0.0)

    def feed(self, event, after: float = 0.0) -> list:
        self.advance(after)
        out = self.core.handle(event, self.now)
        self.actions += [(self.now, a) for a in out]
        return out

    def advance(self, seconds: float) -> None:
        """Let time pass, ticking at every deadline the core asks for."""
        end = self.now + seconds
        while True:
            deadline = self.core.next_deadline()
            if deadline > end:
                break
            self.now = max(self.now, deadline)
            self.actions += [(self.now, a) for a in self.core.handle(c.Tick(), self.now)]
        self.now = end

    def sent(self, kind: str, since: int = 0, **match) -> list:
        return [a for _, a in self.actions[since:] if isinstance(a, c.Send) and a.kind == kind
                and all(a.fields.get(k) == v for k, v in match.items())]

    def of(self, cls, since: int = 0) -> list:
        return [a for _, a in self.actions[since:] if isinstance(a, cls)]

    def mark(self) -> int:
        return len(self.actions)


def command(action: float, target=(1, 161), sender=(255, 190), confirmation=0,
            kind='COMMAND_LONG') -> c.Command:
    return c.Command(sender[0], sender[1], target[0], target[1], c.MAV_CMD_DO_PARACHUTE,
                     (float(action), 0, 0, 0, 0, 0, 0), confirmation, kind)


def ready(clock: Clock, armed: bool = True) -> None:
    """Autopilot heard, module online, preflight passing."""
    clock.feed(AP)
    clock.feed(c.ParachuteState(True, armed, False))
    call = [a for a in clock.of(c.Call) if a.service == 'preflight_check'][-1]
    lines = ('OK   online: answers\nOK   not triggered: no\n'
             + ('OK   armed: armed' if armed else 'FAIL armed: LOCKED: arm it with ~/arm'))
    clock.feed(c.Answer(call.call_id, armed, lines))


def test_round2_23_heartbeat_status_follows_the_parachute_node():
    clock = Clock()
    beats = clock.sent('heartbeat')
    assert beats and beats[0].fields['system_status'] == c.MAV_STATE_UNINIT
    assert beats[0].fields['type'] == c.MAV_TYPE_PARACHUTE
    assert beats[0].fields['autopilot'] == c.MAV_AUTOPILOT_INVALID
    clock.advance(5.0)
    assert len(clock.sent('heartbeat')) == 6  # 1 Hz
    ready(clock, armed=False)
    assert clock.core.system_status() == c.MAV_STATE_STANDBY
    ready(clock, armed=True)
    assert clock.core.system_status() == c.MAV_STATE_ACTIVE
    mark = clock.mark()
    clock.advance(1.0)
    assert clock.sent('heartbeat', mark)[-1].fields['system_status'] == c.MAV_STATE_ACTIVE
    clock.advance(10.0)  # the periodic preflight check
    call = [a for a in clock.of(c.Call) if a.service == 'preflight_check'][-1]
    clock.feed(c.Answer(call.call_id, False, 'FAIL battery: 3.2 V on battery\nOK   armed: ok'))
    assert clock.core.system_status() == c.MAV_STATE_CRITICAL
    assert any('battery' in s.fields['text'] for s in clock.sent('statustext', mark))
    clock.feed(c.ParachuteState(False, True, False))
    assert clock.core.system_status() == c.MAV_STATE_CRITICAL
    assert any('OFFLINE' in s.fields['text'] for s in clock.sent('statustext', mark))
    clock.feed(c.ParachuteState(True, True, True))
    assert clock.core.system_status() == c.MAV_STATE_EMERGENCY


def test_round2_23_preflight_failures_found_while_locked_are_said_once_armed():
    # (test_mavlink_link, campaign s11d run 3: the periodic check found the empty battery
    # while the module was locked; the check after the arm found the same, and nothing was said.)
    clock = Clock()
    ready(clock, armed=False)
    clock.advance(10.0)  # the periodic preflight check, while locked
    call = [a for a in clock.of(c.Call) if a.service == 'preflight_check'][-1]
    clock.feed(c.Answer(call.call_id, False, 'FAIL battery: 3.2 V on battery\n'
                                             'FAIL armed: LOCKED: arm it with ~/arm'))
    mark = clock.mark()
    assert not clock.sent('statustext', mark)
    clock.feed(c.ParachuteState(True, True, False))  # armed: checked again
    call = [a for a in clock.of(c.Call) if a.service == 'preflight_check'][-1]
    clock.feed(c.Answer(call.call_id, False, 'FAIL battery: 3.2 V on battery\nOK   armed: ok'))
    texts = [s.fields['text'] for s in clock.sent('statustext', mark)]
    assert len([t for t in texts if 'preflight FAIL' in t and 'battery' in t]) == 1, texts
    assert clock.core.system_status() == c.MAV_STATE_CRITICAL
    # Said once: the next periodic check with the same failures says nothing more.
    mark = clock.mark()
    clock.advance(10.0)
    call = [a for a in clock.of(c.Call) if a.service == 'preflight_check'][-1]
    clock.feed(c.Answer(call.call_id, False, 'FAIL battery: 3.2 V on battery\nOK   armed: ok'))
    assert not [s for s in clock.sent('statustext', mark) if 'preflight' in s.fields['text']]


def test_round2_23_system_id_zero_sends_nothing_until_an_autopilot_heartbeat():
    clock = Clock(system_id=0)
    clock.advance(5.0)
    clock.feed(c.Heartbeat(7, 190, c.MAV_TYPE_GCS, c.MAV_AUTOPILOT_INVALID))  # a GCS
    clock.feed(command(c.PARACHUTE_RELEASE, target=(0, 0)))
    assert clock.of(c.Send) == [] and clock.of(c.Call) == []
    clock.feed(c.Heartbeat(42, 1, 2, 12))
    beats = clock.sent('heartbeat')
    assert beats and clock.core.sysid == 42


def test_round2_23_a_second_autopilot_is_ignored_and_logged_once():
    clock = Clock()
    clock.feed(AP)
    for _ in range(3):
        clock.feed(c.Heartbeat(9, 1, 2, 3))
    logs = [a for a in clock.of(c.Log) if 'system id 9' in a.text]
    assert len(logs) == 1
    assert clock.core.autopilot == (1, 1) and clock.core.ignored_autopilots == {9: 3}


@pytest.mark.parametrize('target', [(1, 1), (2, 161), (1, 100)])
def test_round2_23_commands_for_other_components_are_ignored(target):
    clock = Clock()
    ready(clock)
    mark = clock.mark()
    clock.feed(command(c.PARACHUTE_RELEASE, target=target))
    clock.advance(1.0)
    assert clock.sent('command_ack', mark) == [] and \
        [a for a in clock.of(c.Call, mark) if a.service == 'deploy'] == []
    assert clock.core.counts['ignored'] == 1


@pytest.mark.parametrize('kind', ['COMMAND_LONG', 'COMMAND_INT'])
@pytest.mark.parametrize('target', [(1, 161), (1, 0), (0, 0)])
def test_round2_23_release_acks_in_progress_then_accepted_and_one_deploy(kind, target):
    clock = Clock()
    ready(clock)
    mark = clock.mark()
    clock.feed(command(c.PARACHUTE_RELEASE, target=target, kind=kind))
    deploys = [a for a in clock.of(c.Call, mark) if a.service == 'deploy']
    assert len(deploys) == 1 and deploys[0].args == {'arm_if_locked': False}
    assert clock.sent('command_ack', mark) == []  # nothing before 100 ms
    clock.advance(0.12)
    acks = clock.sent('command_ack', mark)
    assert [a.fields['result'] for a in acks] == [c.MAV_RESULT_IN_PROGRESS]
    assert acks[0].fields['target_system'] == 255 and acks[0].fields['target_component'] == 190
    for n in (1, 2, 3):  # retransmissions
        clock.feed(command(c.PARACHUTE_RELEASE, target=target, kind=kind, confirmation=n), 0.05)
    assert len([a for a in clock.of(c.Call, mark) if a.service == 'deploy']) == 1
    clock.feed(c.Answer(deploys[0].call_id, True, 'deployed: acknowledged after 1 attempt(s)'))
    results = [a.fields['result'] for a in clock.sent('command_ack', mark)]
    assert results == [c.MAV_RESULT_IN_PROGRESS] * 4 + [c.MAV_RESULT_ACCEPTED]


def test_round2_23_a_fast_answer_gets_only_the_final_ack():
    clock = Clock()
    ready(clock)
    mark = clock.mark()
    clock.feed(command(c.PARACHUTE_ENABLE))
    arm = [a for a in clock.of(c.Call, mark) if a.service == 'arm'][0]
    assert arm.args == {'data': True}
    clock.feed(c.Answer(arm.call_id, True, 'armed (verified by query)'), 0.02)
    assert [a.fields['result'] for a in clock.sent('command_ack', mark)] == \
        [c.MAV_RESULT_ACCEPTED]
    # its ACK was lost: the retransmission gets the same answer, without a second call
    clock.feed(command(c.PARACHUTE_ENABLE, confirmation=1), 0.5)
    assert [a.fields['result'] for a in clock.sent('command_ack', mark)] == \
        [c.MAV_RESULT_ACCEPTED] * 2
    assert len([a for a in clock.of(c.Call, mark) if a.service == 'arm']) == 1


@pytest.mark.parametrize('success,message,result,reason', [
    (False, 'deploy refused: the module is locked (a locked module cannot deploy); arm it '
     'with ~/arm or set arm_if_locked; nothing sent', c.MAV_RESULT_DENIED, c.REASON_LOCKED),
    (False, 'deploy refused: module offline (no reply for 1.0 s); nothing sent',
     c.MAV_RESULT_DENIED, c.REASON_OFFLINE),
    (False, 'deploy outcome UNKNOWN: 1 deploy frame(s) sent, but the link dropped',
     c.MAV_RESULT_FAILED, c.REASON_OUTCOME_UNKNOWN),
    (False, 'the module answered 5a and reports it is not triggered: it did NOT deploy',
     c.MAV_RESULT_FAILED, c.REASON_NOT_DONE),
    (True, 'already deployed: the module reports triggered; nothing sent',
     c.MAV_RESULT_ACCEPTED, c.REASON_ALREADY_DEPLOYED),
    (None, '/parachute/deploy is not available', c.MAV_RESULT_DENIED,
     c.REASON_NO_PARACHUTE_NODE),
    (None, 'no answer from /parachute/deploy', c.MAV_RESULT_FAILED, c.REASON_NO_ANSWER),
])
def test_round2_23_results_say_what_the_parachute_node_did(success, message, result, reason):
    clock = Clock()
    ready(clock)
    mark = clock.mark()
    clock.feed(command(c.PARACHUTE_RELEASE))
    call = [a for a in clock.of(c.Call, mark) if a.service == 'deploy'][0]
    clock.feed(c.Answer(call.call_id, success, message), 0.01)
    ack = clock.sent('command_ack', mark)[-1].fields
    assert (ack['result'], ack['result_param2']) == (result, reason)
    if result != c.MAV_RESULT_ACCEPTED:
        assert clock.sent('statustext', mark)


def test_round2_23_unsupported_action_and_busy():
    clock = Clock()
    ready(clock)
    mark = clock.mark()
    clock.feed(command(3))
    ack = clock.sent('command_ack', mark)[-1].fields
    assert (ack['result'], ack['result_param2']) == (c.MAV_RESULT_UNSUPPORTED,
                                                     c.REASON_UNSUPPORTED_ACTION)
    clock.feed(command(c.PARACHUTE_RELEASE))
    clock.feed(command(c.PARACHUTE_DISABLE, sender=(255, 191)))
    ack = clock.sent('command_ack', mark)[-1].fields
    assert (ack['result'], ack['result_param2']) == (c.MAV_RESULT_DENIED, c.REASON_BUSY)
    assert [a.service for a in clock.of(c.Call, mark)] == ['deploy']


def test_round2_23_parachute_node_silent_gives_failed_not_a_hang():
    clock = Clock(deploy_answer_s=2.0)
    ready(clock)
    mark = clock.mark()
    clock.feed(command(c.PARACHUTE_RELEASE))
    clock.advance(2.5)
    results = [a.fields['result'] for a in clock.sent('command_ack', mark)]
    assert results == [c.MAV_RESULT_IN_PROGRESS, c.MAV_RESULT_FAILED]


def gate(clock: Clock) -> int:
    gate_id = clock.core.new_id()
    clock.feed(c.GateRequest(gate_id))
    return gate_id


@pytest.mark.parametrize('mode,command_id,params', [
    ('disarm', c.MAV_CMD_COMPONENT_ARM_DISARM, (0.0, c.FORCE_DISARM)),
    ('terminate', c.MAV_CMD_DO_FLIGHTTERMINATION, (1.0, 0.0))])
def test_round2_23_gate_stops_motors_and_answers_on_the_ack(mode, command_id, params):
    clock = Clock(stop_motors_before_release=mode)
    ready(clock)
    mark = clock.mark()
    gate_id = gate(clock)
    stops = clock.sent('command_long', mark, command=command_id)
    assert len(stops) == 1
    assert (stops[0].fields['param1'], stops[0].fields['param2']) == params
    assert (stops[0].fields['target_system'], stops[0].fields['target_component']) == (1, 1)
    assert clock.of(c.AnswerGate, mark) == []
    clock.feed(c.Ack(1, 1, command_id, c.MAV_RESULT_ACCEPTED, 1, 161), 0.03)
    answers = clock.of(c.AnswerGate, mark)
    assert len(answers) == 1 and answers[0].gate_id == gate_id and answers[0].stopped


def test_round2_23_gate_without_an_ack_answers_at_motor_stop_wait():
    clock = Clock(motor_stop_wait_s=0.3)
    ready(clock)
    mark = clock.mark()
    gate(clock)
    clock.advance(0.29)
    assert clock.of(c.AnswerGate, mark) == []
    assert len(clock.sent('command_long', mark)) == 3  # resent every 100 ms
    clock.advance(0.02)
    answers = clock.of(c.AnswerGate, mark)
    assert len(answers) == 1 and not answers[0].stopped
    assert any('NOT confirmed' in s.fields['text'] for s in clock.sent('statustext', mark))


def test_round2_23_gate_refused_answers_at_once_and_off_sends_nothing():
    clock = Clock()
    ready(clock)
    mark = clock.mark()
    gate(clock)
    gate(clock)  # a second release at the same time shares the stop
    clock.feed(c.Ack(1, 1, c.MAV_CMD_COMPONENT_ARM_DISARM, c.MAV_RESULT_DENIED), 0.01)
    answers = clock.of(c.AnswerGate, mark)
    assert len(answers) == 2 and not any(a.stopped for a in answers)
    assert len(clock.sent('command_long', mark)) == 1
    off = Clock(stop_motors_before_release='off')
    ready(off)
    mark = off.mark()
    gate(off)
    assert off.sent('command_long', mark) == [] and off.of(c.AnswerGate, mark)[0].stopped


def test_round2_23_gate_with_a_silent_autopilot_does_not_wait():
    clock = Clock()
    ready(clock)
    clock.advance(3.5)
    assert clock.core.autopilot_lost
    mark = clock.mark()
    gate(clock)
    assert len(clock.sent('command_long', mark)) == 1
    assert len(clock.of(c.AnswerGate, mark)) == 1


def test_round2_23_handset_return_to_home_once_per_transition():
    clock = Clock(handset_failsafe_to_autopilot=True)
    ready(clock)
    mark = clock.mark()
    clock.feed(c.Failsafe('NONE'))
    clock.feed(c.Failsafe('RETURN_TO_HOME', 'link lost'))
    clock.feed(c.Failsafe('RETURN_TO_HOME', 'link lost; battery low'))
    clock.feed(c.Ack(1, 1, c.MAV_CMD_NAV_RETURN_TO_LAUNCH, c.MAV_RESULT_ACCEPTED), 0.05)
    clock.advance(5.0)
    assert len(clock.sent('command_long', mark, command=c.MAV_CMD_NAV_RETURN_TO_LAUNCH)) == 1
    assert any('RETURN_TO_LAUNCH' in a.text and 'ACCEPTED' in a.text
               for a in clock.of(c.Log, mark))
    clock.feed(c.Failsafe('NONE'))
    clock.feed(c.Failsafe('RETURN_TO_HOME', 'link lost'))
    assert len(clock.sent('command_long', mark, command=c.MAV_CMD_NAV_RETURN_TO_LAUNCH)) == 2
    off = Clock()
    ready(off)
    mark = off.mark()
    off.feed(c.Failsafe('RETURN_TO_HOME', 'link lost'))
    assert off.sent('command_long', mark) == []


def test_round2_23_statustext_for_deployment_and_trigger_requests():
    clock = Clock()
    ready(clock)
    mark = clock.mark()
    clock.feed(c.RequestDecided('confirmed', 'policy confirm'))
    clock.feed(c.Deployed('freefall'))
    texts = [s.fields for s in clock.sent('statustext', mark)]
    assert any('freefall' in t['text'] and t['severity'] == 0 for t in texts)
    assert all(len(t['text']) <= c.STATUSTEXT_LEN for t in texts)


def test_round2_23_bad_data_and_floods_never_raise():
    clock = Clock()
    ready(clock)
    for i in range(2000):
        clock.feed(c.BadData('junk'))
        clock.feed(command(i % 5, sender=(200 + i % 3, 1), confirmation=i % 7))
        clock.feed(c.Command(1, 1, 1, 161, c.MAV_CMD_DO_PARACHUTE, (), 0))
        clock.feed(c.Command(1, 1, 1, 161, c.MAV_CMD_DO_PARACHUTE, (float('nan'),), 0))
    deploys = [a for a in clock.of(c.Call) if a.service == 'deploy']
    assert len(deploys) == 1  # one RELEASE runs; every other joins it
    assert clock.core.counts['bad_data'] == 2000


class _GateClock:
    def __init__(self) -> None:
        self.t = 50.0
        self.records: list = []
        self.logs: list = []
        self.timeouts: list = []

    def record(self, kind, **fields) -> None:
        self.records.append(fields)

    def log(self, level, text) -> None:
        self.logs.append((level, text))


def test_round2_23_release_gate_never_outlives_the_modules_window_nor_stops_a_release():
    from dps_parachute_ros.release_gate import ReleaseGate, WINDOW_MARGIN_S
    g = _GateClock()

    def call(timeout):
        g.timeouts.append(timeout)
        g.t += timeout
        return None, 'no answer'
    gate = ReleaseGate('gate', call, 0.5, g.record, g.log, clock=lambda: g.t)
    gate.before_release('deploy')
    assert g.timeouts == [0.5]
    t_request = g.t - 0.4  # a trigger request 0.4 s old
    gate.before_release('trigger request', t_request)
    assert g.timeouts[-1] == pytest.approx(1.0 - WINDOW_MARGIN_S - 0.4)
    # The record says how long the gate was given and waited (the tests' proof of a full wait).
    assert g.records[-1]['timeout_ms'] == pytest.approx(g.timeouts[-1] * 1000.0)
    assert g.records[-1]['wait_ms'] == pytest.approx(g.timeouts[-1] * 1000.0)
    assert g.t - t_request <= 1.0 - WINDOW_MARGIN_S + 1e-9
    gate.before_release('trigger request', g.t - 0.9)  # no time left: not called
    assert len(g.timeouts) == 2 and g.records[-1]['called'] is False

    def broken(timeout):
        raise RuntimeError('boom')
    ReleaseGate('gate', broken, 0.5, g.record, g.log, clock=lambda: g.t).before_release('deploy')
    assert g.records[-1]['answered'] is False and 'boom' in g.records[-1]['message']
    assert all(level == 'error' for level, _ in g.logs)

    def broken_record(kind, **fields):
        raise OSError('disk gone')
    ReleaseGate('gate', call, 0.5, broken_record, g.log,
                clock=lambda: g.t).before_release('deploy')  # returns: the release goes on
    assert 'disk gone' in g.logs[-1][1]


def test_round2_23_other_commands_to_us_alone_are_unsupported_broadcasts_ignored():
    clock = Clock()
    ready(clock)
    mark = clock.mark()
    clock.feed(c.Command(255, 190, 1, 161, 512, (245.0,), 0))   # REQUEST_MESSAGE to us
    clock.feed(c.Command(255, 190, 0, 0, 512, (245.0,), 0))     # broadcast: not ours to answer
    acks = clock.sent('command_ack', mark)
    assert [(a.fields['command'], a.fields['result']) for a in acks] == \
        [(512, c.MAV_RESULT_UNSUPPORTED)]


def test_round2_23_release_gate_never_seen_is_no_gate_at_all_and_one_gone_is_said():
    from dps_parachute_ros.release_gate import ReleaseGate
    g = _GateClock()
    ready = [False]

    def call(timeout):
        g.timeouts.append(timeout)
        return True, 'motors stopped'
    gate = ReleaseGate('parachute_mavlink/release_gate', call, 0.5, g.record, g.log,
                       clock=lambda: g.t, ready=lambda: ready[0])
    assert not gate.available('trigger request')
    gate.before_release('deploy')
    assert (g.timeouts, g.records, g.logs) == ([], [], [])  # exactly as without a gate
    ready[0] = True
    gate.before_release('deploy')
    assert g.timeouts == [0.5] and g.records[-1]['success'] is True
    ready[0] = False
    gate.before_release('deploy')
    assert g.records[-1]['called'] is False and 'gone' in g.records[-1]['reason']
    assert g.logs[-1][0] == 'error'
