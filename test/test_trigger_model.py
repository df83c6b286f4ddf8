"""The trigger-request policy's invariants, searched against the virtual parachute (issue 22).

A hypothesis state machine drives `TriggerCore` (``dps_parachute_ros.trigger_core``, no I/O)
against the device model (``dps_parachute_ros.simulation``, `VirtualParachute`) in virtual time:
the module asks (tilted past its threshold on external power) and deploys on a confirmation
within its 1 s window. Random interleavings of requests, answers true and false, policy and
``defer_timeout_s`` changes mid-request, a release gate and its delays (past the window too, a
loaded host), module reboots (seen, or with their heartbeats lost; its second heartbeat taken late
by a reader that stalled, or lost and another reboot within 2 s: D3), the module armed or locked by
another path, unplug and replug, status reads, time passing with the monitor on time or late.
After every step:

- a confirmation leaves only while the policy says ``confirm``, or ``defer`` with a true answer
  given before the request's defer deadline; never while it says ``deny``; never after a reboot
  the driver could know of since the request (a heartbeat taken more than 0.2 s after the one
  before: D3's late heartbeat may be another reboot; or one of a later power-up); never 1 s or
  more after it; never for a request already decided;
- the module deploys on a request only on the confirmation the core sent for that request;
- every request gets at most one decision, "confirmed" exactly when its confirmation left (and
  then within the window); at the end of a sequence (every gate passed, every deadline over),
  exactly one;
- every answer call gets exactly one answer once its gate is passed, SENT exactly when its
  confirmation left;
- ``pending_request`` is true exactly while a request is held for an answer.

(One trigger event per deployment is the deployment events' rule, not this core's: it
publishes no deployment.) What the search found is kept as the named tests below; each was a
hole of the session before the core, kept at pty level in test/test_parachute_core.py too.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple, Type

from hypothesis import HealthCheck, Phase, seed, settings
from hypothesis.internal.conjecture import providers
from hypothesis import strategies as st
from hypothesis.stateful import (initialize, invariant, precondition, rule,
                                 RuleBasedStateMachine, run_state_machine_as_test)
import pytest

from dps_parachute_ros import protocol as p
from dps_parachute_ros.deploy_knowledge import PowerUpHeartbeats, SAME_POWER_UP
from dps_parachute_ros.simulation import VirtualParachute
from dps_parachute_ros.state import MODULE_WINDOW_S
from dps_parachute_ros.release_gate import GateDone, PassGate
from dps_parachute_ros.trigger_core import (
    AnswerCall, Decide, NotSent, Pending, PolicyChanged, RequestReceived, Sent, SetTimer, Stopped,
    Tick, TriggerCore, Write)
from model_runs import EXAMPLES, search
from parachute_model_rig import REBOOT_AFTER_S, REBOOT_KINDS, reboot_faults
from uav_serial_common.core_events import Answer, LinkDown, LinkUp, Log, Rebooted, Record
from uav_serial_common.core_runner import run_core
from uav_serial_common.result import Outcome, Result

START = 1000.0
SLICE = 0.05
"""Virtual time moves in steps of at most this (the model's frames reach the core then)."""
REBOOT_S = 0.3
POWER_UP_HEARTBEATS_S = 0.2
HEARTBEAT = p.encode_module_heartbeat()


@dataclass
class Seen:
    """A trigger request the core was told of, and what became of it."""

    t: float
    defer_s: float                      # in force when it came: its deadline is t + defer_s
    model_t: Optional[float]            # the module's own time of the request
    boot: int                           # the module's boot count then
    voided_at: Optional[float] = None   # a reboot the core was told of after it
    answered_true_at: Optional[float] = None
    decisions: List[Decide] = field(default_factory=list)
    sent_at: Optional[float] = None


@dataclass
class CallRec:
    """One ``~/answer_trigger_request`` call."""

    confirm: bool
    t: float
    answers: List[Result] = field(default_factory=list)
    sends: int = 0
    gate_open: bool = False


class TriggerRig:
    """The core, the module model and the wire between them, in virtual time."""

    def __init__(self, policy: str = 'confirm', defer_s: float = 0.8,
                 core: Type[TriggerCore] = TriggerCore) -> None:
        self.t = START
        self.model = VirtualParachute(now=START - 1.0, boot_count=7)
        self.model.step(START)  # its power-up heartbeats went by before the driver started
        self.model.armed = True
        self.core = core(policy, defer_s)
        self.policy, self.defer_s = policy, defer_s
        self.policy_before = policy
        self.plugged = True
        self.gate_on, self.gate_delay = False, 0.1
        self.gates: List[Tuple[float, PassGate, Optional[CallRec]]] = []
        self.seen: Dict[float, Seen] = {}
        self.calls: List[CallRec] = []
        self.active: Optional[CallRec] = None
        self.problems: List[str] = []
        self.known: Dict[str, Any] = dict(online=True, triggered=False, armed=True, fresh=True)
        self.pending = False
        self.unseen = False  # the module changed (locked, rebooted) since the driver read it
        self.last_heartbeat = -1e9
        self.last_boot = -1e9
        self.power_ups = PowerUpHeartbeats()  # the session's rule (D3): which tell a reboot
        # A reader that stalls: what the module sent meanwhile, with its power-up and pending
        # request, taken in order when it ends.
        self.held: List[Tuple[bytes, int, Any]] = []
        self.hold_until = -1e9
        self.confirmed_deployments = 0
        self.monitor_lag = 0.0  # how late the monitor's tick comes after a deadline
        self.decoder = p.StreamDecoder('from_module')

    # -- stepping the core --------------------------------------------------------------------

    def step(self, event: Any) -> List[Any]:
        """Step the core as the session does: told what is known of the module first."""
        self.core.know(self.known['online'], 'module offline (unplugged)' if not
                       self.known['online'] else '', self.known['triggered'],
                       self.known['armed'], self.known['fresh'])
        return self.core.step(event)

    def run(self, event: Any, call: Optional[CallRec] = None) -> None:
        before, self.active = self.active, call
        try:
            run_core(self, [event], {
                Write: self._send, PassGate: self._gate, Decide: self._decide,
                Answer: self._answer, Pending: self._pending, Record: lambda a: None,
                Log: lambda a: None, SetTimer: lambda a: None})
        finally:
            self.active = before
        if self.pending != self.core.pending:
            self.problems.append('pending_request differs from the core')

    # -- what a test does ---------------------------------------------------------------------

    def can_ask(self) -> bool:
        """Whether the module can ask now (not deployed, in protection, or asking)."""
        m = self.model
        return m.powered and not m.triggered and not m.protection and not m.pending_request

    def ask(self) -> bool:
        """Arm the module (by its switch, say) and tilt it past its threshold: it asks.

        False: it cannot now (deployed, in protection, or a request of its own still open).
        """
        m = self.model
        self.from_model()
        if not (m.powered and not m.triggered and not m.protection and not m.pending_request):
            return False
        if self.t in self.seen:
            self.wait(0.001)  # (one request per instant: they are told apart by their time)
            if m.triggered or m.pending_request:
                return False
        m.set_tilt(0.0)  # (unlatch its attitude trigger)
        if not m.armed:
            m.armed = True
            self.unseen = True
        m.set_tilt(85.0)
        self.from_model()
        return True

    def answer(self, confirm: bool) -> CallRec:
        call = CallRec(confirm, self.t)
        self.calls.append(call)
        if confirm and self.core.pending:
            held = [s for s in self.seen.values() if not s.decisions and s.sent_at is None]
            if held:
                held[-1].answered_true_at = self.t
        self.run(AnswerCall(self.t, confirm, self.gate_on), call)
        return call

    def set_policy(self, policy: str, defer_s: Optional[float] = None) -> None:
        # (A deadline passed before the change is decided under the policy before it.)
        self.policy_before, self.policy = self.policy, policy
        self.defer_s = self.defer_s if defer_s is None else defer_s
        self.run(PolicyChanged(self.t, policy, self.defer_s, self.gate_on))
        self.policy_before = policy

    def reboot(self, quiet: bool = False, late_s: float = 0.0,
               again_s: Optional[float] = None) -> None:
        """Power-cycle the module (boot count +1, locked); `quiet`: its heartbeats lost.

        `late_s`: its first heartbeat is taken, then the reader stalls that long (the second
        is taken late, D3). `again_s`: its first heartbeat is taken, its second lost, and it
        reboots again that long after (that first heartbeat looks like a late second).
        """
        # (Two power-ups' heartbeats closer than 0.2 s would be taken for one, P5.)
        self.wait(max(0.0, max(self.last_heartbeat, self.last_boot) + REBOOT_S - self.t))
        self.model.power_cycle()
        self.last_boot = self.t
        if quiet:
            self.model.step(self.t + 0.06)  # both heartbeats, lost on the wire
            self.t += 0.06
            self.unseen = True
        elif late_s or again_s is not None:
            self.from_model()  # its first heartbeat
            if late_s and self.t >= self.hold_until:
                # (A stall going on is not made longer: no heartbeat is taken more than
                # LATE_HEARTBEAT_S after the one before, the rule's bound, D3.)
                self.hold_until = self.t + late_s
            if again_s is not None:
                self.lose_second_heartbeat()
                self.wait(again_s - 0.06)
                self.model.power_cycle()
                self.last_boot = self.t
        self.from_model()

    def lose_second_heartbeat(self) -> None:
        """50 ms on: the power-up's second heartbeat is lost on the wire, the rest arrives."""
        self.t += 0.06
        self.from_model(lose=HEARTBEAT)

    def unplug(self) -> None:
        if self.plugged:
            self.plugged = False
            self.known.update(online=False, fresh=False)
            self.decoder.reset()
            self.held, self.hold_until = [], -1e9  # (what the port held is lost with it)
            self.run(LinkDown(self.t, 'unplugged'))

    def replug(self) -> None:
        if not self.plugged:
            self.plugged = True
            self.run(LinkUp(self.t))

    def read_status(self) -> None:
        """The driver reads the module (a status frame, a poll): it knows what is true."""
        if self.plugged and self.model.powered and self.t >= self.hold_until:
            self.known.update(online=True, triggered=self.model.triggered,
                              armed=self.model.armed, fresh=True)
            self.unseen = False

    def pass_gate(self, index: int = 0) -> None:
        """The release gate asked for `index`-th returns now."""
        if self.gates:
            _, gate, call = self.gates.pop(min(index, len(self.gates) - 1))
            self.run(GateDone(self.t, gate.token), call)
            if call is not None:
                call.gate_open = False

    def wait(self, seconds: float) -> None:
        """Time passes: the module's frames, the gates due and the monitor's ticks in order."""
        end = self.t + seconds
        while self.t < end:
            times = [end, self.t + SLICE] + [due for due, _, _ in self.gates if due > self.t]
            if self.hold_until > self.t:
                times.append(self.hold_until)
            deadline = self.core.deadline
            if deadline is not None and deadline + self.monitor_lag > self.t:
                times.append(deadline + self.monitor_lag)
            self.t = min(times)
            self.from_model()
            while self.gates and min(due for due, _, _ in self.gates) <= self.t:
                self.pass_gate(min(range(len(self.gates)), key=lambda i: self.gates[i][0]))
            deadline = self.core.deadline
            if deadline is not None and deadline + self.monitor_lag <= self.t:
                self.run(Tick(self.t))

    def finish(self) -> None:
        """Every gate passed, every deadline over: each request decided, each call answered."""
        self.monitor_lag = 0.0
        self.wait(max(0.0, self.hold_until - self.t))  # (the reader takes what it held)
        for _ in range(10):  # (a request taken meanwhile asks for a gate again)
            while self.gates:
                self.pass_gate()
            self.wait(2 * MODULE_WINDOW_S)
            self.run(Tick(self.t))
            if not self.gates:
                break

    # -- the wire -----------------------------------------------------------------------------

    def from_model(self, lose: bytes = b'') -> None:
        """Bring what the module sent to the driver (held while the reader stalls); `lose`:
        a frame lost on the wire."""
        out = self.model.step(self.t).replace(lose, b'', 1) if lose else self.model.step(self.t)
        if not self.plugged:
            return
        self.held.append((out, self.model.boot_count, self.model._pending))
        if self.t < self.hold_until:
            return
        parts, self.held = self.held, []
        for out, boot, pending in parts:
            for frame in self.decoder.feed(out):
                self.take(p.decode_module_frame(frame), boot, pending)

    def take(self, msg: Any, boot: int, pending: Any) -> None:
        """The driver takes `msg` of power-up `boot` (the module's request then: `pending`)."""
        self.known['online'] = True
        if isinstance(msg, p.TriggerRequest):
            while self.t in self.seen:  # (requests are told apart by their time: the reader
                self.t += 1e-6          # takes what it held one after another)
            self.seen[self.t] = Seen(self.t, self.defer_s, pending[0] if pending else None,
                                     boot)
            self.run(RequestReceived(self.t, self.gate_on))
        elif isinstance(msg, p.Heartbeat):
            # The truth: a heartbeat more than 0.2 s after the one before may tell a reboot
            # (D3: a late second heartbeat too), and one of a later power-up does.
            possible = self.t - self.last_heartbeat > POWER_UP_HEARTBEATS_S
            for seen in self.seen.values():
                if seen.voided_at is None and (possible or boot != seen.boot):
                    seen.voided_at = self.t
            self.last_heartbeat = self.t
            # The session's rule tells the core (session_init._on_heartbeat).
            if self.power_ups.take(self.t) != SAME_POWER_UP:
                self.known.update(armed=None, triggered=None, fresh=False)
                self.run(Rebooted(self.t))

    # -- carrying out the core's actions, checked -----------------------------------------------

    def _send(self, send: Write) -> List[Any]:
        seen = self.seen.get(send.t_request)
        if seen is None:
            self.problems.append(f'a confirmation of a request never seen: {send}')
            return [Sent(self.t, send.token)]
        by_answer = seen.answered_true_at is not None and \
            seen.answered_true_at < seen.t + seen.defer_s
        if self.policy == 'deny' or not (self.policy == 'confirm' or
                                         (self.policy == 'defer' and by_answer)):
            self.problems.append(f'a confirmation under {self.policy} (answered at '
                                 f'{seen.answered_true_at}, request at {seen.t}, deadline '
                                 f'{seen.t + seen.defer_s})')
        if seen.voided_at is not None:
            self.problems.append('a confirmation after a reboot voided the request')
        if self.t - seen.t >= MODULE_WINDOW_S:
            self.problems.append(f'a confirmation {self.t - seen.t:.3f} s after the request')
        if seen.decisions or seen.sent_at is not None:
            self.problems.append('a confirmation of a request already decided or confirmed')
        if not self.plugged:
            return [NotSent(self.t, send.token, 'unplugged')]
        seen.sent_at = self.t
        if self.active is not None:
            self.active.sends += 1
        model = self.model
        before, pending = model.deployments, model._pending
        model.receive(send.frame, self.t)
        if model.deployments > before:
            self.confirmed_deployments += model.deployments - before
            # (After a reboot nobody could see, the confirmation of the request before it may
            # meet the module's next request, still on its way: 0x39 names no request. Found
            # by the search; with the reboot seen, the core voids the first: kept below.)
            if model.boot_count == seen.boot and (pending is None or
                                                  pending[0] != seen.model_t):
                self.problems.append('the module deployed on a request the core did not '
                                     'confirm')
        return [Sent(self.t, send.token)]

    def _gate(self, gate: PassGate) -> None:
        self.gates.append((self.t + self.gate_delay, gate, self.active))
        if self.active is not None:
            self.active.gate_open = True

    def _decide(self, decide: Decide) -> None:
        seen = self.seen.get(decide.t_request)
        if seen is None:
            self.problems.append(f'a decision on a request never seen: {decide}')
            return
        seen.decisions.append(decide)
        if len(seen.decisions) > 1:
            self.problems.append(f'two decisions on one request: {seen.decisions}')
        if (decide.decision == 'confirmed') != (seen.sent_at is not None):
            self.problems.append(f'{decide.decision!r} but the confirmation '
                                 f'{"left" if seen.sent_at is not None else "did not leave"}')
        if decide.decision == 'confirmed' and not decide.latency_ms < MODULE_WINDOW_S * 1000:
            self.problems.append(f'confirmed {decide.latency_ms} ms after the request')
        if decide.policy not in (self.policy, self.policy_before):
            self.problems.append(f'decided under {decide.policy}, the policy is {self.policy}')

    def _answer(self, answer: Answer) -> None:
        call = self.active
        if call is None:
            self.problems.append(f'an answer with no call: {answer}')
            return
        call.answers.append(answer.result)
        if 'it deploys' in answer.result.message and not self.unseen and \
                not self.model.triggered:
            self.problems.append(f'"it deploys", and the module did not: {answer.result}')
        if (answer.result.outcome == Outcome.SENT) != (call.sends == 1) or call.sends > 1:
            self.problems.append(f'answered {answer.result} with {call.sends} confirmation(s) '
                                 'sent')

    def _pending(self, action: Pending) -> None:
        self.pending = action.pending

    # -- what the invariants need ---------------------------------------------------------------

    def check(self, final: bool = False) -> None:
        assert not self.problems, self.problems
        assert self.model.deployments == self.confirmed_deployments  # (no other source here)
        for call in self.calls:
            assert len(call.answers) <= 1, call
            assert call.gate_open or len(call.answers) == 1, call
        for seen in self.seen.values():
            assert len(seen.decisions) <= 1, seen
            if final:
                assert len(seen.decisions) == 1, seen


# -- what the search found (each a hole of the session before the core) ------------------------

def test_round2_22_7_a_reboot_while_the_gate_is_passed_voids_the_confirmation():
    rig = TriggerRig('confirm')
    rig.gate_on, rig.gate_delay = True, 0.5
    assert rig.ask()
    rig.reboot()  # (0.3 s: the gate still waits)
    rig.finish()
    rig.check(final=True)
    (seen,) = rig.seen.values()
    assert seen.sent_at is None and seen.decisions[0].decision == 'denied'
    assert 'rebooted' in seen.decisions[0].reason


def test_round2_22_7_a_change_to_deny_while_the_gate_is_passed_sends_nothing():
    rig = TriggerRig('confirm')
    rig.gate_on = True
    assert rig.ask()
    rig.set_policy('deny')
    rig.finish()
    rig.check(final=True)
    (seen,) = rig.seen.values()
    assert seen.sent_at is None and seen.decisions[0].decision == 'denied'
    assert not rig.model.triggered


def test_round2_22_7_a_gate_past_the_window_sends_nothing_even_with_the_monitor_late():
    rig = TriggerRig('confirm')
    rig.gate_on, rig.gate_delay = True, 1.2
    assert rig.ask()
    rig.monitor_lag = 5.0
    rig.wait(1.3)  # the gate returns at 1.2 s, before any tick
    rig.check()
    (seen,) = rig.seen.values()
    assert seen.sent_at is None and seen.decisions[0].decision == 'timed_out'


def test_round2_22_7_an_answer_whose_gate_outlasts_a_reboot_is_refused_not_sent():
    rig = TriggerRig('defer')
    assert rig.ask()
    rig.gate_on, rig.gate_delay = True, 0.5
    call = rig.answer(True)
    assert call.gate_open and not call.answers
    rig.reboot()
    rig.finish()
    rig.check(final=True)
    assert call.answers[0].outcome == Outcome.REFUSED and call.answers[0].cause == 'rebooted'
    assert call.sends == 0 and not rig.model.triggered


def test_round2_22_7_an_answer_after_the_defer_deadline_with_the_monitor_late_sends_nothing():
    rig = TriggerRig('defer', 0.5)
    assert rig.ask()
    rig.monitor_lag = 5.0
    rig.wait(0.6)
    call = rig.answer(True)
    rig.check()
    assert call.answers[0].outcome == Outcome.REFUSED and call.sends == 0


def test_round2_22_7_a_change_to_defer_while_the_gate_is_passed_waits_for_an_answer():
    rig = TriggerRig('confirm')
    rig.gate_on = True
    assert rig.ask()
    rig.set_policy('defer')
    assert rig.core.pending
    rig.pass_gate()  # its gate confirms nothing now
    rig.check()
    call = rig.answer(True)
    rig.pass_gate()
    rig.check()
    assert call.answers[0].outcome == Outcome.SENT and rig.model.triggered


def test_round2_22_7_a_deferred_request_answered_true_deploys_the_module():
    rig = TriggerRig('defer')
    assert rig.ask()
    rig.wait(0.3)
    call = rig.answer(True)
    rig.check()
    assert call.answers[0].outcome == Outcome.SENT and rig.model.triggered
    assert 'it deploys' in call.answers[0].message


@pytest.mark.parametrize('quiet', [False, True])
def test_round2_22_7_a_reboot_seen_voids_the_request_it_ended(quiet):
    """Found by the 20,000-sequence search: held, the module rebooted, was armed again and
    asked again at once; an answer true to the first request confirmed the second, which the
    driver had not yet heard of. With the reboot's heartbeats seen, the first request is void:
    nothing is confirmed. With them lost (`quiet`), no driver can tell (0x39 names no request):
    the invariant allows it only then."""
    rig = TriggerRig('defer', 0.2)
    assert rig.ask()
    first = rig.model.boot_count
    rig.reboot(quiet)
    rig.model.armed = True  # (tilted still: it asks at its next instant)
    rig.unseen = True
    call = rig.answer(True)
    rig.check()
    if quiet:
        assert call.answers[0].outcome == Outcome.SENT and rig.model.boot_count != first
    else:
        assert call.answers[0].cause == 'not_pending' and call.sends == 0
        assert not rig.model.triggered
    rig.finish()
    rig.check(final=True)


@pytest.mark.parametrize('stall', [0.3, 0.9])  # (the module's window is 1 s)
def test_round2_22_3_a_late_second_heartbeat_voids_a_held_request(stall):
    """D3: the module reboots, is armed and asks at once; the reader takes the first heartbeat
    and the request, then stalls: the second heartbeat is taken `stall` s after the first. It
    cannot be told from another reboot: the request is void, an answer true sends nothing."""
    rig = TriggerRig('defer', 0.95)
    rig.reboot()
    rig.wait(REBOOT_S)
    rig.model.power_cycle()
    rig.from_model()  # its first heartbeat
    assert rig.ask() and rig.core.pending
    rig.hold_until = rig.t + stall - 0.01
    rig.wait(stall)
    assert not rig.core.pending
    call = rig.answer(True)
    rig.check()
    assert call.sends == 0 and call.answers[0].outcome == Outcome.REFUSED
    assert not rig.model.triggered
    rig.finish()
    rig.check(final=True)


@pytest.mark.parametrize('again', [0.3, 0.9])
def test_round2_22_3_a_reboot_that_looks_like_a_late_heartbeat_voids_a_held_request(again):
    """D3: the module reboots (its first heartbeat taken, its second lost), is armed and asks;
    held under defer. It reboots again `again` s after the first: that power-up's first
    heartbeat looks like the late second of the one before, and is a reboot all the same: the
    request is void, an answer true sends nothing."""
    rig = TriggerRig('defer', 0.95)
    rig.reboot()
    rig.wait(REBOOT_S)
    rig.model.power_cycle()
    rig.last_boot = rig.t
    rig.from_model()
    rig.lose_second_heartbeat()
    assert rig.ask() and rig.core.pending
    rig.wait(again - 0.07)
    rig.model.power_cycle()
    rig.from_model()  # its heartbeat, within 2 s of the one before: late, or another reboot
    assert not rig.core.pending
    call = rig.answer(True)
    rig.check()
    assert call.sends == 0 and call.answers[0].outcome == Outcome.REFUSED
    rig.finish()
    rig.check(final=True)


def test_round2_22_3_a_reboot_taken_right_after_a_late_heartbeat_voids_the_request_between():
    """D3: the module reboots; the reader takes its first heartbeat and stalls. Meanwhile the
    module sends its second, is armed and asks, and reboots again (locked). When the stall
    ends the reader takes the late second heartbeat (handled as a reboot), the request of that
    power-up, and the next power-up's heartbeats, within 0.2 s of the late one: they tell a
    reboot after the request, which voids it; an answer true sends nothing."""
    rig = TriggerRig('defer', 0.95)
    rig.reboot()
    rig.wait(REBOOT_S)
    rig.model.power_cycle()
    rig.last_boot = rig.t
    rig.from_model()  # its first heartbeat
    rig.hold_until = rig.t + 0.8
    rig.wait(0.1)  # its second, held
    assert rig.ask()  # its request, held
    rig.wait(0.3)
    rig.model.power_cycle()  # another power-up: its heartbeats held
    rig.wait(0.5)  # the stall ends
    assert len(rig.seen) == 1
    call = rig.answer(True)
    rig.check()
    assert call.sends == 0 and call.answers[0].outcome == Outcome.REFUSED
    rig.finish()
    rig.check(final=True)


def test_round2_22_3_found_a_request_between_a_late_heartbeat_and_a_reboot_is_void():
    """Found by the 20,000-sequence search once it generated D3's late heartbeats (kept as it
    shrank it): the module rebooted, the reader took its first heartbeat and stalled 0.6 s;
    meanwhile the module asked, and rebooted again (its first heartbeat seen, its second lost).
    The stall ended: the late second heartbeat (a possible reboot), the request, and the next
    power-up's first heartbeat within 0.2 s of the late one, which the rule took for the same
    power-up: the confirmation, after the release gate, went to a module rebooted since."""
    rig = TriggerRig('confirm', 0.2)
    rig.reboot(late_s=0.6)
    rig.wait(0.01)
    rig.wait(0.3)
    assert rig.ask()
    rig.gate_on, rig.gate_delay = True, 0.0
    rig.reboot(again_s=0.3)
    rig.finish()
    rig.check(final=True)
    (seen,) = rig.seen.values()
    assert seen.sent_at is None and seen.decisions[0].decision == 'denied'


def test_round2_22_3_found_a_request_between_late_heartbeats_of_three_power_ups_is_void():
    """Found by the 20,000-sequence search after the rule above: the reader stalled twice; the
    heartbeat taken 0.6 s after a burst of late ones was taken for a sure first, and the next
    power-up's first, taken with it and a request of the power-up before, for its second."""
    rig = TriggerRig('confirm', 0.2)
    assert rig.ask()
    rig.reboot(late_s=0.3)
    rig.reboot(late_s=0.6)
    rig.gate_on, rig.gate_delay = True, 0.0
    rig.model.armed = True  # (by its switch: it asks at its next instant)
    rig.unseen = True
    rig.reboot(again_s=0.6)
    rig.finish()
    rig.check(final=True)
    late = [s for s in rig.seen.values() if s.t > START]
    assert late and all(s.sent_at is None for s in late), late


def test_round2_22_7_a_driver_stopping_leaves_a_held_request_not_answered():
    core = TriggerCore('defer')
    core.know(True, '', False, True, True)
    core.step(RequestReceived(1.0))
    out = core.step(Stopped(1.1))
    assert [dict(a.fields)['decision'] for a in out if isinstance(a, Record)] == ['not answered']
    assert not core.pending and core.deadline is None


# -- the search -------------------------------------------------------------------------------

class TriggerPolicyModel(RuleBasedStateMachine):
    """A TriggerCore against the virtual parachute, in virtual time."""

    CORE: Type[TriggerCore] = TriggerCore

    def __init__(self) -> None:
        super().__init__()
        self.rig = TriggerRig('defer', core=self.CORE)

    @initialize(policy=st.sampled_from(['confirm', 'deny', 'defer', 'defer']),
                defer_s=st.sampled_from([0.2, 0.5, 0.8, 0.95]), gate=st.booleans(),
                delay=st.sampled_from([0.0, 0.05, 0.3, 0.7, 1.2]),
                lag=st.sampled_from([0.0, 0.1, 0.3, 5.0]))
    def start(self, policy: str, defer_s: float, gate: bool, delay: float, lag: float) -> None:
        self.rig = TriggerRig(policy, defer_s, core=self.CORE)
        self.rig.gate_on, self.rig.gate_delay = gate, delay
        self.rig.monitor_lag = lag

    @precondition(lambda self: self.rig.can_ask())
    @rule()
    def module_asks(self) -> None:
        self.rig.ask()

    @rule(confirm=st.booleans())
    def answer(self, confirm: bool) -> None:
        self.rig.answer(confirm)

    @precondition(lambda self: self.rig.core.pending)
    @rule(confirm=st.booleans(), after=st.sampled_from([0.0, 0.1, 0.3, 0.6, 0.9]))
    def answer_the_held_request(self, confirm: bool, after: float) -> None:
        """Someone answers the request held, `after` seconds later."""
        self.rig.wait(after)
        self.rig.answer(confirm)

    @rule(policy=st.sampled_from(['confirm', 'deny', 'defer']),
          defer_s=st.sampled_from([None, 0.2, 0.5, 0.8, 0.95]))
    def policy_changes(self, policy: str, defer_s: Optional[float]) -> None:
        self.rig.set_policy(policy, defer_s)

    @rule(on=st.booleans(), delay=st.sampled_from([0.0, 0.05, 0.3, 0.7, 1.2]))
    def release_gate(self, on: bool, delay: float) -> None:
        """A release gate there or not; the time it takes (1.2 s: a host too loaded)."""
        self.rig.gate_on, self.rig.gate_delay = on, delay

    @rule(index=st.integers(0, 2))
    def a_gate_returns(self, index: int) -> None:
        self.rig.pass_gate(index)

    @rule(kind=st.sampled_from(REBOOT_KINDS), after=st.sampled_from(REBOOT_AFTER_S))
    def module_reboots(self, kind: str, after: float) -> None:
        """The module reboots: its heartbeats seen or lost, or (D3) its second taken `after`
        the first by a reader that stalled, or lost and another reboot `after` the first."""
        self.rig.reboot(**reboot_faults(kind, after))

    @rule(armed=st.booleans())
    def someone_else_arms_or_locks(self, armed: bool) -> None:
        """Armed or locked by another path (its switch); the driver reads it later."""
        if not self.rig.model.triggered and self.rig.model.armed != armed:
            self.rig.model.armed = armed
            self.rig.unseen = True

    @rule(seconds=st.sampled_from([0.0, 0.1, 0.5, 1.5]))
    def unplugged_for(self, seconds: float) -> None:
        """Unplugged (the module's frames lost meanwhile), plugged in again."""
        self.rig.unplug()
        self.rig.wait(seconds)
        self.rig.replug()

    @rule()
    def the_driver_reads_the_module(self) -> None:
        self.rig.read_status()

    @rule(seconds=st.sampled_from([0.01, 0.1, 0.2, 0.3, 0.6, 1.1]))
    def time_passes(self, seconds: float) -> None:
        self.rig.wait(seconds)

    @rule(lag=st.sampled_from([0.0, 0.1, 0.3, 5.0]))
    def the_monitor_runs_late(self, lag: float) -> None:
        """The monitor's tick comes `lag` after a deadline (a loaded host)."""
        self.rig.monitor_lag = lag

    @invariant()
    def the_policy_holds(self) -> None:
        self.rig.check()

    def teardown(self) -> None:
        self.rig.finish()
        self.rig.check(final=True)


def test_round2_22_7_trigger_request_invariants_hold_over_random_sequences():
    search(TriggerPolicyModel, 'parachute_trigger', steps=50)


# -- the search against the policy as the session had it before the core ------------------------

class GateUnseen(TriggerCore):
    """The session before the core: a request waiting for the release gate was nobody's (a
    reboot, a policy change, the window did not touch it), and the confirmation followed the
    gate without judging anything again (``_confirm_after_gate``, ``_answer_pending``)."""

    def _pass_gate(self, req: Any) -> None:
        super()._pass_gate(req)
        if self._open is req:
            self._open = None

    def _on_GateDone(self, event: GateDone) -> None:
        req = self._gates.pop(event.token, None)
        if req is not None and req.gate == event.token and not req.decided:
            req.gate = 0
            self._send(req)


class DeadlineByTickOnly(TriggerCore):
    """The session before the core: the defer deadline was judged by the monitor's tick alone,
    so an answer after it, before a late tick, confirmed the request."""

    def step(self, event: Any) -> List[Any]:
        if not isinstance(event, Tick):
            self._expire = lambda: None  # type: ignore[assignment]
        try:
            return super().step(event)
        finally:
            self.__dict__.pop('_expire', None)


@pytest.mark.parametrize('core, found, search_seed', [
    (GateUnseen, ('after a reboot voided', 'a confirmation under deny',
                  'a confirmation under defer', 's after the request', 'did not confirm'), 11),
    (DeadlineByTickOnly, ('a confirmation under defer',), 16)])
def test_round2_22_7_the_search_finds_the_holes_of_the_session_before_the_core(
        core, found, search_seed, monkeypatch):
    """The search is strong enough to find each hole the core closed.

    It must find them every time, not by luck: unseeded, the deadline's hole took 199-2,955
    sequences (12-33 s) and a budget of 2,000 missed it once. So the search starts from a fixed
    seed, and without the constants hypothesis collects from the modules loaded in the process
    (which differ with the tests an xdist worker ran before: from one seed, 12, 118 and 363
    sequences). What it generates then depends on the seed, the settings and the hypothesis
    version alone: 6 and 12 sequences here. The budget of 50 default runs is for another
    hypothesis version.
    """
    # Private to hypothesis; where they are gone the seed and the budget still hold.
    monkeypatch.setattr(providers, '_get_local_constants', lambda: providers.Constants(),
                        raising=False)
    monkeypatch.setattr(providers, 'CONSTANTS_CACHE', {}, raising=False)

    @seed(search_seed)
    class Before(TriggerPolicyModel):
        CORE = core

    with pytest.raises(AssertionError) as failure:
        run_state_machine_as_test(Before, settings=settings(
            max_examples=EXAMPLES * 50, stateful_step_count=50, deadline=None, database=None,
            suppress_health_check=list(HealthCheck),
            phases=[Phase.generate, Phase.target]))
    assert any(text in str(failure.value) for text in found), failure.value
