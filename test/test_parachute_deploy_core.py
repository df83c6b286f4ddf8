"""The deploy procedure as a state machine without I/O (issue 22 items 1 and 2): events in,
actions out, stepped by hand in microseconds. No thread, pty, clock or process."""

from __future__ import annotations

import pytest

from dps_parachute_ros import protocol as p
from dps_parachute_ros.deploy_core import (DEPLOY_FRAME, DeployAnswer, DeployCall, DeployCore,
                                           Report, SaveAttempts, Stored)
from dps_parachute_ros.deploy_knowledge import (LATE_HEARTBEAT_EVENT, LATE_HEARTBEAT_S,
                                                MAYBE_REBOOT, PowerUpHeartbeats, REBOOT,
                                                SAME_POWER_UP)
from dps_parachute_ros.release_gate import GateDone, PassGate
from uav_serial_common.core_events import (Busy, LinkDown, LinkUp, Log, Rebooted, Record, Reply,
                                           Request, SYNC_WAIT, Timeout)
from uav_serial_common.core_runner import run_core

T0 = 100.0


def msg(raw: bytes):
    return p.decode_module_bytes(raw)


BOOT = msg(p.module_frame(p.CMD_BOOT_COUNT, 5))
BOOT_6 = msg(p.module_frame(p.CMD_BOOT_COUNT, 6))
ARMED = msg(p.encode_status_frame(0, 10, triggered=False, armed=True))
LOCKED = msg(p.encode_status_frame(0, 10, triggered=False, armed=False))
TRIGGERED = msg(p.encode_status_frame(0, 10, triggered=True, armed=False))
ACK = msg(p.module_frame(p.CMD_DEPLOY, 1))
NACK = msg(p.module_frame(p.CMD_DEPLOY, 0))
NOT_TRIGGERED = msg(p.module_frame(p.CMD_TRIGGERED, 0))


def ready(stored=None) -> DeployCore:
    """A core that has read an armed module of boot 5 (the stream told it)."""
    core = DeployCore(stored)
    core.step(LinkUp(T0))
    core.step(Reply(T0, BOOT))
    core.step(Reply(T0, ARMED))
    assert core.online and core.fresh and core.armed
    return core


def kinds(actions) -> list:
    return [type(a).__name__ for a in actions]


def answer_of(actions) -> DeployAnswer:
    found = [a for a in actions if isinstance(a, DeployAnswer)]
    assert len(found) == 1, actions
    return found[0]


def test_round2_22_1_a_bad_token_is_refused_at_once_and_nothing_is_sent():
    core = ready()
    actions = core.step(DeployCall(T0, 'deploy'))
    assert kinds(actions)[0] == 'Record' and not any(isinstance(a, Request) for a in actions)
    answer = answer_of(actions)
    assert answer.outcome == 'refused' and "confirm must be exactly 'DEPLOY'" in answer.message
    assert not core.busy


def test_round2_22_1_the_decision_is_recorded_and_synced_before_the_deploy_frame_leaves():
    core = ready()
    actions = core.step(DeployCall(T0, 'DEPLOY'))
    assert kinds(actions)[-3:] == ['Record', 'SaveAttempts', 'Request']
    record, save, send = actions[-3:]
    assert record.sync == SYNC_WAIT  # on disk before the next action, not only asked for
    assert dict(record.fields)['what'] == 'deploy: sending the deploy frame'
    assert save == SaveAttempts(5, 1, 1, 1)  # the frame counts before it can leave (P11)
    assert send.frame == DEPLOY_FRAME and send.expect == (p.DeployAck,)
    actions = core.step(Reply(T0 + 0.004, ACK))
    answer = answer_of(actions)
    assert answer.outcome == 'deployed' and answer.ok
    assert answer.message == 'deployed: acknowledged after 1 attempt(s), 4.0 ms'
    assert [a for a in actions if isinstance(a, Report)] == [Report('deploy ack', 5)]
    assert (core.failed, core.unacked, core.armed, core.triggered) == (0, 0, False, True)


def test_round2_22_1_the_release_gate_is_passed_after_every_refusal_and_before_the_frame():
    core = ready()
    actions = core.step(DeployCall(T0, 'DEPLOY', gate=True))
    assert isinstance(actions[-1], PassGate) and not any(isinstance(a, Request) for a in actions)
    actions = core.step(GateDone(T0 + 0.5))
    assert actions[-1].frame == DEPLOY_FRAME
    locked = DeployCore()
    locked.step(LinkUp(T0))
    locked.step(Reply(T0, LOCKED))
    locked.step(Reply(T0, BOOT))
    actions = locked.step(DeployCall(T0, 'DEPLOY', gate=True))
    assert answer_of(actions).outcome == 'refused'
    assert not any(isinstance(a, PassGate) for a in actions)


def test_round2_22_1_a_second_call_while_one_runs_is_refused_and_the_first_goes_on():
    core = ready()
    core.step(DeployCall(T0, 'DEPLOY'))
    second = answer_of(core.step(DeployCall(T0 + 0.001, 'DEPLOY')))
    assert second.outcome == 'refused' and 'still running' in second.message
    assert answer_of(core.step(Reply(T0 + 0.004, ACK))).outcome == 'deployed'


def test_round2_22_1_a_frame_that_never_left_is_not_counted_and_the_call_says_so():
    core = ready()
    core.step(DeployCall(T0, 'DEPLOY'))
    actions = core.step(LinkDown(T0 + 0.001, 'write failed', frame_left=False))
    answer = answer_of(actions)
    assert answer.outcome == 'refused'
    assert answer.message == ('deploy failed before the frame left: write failed; nothing sent')
    assert (core.failed, core.unacked) == (0, 0)


def test_round2_22_1_a_link_down_after_the_frame_left_is_unknown_until_read():
    core = ready()
    core.step(DeployCall(T0, 'DEPLOY'))
    answer = answer_of(core.step(LinkDown(T0 + 0.001, 'unplugged')))
    assert answer.outcome == 'unknown' and not answer.ok
    assert answer.message.startswith('deploy outcome UNKNOWN: 1 deploy frame(s) sent, but the '
                                     'link dropped (unplugged)')
    # Meanwhile a refusal says that an earlier frame's fate is not known.
    refusal = answer_of(core.step(DeployCall(T0 + 1, 'DEPLOY')))
    assert refusal.outcome == 'refused' and 'UNKNOWN (the parachute may have deployed)' in \
        refusal.message
    core.step(LinkUp(T0 + 2))
    actions = core.step(Reply(T0 + 2, TRIGGERED))
    resolved = [dict(a.fields) for a in actions if isinstance(a, Record)]
    assert {'what': 'deploy', 'outcome': 'deployed', 'resolved': 'read after the deploy'} in \
        resolved
    assert not core.outcome_unknown


def test_round2_22_1_a_busy_link_refuses_and_does_not_count_the_frame():
    core = ready()
    core.step(DeployCall(T0, 'DEPLOY'))
    answer = answer_of(core.step(Busy(T0, 'another request for DeployAck is still running')))
    assert answer.message == 'deploy refused: another request for DeployAck is still running'
    assert core.failed == 0


def test_round2_22_1_p11_two_unacknowledged_frames_then_not_deployed_and_a_third_refused():
    core = ready()
    core.step(DeployCall(T0, 'DEPLOY'))
    actions = core.step(Timeout(T0 + 1))
    assert actions[-1].frame == p.encode_triggered_query()
    actions = core.step(Reply(T0 + 1.01, NOT_TRIGGERED))      # then it is read again (D15)
    assert actions[-1].frame == p.encode_boot_count_query()
    core.step(Reply(T0 + 1.02, BOOT))
    actions = core.step(Reply(T0 + 1.03, ARMED))
    assert actions[-1].frame == p.encode_boot_count_query()  # and after its status again
    actions = core.step(Reply(T0 + 1.04, BOOT))
    assert actions[-1].frame == DEPLOY_FRAME                 # the second attempt
    core.step(Timeout(T0 + 2))
    core.step(Reply(T0 + 2.01, NOT_TRIGGERED))
    core.step(Reply(T0 + 2.02, BOOT))
    core.step(Reply(T0 + 2.03, ARMED))
    # The same power-up before and after its status: its "not triggered" holds.
    answer = answer_of(core.step(Reply(T0 + 2.04, BOOT)))
    assert answer.outcome == 'not deployed' and 'P11' in answer.message
    assert (core.failed, core.unacked) == (2, 2)
    third = answer_of(core.step(DeployCall(T0 + 3, 'DEPLOY')))
    assert third.message.startswith('deploy refused: 2 deploy frames in a row went '
                                    'unacknowledged; a third could put the module into '
                                    'protection (P11)')


@pytest.mark.parametrize('boot, failed', [(5, 2), (6, 0)])
def test_round2_22_1_a_new_core_takes_back_the_attempts_of_the_same_power_up_only(boot, failed):
    core = DeployCore(Stored(boot, 2, 2))
    assert core.failed == 2  # counted before anything was read: it may be the same power-up
    core.step(LinkUp(T0))
    core.step(Reply(T0, BOOT))
    assert core.failed == failed


def test_round2_22_1_a_module_refusing_the_frame_but_triggered_is_deployed():
    core = ready()
    core.step(DeployCall(T0, 'DEPLOY'))
    core.step(Reply(T0 + 0.004, NACK))
    answer = answer_of(core.step(Reply(T0 + 0.01, msg(p.module_frame(p.CMD_TRIGGERED, 1)))))
    assert answer.outcome == 'deployed' and answer.ok and 'already triggered' in answer.message


def test_round2_22_2_the_runner_carries_out_actions_in_order_and_feeds_replies_back():
    core = ready()
    seen = []

    def send(action: Request):
        seen.append(action.frame)
        return [Reply(T0 + 0.004, ACK)]

    done = run_core(core, [DeployCall(T0, 'DEPLOY')], {
        Request: send, Record: seen.append, SaveAttempts: seen.append, DeployAnswer: seen.append,
        Report: seen.append, Log: seen.append})
    answers = [a for a in done if isinstance(a, DeployAnswer)]
    assert [a.outcome for a in answers] == ['deployed'] and answers[0] in seen
    assert DEPLOY_FRAME in seen and seen.index(DEPLOY_FRAME) < seen.index(answers[0])


def test_round2_22_2_the_runner_never_drops_an_action_it_has_no_handler_for():
    with pytest.raises(TypeError, match='no handler'):
        run_core(ready(), [DeployCall(T0, 'DEPLOY')], {Record: lambda a: None})


def test_round2_22_which_unsolicited_heartbeats_tell_a_reboot():
    # P5/D3: a power-up sends two heartbeats 50 ms apart. A second one taken late (a stalled
    # reader) may be that pair's or another reboot: handled as a reboot, recorded as neither.
    beats = PowerUpHeartbeats()
    assert beats.take(10.0) == REBOOT
    assert beats.take(10.05) == SAME_POWER_UP
    assert beats.take(20.0) == REBOOT
    assert beats.take(20.4) == MAYBE_REBOOT    # the pair's second, 0.4 s late
    assert beats.take(20.9) == REBOOT          # a third: the pair was complete
    assert beats.take(30.0) == REBOOT
    assert beats.take(30.0 + LATE_HEARTBEAT_S + 0.1) == REBOOT  # too late to be the second
    # The window runs from when the first was handled, not from when it was taken.
    assert beats.take(40.0) == REBOOT
    beats.handled(40.5)
    assert beats.take(40.6) == SAME_POWER_UP


def test_round2_22_3_heartbeats_taken_together_are_one_power_up_only_as_a_first_and_second():
    # Found by the trigger model's search for D3 (a reader that stalled takes the heartbeats
    # of two power-ups together): one within 0.2 s of a late heartbeat may be the first of
    # another power-up (the late one was the pair's second). The window alone took both for
    # the same power-up, and a trigger request of the power-up before, taken in between,
    # stayed pending after it rebooted.
    beats = PowerUpHeartbeats()
    assert beats.take(10.0) == REBOOT
    assert beats.take(10.6) == MAYBE_REBOOT    # the pair's second, late (or another reboot)
    assert beats.take(10.6) == MAYBE_REBOOT    # the next power-up's first (or that one's second)
    assert beats.take(10.65) == MAYBE_REBOOT   # (and so on while they come together)
    # After those, one alone is another power-up, or the late second of the one before: a
    # reboot either way, and the one close after it is no surer.
    assert beats.take(11.2) == REBOOT
    assert beats.take(11.2) == MAYBE_REBOOT
    # A pair surely whole, then one close after it: the module's answer to the driver's
    # heartbeat is the same frame (taken as unsolicited when late): not a reboot.
    assert beats.take(20.0) == REBOOT
    assert beats.take(20.05) == SAME_POWER_UP
    assert beats.take(20.1) == SAME_POWER_UP
    assert beats.take(20.6) == REBOOT          # after a pair: another power-up's first
    assert beats.take(20.65) == SAME_POWER_UP


def test_round2_22_the_core_handles_a_late_heartbeat_as_a_reboot_but_records_none():
    core = ready()
    actions = core.step(Rebooted(T0 + 1.0))
    assert not core.fresh and core.armed is None and not core.boot_current
    assert [a for a in actions if isinstance(a, Record)] == [
        Record.of('state', event='module reboot (unsolicited heartbeat)')]
    core.step(Reply(T0 + 1.1, BOOT_6))
    assert core.boot_current
    actions = core.step(Rebooted(T0 + 1.5))  # the power-up's second, late
    assert not core.fresh and core.armed is None and not core.boot_current
    assert [a for a in actions if isinstance(a, Record)] == [
        Record.of('state', event=LATE_HEARTBEAT_EVENT)]
    actions = core.step(Reply(T0 + 1.6, BOOT_6))  # the same power-up: no reboot
    assert core.boot_current and not any(isinstance(a, Log) for a in actions)
