"""The deploy procedure's safety invariants, searched against the virtual parachute (issue 22).

A hypothesis state machine drives `DeployCore` (``dps_parachute_ros.deploy_core``, no I/O)
against the device model (``dps_parachute_ros.simulation``) in virtual time, through the wire of
``parachute_model_rig``: random interleavings of deploy calls (good and bad token,
``arm_if_locked``), the module armed, locked or deployed by someone else, its igniter failing,
wire faults on each request (the request or the reply dropped, a byte corrupted, the reply past
its deadline, garbage before it), unplug and replug, module reboots (seen, or with their
heartbeats lost; its second heartbeat taken late by a reader that stalled, or lost and another
reboot within 2 s: D3's late heartbeat, as a rule and as wire faults), and a respawned driver (a
new core from the attempts the old one kept). It runs twice: the core on its own, and as the
session runs it (``mirror``: told before each step what the session's threads took in, here a
second core that is never called). After every step:

- at most two deploy frames of one power-up without a successful acknowledgement (P11), across
  reconnects and restarts, and the module never in protection;
- no deploy frame on an armed state not read since the last reboot the driver could know of
  (or the last reconnect) (D15): a heartbeat taken more than 0.2 s after the one before is one
  (D3: a late second heartbeat may be another reboot), and so is any heartbeat of the power-up
  the frame goes to (one taken within 0.2 s of a late heartbeat is taken with it);
- every deploy call answered exactly once;
- never "refused" or "not deployed" when the module deployed during the call, never
  "deployed" when it never deployed; UNKNOWN only when a deploy frame left;
- the decision recorded (synced) and the attempt kept before the deploy frame leaves;
- arming (`~/arm`, an `ArmCall` of the same core, with or without the settings core's check
  passing): every call answered once; "refused" only with no arm or lock frame sent, any
  other answer only with one sent; "armed"/"locked" only when the module is so (or rebooted
  since, which locks it); an arm frame only on a triggered state read as not triggered since
  the last reboot the driver could know of, and only after the check passed; an UNKNOWN
  leaves the armed state unknown (or the truth read since), never a guess; a module that
  answers, is not triggered and has no reboot unseen or still to come can be armed;
- a module that is armed, answers, is below the P11 limit and not triggered is deployed by a
  deploy call with the good token on a clean wire (and no reboot the driver could not see since
  it last read the boot count: until it asks, it cannot know that the module it saw triggered
  was switched off and on, or armed by another path whose status frame was lost).

The search found, for arming: a reboot (a late second heartbeat, D3) taken while the check
ran, after which the arm frame went on the state read before it (the old session did the same);
and a rig that said the frame of a request had not left when only its retry had not.

(The search found that a module deployed by another source while the driver armed it for a
deploy is answered "refused: arming failed: ... the query says locked": true of this call, the
refusal says what the call did, so "refused" is judged against the deployments by the call's
own frames.)

The findings of issue 21 that concern deploy are plain tests below, stepping the core.
"""

from __future__ import annotations

from hypothesis import strategies as st
from hypothesis.stateful import invariant, precondition, rule, RuleBasedStateMachine

import pytest

from dps_parachute_ros.deploy_core import DeployCore, MAX_FAILED_DEPLOYS
from dps_parachute_ros.deploy_knowledge import LATE_HEARTBEAT_EVENT
from model_runs import search
from dps_parachute_ros.release_gate import GateDone
from parachute_model_rig import (ArmRun, Call, FAULTS, HEARTBEAT, JUDGEMENTS, ModelRig,
                                 REBOOT_AFTER_S, REBOOT_KINDS, REBOOT_S, reboot_faults)
from uav_serial_common.core_events import Record
from uav_serial_common.result import Outcome


def deployed_during(call: Call) -> bool:
    """Whether the module deployed during the call (by its frames or another source)."""
    return call.deployments_after > call.deployments_before


def check_call(rig: ModelRig, call: Call) -> None:
    """The truth of one call's answer, judged against the model."""
    assert len(call.answers) == 1, call.answers
    answer = call.answers[0]
    assert not rig.core.busy
    if answer.outcome in ('refused', 'not deployed'):
        # (A deployment by another source during the call, unseen, does not make this
        # call's refusal false: it says what this call did.)
        assert call.serial_deployments == 0, answer.message
    if answer.outcome == 'refused':
        assert call.deploy_frames == 0, answer.message
    assert answer.ok == (answer.outcome in ('deployed', 'already deployed')), answer
    if answer.ok:
        # The parachute is out: it deployed once (a reboot since, unseen, does not undo that).
        assert rig.model.deployments > 0, answer.message
    if answer.outcome == 'deployed':
        assert deployed_during(call) or call.triggered_before or rig.model.triggered, \
            answer.message
    if answer.outcome == 'unknown':
        assert call.deploy_sends > 0, answer.message


def check_arm(rig: ModelRig, call: ArmRun) -> None:
    """The truth of one arm (or lock) call's answer, judged against the model."""
    assert len(call.answers) == 1, call.answers
    result = call.answers[0].result
    assert not rig.core.busy
    assert not call.problems, call.problems
    if result.outcome is Outcome.REFUSED:
        assert call.arm_sends == 0, result.message
    else:
        assert call.arm_sends > 0, result
    if result.outcome is Outcome.DONE:
        # As asked, unless the module rebooted since the call began (a reboot locks it).
        assert rig.model.armed == call.want or rig.model.boot_count != call.boot_before, result
    if result.outcome is Outcome.UNKNOWN:
        # Never a guess kept as known: not known, or the truth read since.
        known = knower(rig)
        assert known.armed is None or known.armed == rig.model.armed, result


def armable(rig: ModelRig) -> bool:
    """Whether an arm call now on a clean wire must arm: the module answers, is not
    triggered, with no reboot unseen or due, and no power-up heartbeat still to come (taken
    during the call, it may be a reboot after the read-back, D3: the answer says UNKNOWN)."""
    return (rig.plugged and rig.model.powered and rig.t >= rig.hold_until
            and rig.reboot_at is None and not rig.unseen_reboot
            and rig.model._second_heartbeat_at is None
            and not rig.model.triggered and not rig.model.protection)


def deployable(rig: ModelRig) -> bool:
    """Whether a deploy call now must deploy: the module armed, answering, not triggered, below
    P11, with nothing unseen since it was read, and no reboot of the module due (a reboot
    during the call locks it)."""
    return (rig.plugged and rig.model.powered and rig.t >= rig.hold_until
            and rig.reboot_at is None
            and not rig.unseen_reboot and not rig.unseen_change
            and not rig.model.igniter_fault
            and rig.model.armed and not rig.model.triggered and not rig.model.protection
            and rig.core.failed < MAX_FAILED_DEPLOYS)


def test_round2_22_3_found_a_module_rebooting_during_the_call_is_refused_as_locked():
    # The search (campaign run of 2026-11-27): a late heartbeat of a reboot, then (within 2 s,
    # D3) another reboot was due; the driver respawned, and its deploy armed the module but
    # the arm reply came late. The module was armed and answered, and the oracle asked that a
    # deploy call deploy it, but the second reboot came during that call: the module it read
    # was locked, and "refused: locked" was true. The oracle now waits for a reboot due.
    rig = ModelRig(armed=True)
    check_call(rig, rig.deploy(faults=['late_heartbeat_reboot']))
    rig.restart_driver()
    check_call(rig, rig.deploy(arm_if_locked=True, faults=['clean', 'clean', 'delay']))
    assert rig.model.armed and rig.reboot_at is not None
    assert not deployable(rig)
    boot = rig.model.boot_count
    call = rig.deploy()
    check_call(rig, call)
    assert rig.model.boot_count == boot + 1 and not rig.model.armed
    assert call.answers[0].outcome == 'refused' and 'locked' in call.answers[0].message
    # Once that reboot is read, a deploy arms and deploys it (the rule the oracle keeps).
    call = rig.deploy(arm_if_locked=True)
    check_call(rig, call)
    assert call.answers[0].outcome == 'deployed', call.answers[0].message


# -- the issue-21 findings that concern deploy, and what the search found ---------------------

def test_round2_22_1_a_deploy_after_an_unplug_does_not_promise_on_old_knowledge():
    rig = ModelRig(armed=True)
    rig.status_frame()  # the driver saw it armed...
    rig.unplug()
    rig.model.armed = False  # ...and someone locked it while unplugged
    rig.replug()
    call = rig.deploy()
    check_call(rig, call)
    assert call.answers[0].outcome == 'refused' and 'locked' in call.answers[0].message
    assert call.deploy_sends == 0 and not rig.order_problems


def test_round2_22_1_a_respawned_driver_cannot_send_a_third_frame_to_the_same_power_up():
    rig = ModelRig(armed=True)
    rig.model.igniter_fault = True  # every attempt fails, unanswered
    call = rig.deploy(faults=['clean', 'clean', 'drop_reply', 'clean', 'clean', 'clean',
                              'drop_reply', 'clean'])
    assert call.deploy_sends == 2 and call.answers[0].outcome == 'not deployed'
    rig.restart_driver()
    assert rig.core.failed == MAX_FAILED_DEPLOYS  # before it read anything of the module
    again = rig.deploy()
    assert again.answers[0].outcome == 'refused' and 'P11' in again.answers[0].message
    assert again.deploy_sends == 0 and not rig.model.protection


def test_round2_22_1_a_respawned_driver_counts_nothing_of_another_power_up():
    rig = ModelRig(armed=True)
    rig.model.igniter_fault = True
    rig.deploy(faults=['clean', 'clean', 'drop_reply', 'clean', 'clean', 'clean', 'drop_reply'])
    rig.model.igniter_fault = False
    rig.power_cycle(quiet=True)
    rig.model.armed = True
    rig.restart_driver()
    call = rig.deploy()
    assert call.answers[0].outcome == 'deployed' and rig.model.triggered


def test_round2_22_1_triggered_seen_after_the_frame_left_is_a_deployment_not_unknown():
    rig = ModelRig(armed=True)
    # The frame deploys it, the acknowledgement is lost, and the link drops while the driver
    # asks whether it is triggered; the status frame that says TRIGGERED came before.
    rig.faults = []
    call = rig.deploy(faults=['clean', 'clean', 'delay', 'unplug_after'])
    answer = call.answers[0]
    assert deployed_during(call)
    assert answer.outcome == 'deployed' and answer.ok, answer.message
    check_call(rig, call)


def test_round2_22_1_a_reboot_after_the_frame_left_is_settled_by_the_trigger_records():
    # Found by the search: the frame deployed the module, its acknowledgement was lost, and
    # the module rebooted before the driver asked: "not triggered" then speaks of the new
    # power-up, and "it did NOT deploy" was false. The trigger records of the power-up the
    # frame went to settle it; unknown when they are not read.
    rig = ModelRig(armed=True)
    call = rig.deploy(faults=['clean', 'clean', 'drop_reply', 'reboot'])
    assert deployed_during(call)
    answer = call.answers[0]
    assert answer.outcome == 'deployed', answer.message
    assert 'trigger records show a serial deployment in boot 8' in answer.message
    check_call(rig, call)
    rig = ModelRig(armed=True)
    call = rig.deploy(faults=['clean', 'clean', 'drop_reply', 'reboot', 'clean', 'clean',
                              'drop_reply'])
    assert deployed_during(call) and call.answers[0].outcome == 'unknown'
    check_call(rig, call)
    # The frame lost on its way, then a reboot: the records show no deployment in that boot.
    rig = ModelRig(armed=True)
    call = rig.deploy(faults=['clean', 'clean', 'drop_request', 'reboot'])
    answer = call.answers[0]
    assert answer.outcome == 'not deployed' and 'did NOT deploy' in answer.message and \
        'locked now' in answer.message, answer.message
    check_call(rig, call)


def test_round2_22_1_a_deploy_reads_the_boot_count_before_its_frame_leaves():
    # Found by the 20,000-sequence search: the stream said armed, the boot count was never
    # read; the frame deployed the module, the acknowledgement was lost, and the module
    # rebooted with its heartbeats lost before the triggered query: the driver said "it did
    # NOT deploy, and it is locked now". The kept sequence, then the same faults one request
    # later (the deploy reads the boot count first now).
    rig = ModelRig(armed=True)
    rig.status_frame()
    call = rig.deploy(faults=['drop_reply', 'reboot_quiet'])
    check_call(rig, call)
    rig = ModelRig(armed=True)
    rig.status_frame()
    call = rig.deploy(faults=['clean', 'clean', 'drop_reply', 'reboot_quiet'])
    assert deployed_during(call)
    answer = call.answers[0]
    assert answer.outcome == 'deployed' and 'rebooted after the deploy frame left' in \
        answer.message, answer.message
    check_call(rig, call)


def test_round2_22_1_an_armed_state_read_before_a_reboot_is_not_taken_as_fresh():
    # Found by the 20,000-sequence search: the re-read's status query went unanswered, the
    # armed query said armed, and the module rebooted (its heartbeat seen) before it answered
    # the triggered query: the driver took the armed state of the power-up before and sent the
    # deploy frame to a module that had not been read since its reboot (D15).
    rig = ModelRig(armed=True)
    rig.power_cycle()
    call = rig.deploy(faults=['clean', 'drop_request', 'drop_request', 'arm_by_other',
                              'reboot'])
    assert not rig.order_problems, rig.order_problems
    assert call.deploy_sends == 0 and call.answers[0].outcome == 'refused'
    check_call(rig, call)


def test_round2_22_1_frames_sent_after_a_reboot_count_for_the_new_power_up():
    # Found by the 20,000-sequence search: the module rebooted as a deploy frame arrived (its
    # heartbeat seen), a status frame said armed again, and two more deploys went out on the
    # old boot count; when the new one was read the driver cleared the count as "another
    # power-up" although both frames had gone to it, and a third frame followed (P11).
    rig = ModelRig(armed=True)
    rig.deploy(faults=['clean', 'clean', 'reboot'])
    rig.model.armed = True
    rig.status_frame()
    rig.deploy(faults=['drop_request'])
    rig.deploy(faults=['drop_reply'])
    assert all(n <= 2 for n in rig.unacked.values()), rig.unacked
    assert not rig.order_problems


def test_round2_22_1_the_records_since_the_frames_power_up_settle_a_reboot_told_late():
    # Found by the 20,000-sequence search: the module rebooted unseen while it was armed for the
    # deploy, the frame deployed it in that new power-up and its acknowledgement was lost, then
    # it rebooted again (seen): the records of the boot the driver knew showed nothing, and it
    # said "did NOT deploy". Any record since that boot settles it.
    rig = ModelRig(armed=True)
    rig.power_cycle()
    call = rig.deploy(arm_if_locked=True, faults=['clean', 'clean', 'reboot_quiet', 'clean',
                                                  'drop_reply', 'reboot'])
    assert deployed_during(call)
    check_call(rig, call)
    assert call.answers[0].outcome == 'deployed', call.answers[0].message


def test_round2_22_1_a_deployment_known_before_the_frame_is_not_the_frames():
    # Found by the search right after the fix above: the module deployed (acknowledged) in
    # boot 8, rebooted unseen; the next deploy's frame was lost and a reboot found: the record
    # of boot 8 is the deployment known before, not this frame's: "did NOT deploy".
    rig = ModelRig(armed=True)
    assert rig.deploy().answers[0].outcome == 'deployed'
    rig.power_cycle(quiet=True)
    rig.status_frame()
    call = rig.deploy(arm_if_locked=True, faults=['clean', 'clean', 'drop_request'])
    check_call(rig, call)
    assert call.answers[0].outcome == 'not deployed', call.answers[0].message


def test_round2_22_1_a_module_silent_to_the_triggered_query_is_read_by_its_status():
    # The frame and the triggered query are lost; the re-read's status says "not triggered"
    # in the same power-up (its boot count, asked again after it, unchanged): a second frame
    # goes (as before the core), then UNKNOWN (P11).
    rig = ModelRig(armed=True)
    call = rig.deploy(faults=['clean', 'clean', 'drop_request', 'drop_request', 'clean',
                              'clean', 'clean', 'drop_request', 'drop_request'])
    check_call(rig, call)
    assert call.deploy_sends == 2 and call.answers[0].outcome == 'unknown', call.answers
    assert rig.core.failed == 2


def test_round2_22_1_another_sources_deployment_unseen_is_not_the_frames():
    # Found by the search (the core as the session runs it): deployed in boot 8; a reboot
    # unseen; another source deployed in boot 9, unseen; another reboot unseen; the next frame
    # was lost and a reboot found. The PWM record of boot 9 is not this frame's deployment.
    rig = ModelRig(armed=True, mirror=True)
    rig.deploy()
    rig.power_cycle(quiet=True)
    rig.model.armed = True
    rig.status_frame()
    rig.model._fire(0x04)
    rig.power_cycle(quiet=True)
    call = rig.deploy(faults=['drop_request'])
    check_call(rig, call)
    assert call.answers[0].outcome != 'deployed', call.answers[0].message


def test_round2_22_1_a_respawned_driver_counts_the_frames_sent_after_a_reboot_unseen():
    # Found by the 20,000-sequence search: the module rebooted unseen (boot 8 -> 9), the
    # driver sent a frame to it on boot count 8 (refused: its igniter failed), kept "boot 8,
    # one frame" and was respawned; reading boot 9 it took the frame for another power-up's,
    # and two more went to boot 9: protection (P11). The frames sent since the last boot count
    # read are kept, and count.
    for mirror in (False, True):
        rig = ModelRig(armed=True, mirror=mirror)
        rig.deploy(faults=['clean', 'reboot_quiet'])
        rig.model.armed = True
        rig.status_frame()
        rig.model.igniter_fault = True
        rig.deploy()
        rig.restart_driver()
        rig.deploy()
        rig.deploy()
        assert all(n <= 2 for n in rig.unacked.values()), (mirror, rig.unacked)
        assert not rig.model.protection


def test_round2_22_1_a_clean_deploy_of_an_armed_module_deploys_it():
    rig = ModelRig(armed=True)
    call = rig.deploy()
    assert call.answers[0].outcome == 'deployed' and rig.model.triggered
    assert not rig.order_problems


@pytest.mark.parametrize('mirror', [False, True])
def test_issue22_found_a_reboot_between_the_boot_count_and_the_status_of_a_retry_is_seen(mirror):
    # The bench-size search: the deploy frame deployed the module and its acknowledgement was
    # lost; the triggered query was lost too. The re-read before a retry asked the boot count
    # (unchanged), then the status, and the module rebooted between the two, its heartbeats
    # lost: "not triggered, locked" came from the next power-up, and the call said "it did NOT
    # deploy". The boot count asked again after the status shows the reboot; the trigger
    # records then tell the deployment.
    rig = ModelRig(armed=True, mirror=mirror)
    call = rig.deploy(faults=['clean', 'clean', 'drop_reply', 'drop_request', 'clean',
                              'reboot_quiet'])
    assert deployed_during(call)
    check_call(rig, call)
    assert call.answers[0].outcome == 'deployed', call.answers[0].message


# -- arming (an ArmCall of the same core) --------------------------------------------------------

@pytest.mark.parametrize('mirror', [False, True])
def test_issue22_arm_and_lock_on_a_clean_wire_are_verified_by_a_query(mirror):
    rig = ModelRig(armed=False, mirror=mirror)
    call = rig.arm(True)
    check_arm(rig, call)
    assert call.answers[0].result.outcome is Outcome.DONE and rig.model.armed
    call = rig.arm(False)
    check_arm(rig, call)
    assert call.answers[0].result.outcome is Outcome.DONE and not rig.model.armed


@pytest.mark.parametrize('judgement, cause', [('would deploy', 'would_deploy'),
                                              ('no answer', 'no_reply')])
def test_issue22_an_arm_the_check_does_not_pass_is_refused_with_nothing_sent(judgement, cause):
    rig = ModelRig(armed=False)
    call = rig.arm(True, judgement=judgement)
    check_arm(rig, call)
    result = call.answers[0].result
    assert result.outcome is Outcome.REFUSED and result.cause == cause, result
    assert call.arm_sends == 0 and not rig.model.armed
    # A lock is never judged: it cannot deploy the module.
    rig.model.armed = True
    call = rig.arm(False, judgement=judgement)
    assert call.answers[0].result.outcome is Outcome.DONE and call.judged == 0


def arm_on_a_read_module(mirror: bool, armed: bool, want: bool, faults: list):
    """Arm (or lock) a module whose state was read, `faults` on its frame first; checked."""
    rig = ModelRig(armed=armed, mirror=mirror)
    rig.status_frame()  # (read: the arm or lock frame is its first request)
    call = rig.arm(want, faults=faults)
    check_arm(rig, call)
    return rig, call


@pytest.mark.parametrize('mirror', [False, True])
def test_issue22_an_arm_whose_reply_was_lost_is_unknown_and_no_deploy_goes_on_a_guess(mirror):
    rig, call = arm_on_a_read_module(mirror, False, True, ['drop_reply', 'drop_reply'])
    result = call.answers[0].result
    assert result.outcome is Outcome.UNKNOWN and result.cause == 'no_reply', result
    assert rig.model.armed and knower(rig).armed is None
    # The next deploy reads the module afresh before its frame (D15).
    deploy = rig.deploy()
    check_call(rig, deploy)
    assert deploy.answers[0].outcome == 'deployed' and not rig.order_problems


@pytest.mark.parametrize('mirror', [False, True])
def test_issue22_found_a_lock_whose_first_frame_left_is_never_said_not_sent(mirror):
    # The search: the lock frame's first attempt was lost on its way, its retry met the port
    # unplugged. "lock not sent" was false of the first: it left, and what it did is unknown.
    _, call = arm_on_a_read_module(mirror, True, False, ['drop_request', 'unplug_before'])
    assert call.answers[0].result.outcome is Outcome.UNKNOWN, call.answers[0].result


@pytest.mark.parametrize('mirror', [False, True])
def test_issue22_found_a_reboot_taken_while_an_arm_is_checked_is_read_before_the_frame(mirror):
    # The search: the module rebooted as the re-read's status query came, and the reader
    # stalled; its late second heartbeat (D3: maybe another reboot) was taken while the
    # settings core's check ran. The arm frame went on the state read before it: the module
    # is read again first, and checked again.
    rig = ModelRig(armed=True, mirror=mirror)
    rig.deploy()
    rig.restart_driver()
    call = rig.arm(True, faults=['clean', 'late_heartbeat'])
    check_arm(rig, call)
    assert call.judged == 2 and call.answers[0].result.outcome is Outcome.DONE


def late_heartbeats(rig: ModelRig) -> int:
    """How many late heartbeats (D3) the core recorded (a mirror core leaves that to the
    session)."""
    return sum(1 for a in rig.actions if isinstance(a, Record)
               and dict(a.fields).get('event') == LATE_HEARTBEAT_EVENT)


def knower(rig: ModelRig) -> DeployCore:
    """The core that keeps what is known of the module (the keeper of a mirror core)."""
    return rig.keeper if rig.keeper is not None else rig.core


@pytest.mark.parametrize('mirror', [False, True])
@pytest.mark.parametrize('stall', [0.3, 1.9])
def test_round2_22_3_a_late_second_heartbeat_leaves_the_armed_state_unknown(mirror, stall):
    # The module reboots and is armed by its switch right away; the reader takes the first
    # heartbeat and the status frame that says armed, then stalls: the second heartbeat is
    # taken `stall` s after the first. The driver cannot tell it from another reboot (D3): the
    # armed state is unknown until read again; a deploy reads it first.
    rig = ModelRig(armed=True, mirror=mirror)
    rig.status_frame()
    rig.wait(REBOOT_S)
    rig.model.power_cycle()
    rig.wait(0.0)  # its first heartbeat: a reboot
    rig.model.armed = True
    rig.status_frame()
    assert knower(rig).armed is True
    rig.hold_until = rig.t + stall
    rig.wait(stall + 0.1)  # its second heartbeat, taken late
    assert knower(rig).armed is None and not knower(rig).fresh
    call = rig.deploy()
    check_call(rig, call)
    assert not rig.order_problems, rig.order_problems
    assert call.answers[0].outcome == 'deployed' and rig.model.triggered


@pytest.mark.parametrize('mirror', [False, True])
@pytest.mark.parametrize('again', [0.3, 1.9])
def test_round2_22_3_a_reboot_that_looks_like_a_late_heartbeat_voids_the_armed_state(mirror,
                                                                                     again):
    # The module reboots (its first heartbeat taken, its second lost), is armed by its switch
    # (a status frame says so) and reboots again `again` s after the first: that power-up's
    # first heartbeat looks like the late second of the one before (D3). It is a reboot as far
    # as a deploy is concerned: the module is locked now, and no frame may go on "armed".
    rig = ModelRig(armed=True, mirror=mirror)
    rig.wait(REBOOT_S)
    rig.model.power_cycle()
    rig.wait(0.0)
    rig._lose_second_heartbeat()
    rig.model.armed = True
    rig.status_frame()
    assert knower(rig).armed is True
    rig.wait(again - 0.06)
    rig.model.power_cycle()
    rig.wait(0.1)
    assert knower(rig).armed is None and not knower(rig).fresh
    call = rig.deploy()
    check_call(rig, call)
    assert not rig.order_problems, rig.order_problems
    assert call.deploy_sends == 0 and call.answers[0].outcome == 'refused', call.answers
    assert 'locked' in call.answers[0].message


@pytest.mark.parametrize('mirror', [False, True])
@pytest.mark.parametrize('fault', ['late_heartbeat', 'late_heartbeat_slow',
                                   'late_heartbeat_reboot', 'lost_heartbeat_reboot'])
@pytest.mark.parametrize('at', [0, 1, 2, 3, 4])
def test_round2_22_3_late_heartbeats_on_each_request_of_a_deploy(mirror, fault, at):
    # The wire faults of D3 on each request of a deploy in turn (the boot count, the status and
    # armed queries, the frame, the triggered query), then the same with the module armed again
    # by its switch and read, and a clean deploy: no frame on an armed state of another
    # power-up, no third unacknowledged frame, every answer true.
    rig = ModelRig(armed=True, mirror=mirror)
    rig.status_frame()
    call = rig.deploy(arm_if_locked=True, faults=['clean'] * at + [fault])
    check_call(rig, call)
    rig.wait(2.0)
    rig.model.armed = True
    rig.status_frame()
    check_call(rig, rig.deploy(faults=['clean'] * at + [fault]))
    rig.wait(2.0)
    check_call(rig, rig.deploy())
    assert not rig.order_problems, rig.order_problems
    assert all(n <= MAX_FAILED_DEPLOYS for n in rig.unacked.values()), rig.unacked
    if fault in rig.applied and fault != 'lost_heartbeat_reboot' and not mirror:
        assert late_heartbeats(rig), rig.actions


@pytest.mark.parametrize('mirror', [False, True])
@pytest.mark.parametrize('change', ['reboot', 'late_heartbeat', 'lock', 'deployed'])
def test_round2_22_3_found_a_change_while_the_deploy_gate_is_passed_is_judged_before_the_frame(
        mirror, change):
    # Found by the 20,000-sequence search once the reader could stall: the frames it held came
    # in while the release gate was passed (a late heartbeat, a status frame saying deployed):
    # the deploy frame left on the armed state read before the gate. Whatever is taken
    # meanwhile is judged before the frame leaves (D15), as the trigger core does (22_7): read
    # afresh, then sent or answered as before the gate.
    rig = ModelRig(armed=True, mirror=mirror)
    if change == 'late_heartbeat':
        rig.wait(REBOOT_S)
        rig.model.power_cycle()
        rig.wait(0.0)  # its first heartbeat: a reboot...
        rig._lose_second_heartbeat()  # ...whose second the reader takes late (below)
        rig.model.armed = True
    rig.status_frame()
    model = rig.model

    def gate(action):
        rig.actions.append(action)
        if change == 'reboot':
            rig.power_cycle()
        elif change == 'late_heartbeat':
            rig.t += 0.5
            rig._run(rig._deliver([(HEARTBEAT, model.boot_count)]))
        elif change == 'lock':
            model.armed = False
            rig.status_frame()
        else:
            model._fire(0x04)
            rig.status_frame()
        return [GateDone(rig.t)]

    rig._gate = gate
    call = rig.deploy(gate=True)
    check_call(rig, call)
    # (Among what they check: no deploy frame on an armed state not read since the last
    # reboot the driver knows of, or may have missed.)
    assert not rig.order_problems, rig.order_problems
    if change == 'late_heartbeat':
        # Still armed, in the same power-up or not: read afresh after the gate, then sent
        # (refusing would fail a deploy the module can take).
        assert call.deploy_sends == 1 and call.answers[0].outcome == 'deployed', call.answers
        return
    assert call.deploy_sends == 0, call.answers
    assert call.answers[0].outcome == ('already deployed' if change == 'deployed' else
                                       'refused'), call.answers


@pytest.mark.parametrize('mirror', [False, True])
def test_round2_22_3_a_request_answered_by_a_frame_the_reader_held_ends_once(mirror):
    # Reported by the 20,000-sequence search, a fault of the rig: the reader's stall ended with
    # the reply to the boot count query and a status frame of the stream; the status query sent
    # on the reply was answered by that frame (as a link matches replies), its own frame left
    # and the module was unplugged: that LinkDown reached the core while it waited for the
    # deploy frame, which never left ("UNKNOWN"). A request ends once: the deploy frame's own
    # send tells the link is down (nothing sent).
    rig = ModelRig(armed=True, mirror=mirror)
    rig.status_frame()
    check_call(rig, rig.deploy(faults=['late_heartbeat_slow']))
    rig.model.armed = True
    rig.status_frame()
    call = rig.deploy(faults=['clean', 'unplug_after'])
    check_call(rig, call)
    assert call.answers[0].outcome == 'refused' and call.deploy_sends == 0, call.answers
    assert not rig.order_problems, rig.order_problems


@pytest.mark.parametrize('mirror', [False, True])
def test_round2_22_3_found_a_respawn_keeps_the_frames_of_a_run_that_never_read_the_boot_count(
        mirror):
    # Found by the 20,000-sequence search: the boot count query was lost, the status said armed
    # (armed by another path), the frame was refused (its igniter failed: P11 counts it); the
    # attempt was kept with no boot count, and the file of attempts wrote nothing without one:
    # the respawned driver started from zero and two more frames put the module into
    # protection. Kept with no boot count now, they count as sent since the last read.
    rig = ModelRig(armed=True, mirror=mirror)
    rig.power_cycle()
    rig.model.igniter_fault = True
    rig.deploy(faults=['drop_request', 'arm_by_other'])
    rig.restart_driver()
    rig.deploy()
    rig.deploy()
    assert all(n <= MAX_FAILED_DEPLOYS for n in rig.unacked.values()), rig.unacked
    assert not rig.model.protection


def test_round2_22_3_the_attempts_of_a_run_that_never_read_the_boot_count_are_kept(tmp_path):
    from dps_parachute_ros.attempts import Attempts, AttemptsFile
    kept = AttemptsFile(str(tmp_path), '/dev/ttyX')
    assert kept.save(None, 1, 0, 1) == ''
    assert AttemptsFile(str(tmp_path), '/dev/ttyX').load() == Attempts('/dev/ttyX', None, 1, 0, 1)


# -- the search -------------------------------------------------------------------------------

class ParachuteDeployModel(RuleBasedStateMachine):
    """A DeployCore against the virtual parachute on a faulty wire, in virtual time."""

    MIRROR = False

    def __init__(self) -> None:
        super().__init__()
        self.rig = ModelRig(armed=True, mirror=self.MIRROR)

    @rule(token=st.sampled_from(['DEPLOY', 'DEPLOY', 'deploy', '']), arm=st.booleans(),
          faults=st.lists(st.sampled_from(FAULTS), max_size=8), gate=st.booleans())
    def deploy(self, token: str, arm: bool, faults: list, gate: bool) -> None:
        call = self.rig.deploy(token, arm, faults, gate)
        check_call(self.rig, call)

    @precondition(lambda self: deployable(self.rig))
    @rule()
    def a_module_that_answers_can_be_deployed(self) -> None:
        call = self.rig.deploy()
        check_call(self.rig, call)
        assert call.answers[0].outcome == 'deployed', call.answers[0].message
        assert self.rig.model.triggered

    @rule(want=st.booleans(), faults=st.lists(st.sampled_from(FAULTS), max_size=6),
          judgement=st.sampled_from(JUDGEMENTS))
    def arm(self, want: bool, faults: list, judgement: str) -> None:
        call = self.rig.arm(want, faults, judgement)
        check_arm(self.rig, call)

    @precondition(lambda self: armable(self.rig))
    @rule()
    def a_module_that_answers_can_be_armed(self) -> None:
        call = self.rig.arm(True)
        check_arm(self.rig, call)
        assert call.answers[0].result.outcome is Outcome.DONE, call.answers[0].result
        assert self.rig.model.armed

    @rule(armed=st.booleans(), seen=st.booleans())
    def someone_else_arms_or_locks(self, armed: bool, seen: bool) -> None:
        """The module armed or locked by another path; `seen`: its status frame reaches us."""
        if not self.rig.model.triggered and self.rig.model.armed != armed:
            self.rig.model.armed = armed
            self.rig.unseen_change = True
            if seen:
                self.rig.status_frame()

    @rule()
    def someone_else_deploys(self) -> None:
        """Another source deploys it (a failed attempt of another source, unseen by the driver,
        would count towards P11 where the driver cannot count it: not modelled)."""
        if self.rig.model._can_fire() and not self.rig.model.igniter_fault:
            self.rig.model._fire(0x04)

    @rule(on=st.booleans())
    def igniter_fault(self, on: bool) -> None:
        """The module's igniter fails: its deploy attempts fail and count towards P11."""
        self.rig.model.igniter_fault = on

    @rule()
    def unplug(self) -> None:
        self.rig.unplug()

    @rule()
    def replug(self) -> None:
        self.rig.replug()

    @rule(kind=st.sampled_from(REBOOT_KINDS), after=st.sampled_from(REBOOT_AFTER_S))
    def module_reboots(self, kind: str, after: float) -> None:
        """The module reboots: its heartbeats seen or lost, or (D3) its second taken `after`
        the first by a reader that stalled, or lost and another reboot `after` the first."""
        self.rig.power_cycle(**reboot_faults(kind, after))

    @rule()
    def driver_restarts(self) -> None:
        self.rig.restart_driver()

    @rule(seconds=st.sampled_from([0.01, 0.1, 0.5, 2.0]))
    def time_passes(self, seconds: float) -> None:
        self.rig.wait(seconds)

    @rule()
    def a_status_frame(self) -> None:
        self.rig.status_frame()

    @invariant()
    def at_most_two_unacknowledged_deploy_frames_per_power_up(self) -> None:
        assert all(n <= MAX_FAILED_DEPLOYS for n in self.rig.unacked.values()), self.rig.unacked
        assert not self.rig.model.protection

    @invariant()
    def every_deploy_frame_on_a_fresh_armed_state_after_its_synced_decision(self) -> None:
        assert not self.rig.order_problems, self.rig.order_problems

    @invariant()
    def every_call_answered_once_and_truly(self) -> None:
        for call in [*self.rig.calls, *self.rig.arm_calls]:
            assert len(call.answers) == 1, call.answers


class ParachuteSessionDeployModel(ParachuteDeployModel):
    """The core as the session runs it (mirror): told what the session's threads took in."""

    MIRROR = True


def test_round2_22_3_parachute_deploy_invariants_hold_over_random_sequences():
    search(ParachuteDeployModel, 'parachute', steps=50)


def test_round2_22_3_the_sessions_deploy_core_keeps_the_invariants_too():
    search(ParachuteSessionDeployModel, 'parachute_session', steps=50)


def test_round2_22_8_a_record_answer_cut_short_never_says_did_not_deploy():
    # The CI run that failed: a loaded host cut a trigger-record answer short. The frame
    # deployed the module, its acknowledgement was lost and the module rebooted; the records
    # answer lost the frame of that deployment: "no serial deployment since boot 8, it did NOT
    # deploy" was false. An answer without every slot's frame tells what it holds, no absence.
    rig = ModelRig(armed=True)
    call = rig.deploy(faults=['clean', 'clean', 'drop_reply', 'reboot'] + ['cut_records'] * 8)
    assert deployed_during(call)
    answer = call.answers[0]
    assert answer.outcome == 'unknown', answer.message
    check_call(rig, call)
