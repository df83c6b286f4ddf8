"""Trigger requests of the module (D8): the runtime of `TriggerCore` in the session.

Part of `ParachuteSession` (``dps_parachute_ros.session`` assembles it; the shared state and the
lock are described there). The policy's rules are `TriggerCore`'s (``trigger_core``, no I/O):
every thread below steps it with an event and carries out its actions in order, under
``_trigger_lock`` (held only while stepping and carrying out; never while the release gate
waits). Before each event the core is told what the session knows of the module. Threads:

- serial reader: a trigger request (``_on_trigger_request``). Under ``confirm`` without a gate
  the core's first action is the confirmation, written right there (why a confirm takes
  milliseconds); the reader never waits for the gate.
- gate (``parachute-gate``): a release gate the core asks for from any thread but an answer
  call is passed on a short-lived thread of its own, which then steps `GateDone`.
- callers: ``answer_trigger_request`` (the node's service thread; it passes the gate itself:
  its answer waits for it), a policy change (``reconfigure``), a reboot seen on any thread
  (``_void_pending``), ``stop``.
- monitor: ``tick()`` steps `Tick` (the defer deadline, the module's window); it sleeps until
  the core's ``deadline``, and the core's `SetTimer` wakes it by then (``wake(by=...)``).

Owns ``_triggers`` (the core) and ``_trigger_lock``; the ``pending_request`` field of the
snapshot. A confirmation never waits behind I/O (only behind the release gate, off the reader).
"""

from __future__ import annotations

import threading
from dataclasses import replace
from types import SimpleNamespace
from typing import Any, List, Optional

from dps_parachute_ros.link import LinkDown
from dps_parachute_ros.release_gate import GateDone, PassGate
from dps_parachute_ros.state import RequestDecision, Result
from dps_parachute_ros.trigger_core import (
    AnswerCall, Decide, Event, NotSent, Pending, PolicyChanged, RequestReceived, ROUTE, Sent,
    SetTimer, Stopped, Tick, TriggerCore, Write)
from uav_serial_common.core_events import Answer, Log, Rebooted, Record
from uav_serial_common.core_runner import run_core


class TriggerRequests:
    """The trigger-request runtime of `ParachuteSession` (a mixin: it uses the session's state)."""

    def _init_triggers(self) -> None:
        config = self._config
        self._triggers = TriggerCore(config.trigger_request_policy, config.defer_timeout_s)
        self._trigger_lock = threading.RLock()

    def _trigger(self, event: Event, wait_gate: bool = False) -> Optional[Result]:
        """Step the core with `event`, carry out its actions; the answer to a call, if any.

        A release gate asked for is passed here when `wait_gate` (an answer call waits for
        it anyway), else on a gate thread.
        """
        gates: List[PassGate] = []
        answers: List[Result] = []

        def step(ev: Event) -> List[Any]:
            with self._lock:
                snap = self._snap
            self._triggers.know(snap.online, '' if snap.online else self._offline_text(snap),
                                snap.triggered, snap.armed, snap.fresh)
            return self._triggers.step(ev)

        with self._trigger_lock:
            run_core(SimpleNamespace(step=step), [event], {
                Write: self._trigger_write, Decide: self._trigger_decide,
                Record: self._carry_record, SetTimer: self._trigger_timer,
                Log: self._carry_log,
                Pending: self._trigger_pending, PassGate: gates.append,
                Answer: lambda action: answers.append(action.result)})
        for gate in gates:
            if wait_gate:
                answers.extend(filter(None, [self._pass_gate(gate)]))
            else:
                threading.Thread(target=self._pass_gate, args=(gate,), name='parachute-gate',
                                 daemon=True).start()
        return answers[0] if answers else None

    def _pass_gate(self, gate: PassGate) -> Optional[Result]:
        if self.release_gate is not None:
            self.release_gate.before_release(gate.what, gate.t_request)  # (never raises)
        return self._trigger(GateDone(self.clock(), gate.token))

    def _trigger_timer(self, action: SetTimer) -> None:
        # The core's deadline is on the session's clock (its events carry self.clock()), the
        # monitor's too: it runs by then (a sleep that ends earlier is left alone), and its
        # duty's next deadline (_monitor_due) holds the core's, so it is kept after any run.
        self._monitor.wake(by=action.at)

    def _trigger_write(self, action: Write) -> List[Event]:
        try:
            self.link.write(action.frame)
        except LinkDown as exc:
            return [NotSent(self.clock(), action.token, str(exc))]
        return [Sent(self.clock(), action.token)]

    def _trigger_decide(self, action: Decide) -> None:
        self.blackbox.record('decision', what='trigger request', decision=action.decision,
                             policy=action.policy, reason=action.reason,
                             latency_ms=action.latency_ms)
        self.blackbox.sync(None)
        self.listener.on_trigger_request(RequestDecision(action.decision, action.policy,
                                                         action.reason, action.latency_ms))
        self.listener.on_diagnostics()

    def _trigger_pending(self, action: Pending) -> None:
        with self._lock:
            self._snap = replace(self._snap, pending_request=action.pending)
        self.listener.on_diagnostics()

    def _gate_ready(self) -> bool:
        """Whether a request confirmed by the policy passes a release gate first."""
        return self._triggers.policy == 'confirm' and self.release_gate is not None and \
            self.release_gate.available(ROUTE)

    # -- the events ----------------------------------------------------------------------------

    def _on_trigger_request(self) -> None:
        t_rx = self.clock()
        self._trigger(RequestReceived(t_rx, self._gate_ready()))

    def _void_pending(self, why: str) -> None:
        """Void a request of the module's last power-up: it rebooted (nothing is sent)."""
        self._trigger(Rebooted(self.clock()))

    def _policy_changed(self, policy: str, defer_timeout_s: float) -> None:
        self._trigger(PolicyChanged(self.clock(), policy, defer_timeout_s,
                                    self.release_gate is not None))

    def _trigger_deadline(self) -> Optional[float]:
        with self._trigger_lock:
            return self._triggers.deadline

    def _trigger_tick(self, now: float) -> None:
        due = self._trigger_deadline()
        if due is not None and now >= due:
            self._trigger(Tick(now))

    def _trigger_stop(self) -> None:
        self._trigger(Stopped(self.clock()))

    def answer_trigger_request(self, confirm: bool) -> Result:
        """`~/answer_trigger_request`: answer the deferred request, if one is pending."""
        result = self._trigger(AnswerCall(self.clock(), confirm, self.release_gate is not None),
                               wait_gate=True)
        # (The core answers every call once; this is for a bug, never silence.)
        return result or Result.failed('the trigger-request core gave no answer', cause='bug')
