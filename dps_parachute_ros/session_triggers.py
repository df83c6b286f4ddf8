"""Trigger requests of the module (D8): the policy, the deferred answer, and its voiding.

Part of `ParachuteSession` (``dps_parachute_ros.session`` assembles it; the shared state and the
lock are described there). Threads:

- serial reader: ``_on_trigger_request`` decides at once under ``confirm`` and ``deny``, writing
  the confirmation first, before anything else (why a confirm takes milliseconds); under
  ``defer`` it parks the request in ``_pending`` and wakes the monitor for its deadline.
- gate (``parachute-gate``): under ``confirm`` with a release gate available (``release_gate``,
  set by the node), one short-lived thread per request runs ``_confirm_after_gate``: the gate
  (the motor stop) waits there, then the confirmation is written; the reader never waits.
- callers: ``answer_trigger_request`` (the node's service thread; it passes the release gate
  before the confirmation) and a policy change (``reconfigure``) settle a pending request; a
  reboot seen on any thread voids it (``_void_pending``).
- monitor: ``tick()`` denies a request nobody answered within ``defer_timeout_s``.

Owns ``_pending`` (guarded by ``_lock``; ``stop`` drops it, the monitor's ``tick`` times it out)
and the ``pending_request`` field of the snapshot. No method here waits for a reply: a
trigger-request confirmation never waits behind I/O (only behind the release gate, off the
reader thread).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import threading
from typing import Optional

from dps_parachute_ros import protocol as p
from dps_parachute_ros.link import LinkDown
from dps_parachute_ros.state import MODULE_WINDOW_S, RequestDecision, Result


@dataclass
class _Pending:
    t_rx: float
    deadline: float


class TriggerRequests:
    """The trigger-request policy of `ParachuteSession` (a mixin: it uses the session's state)."""

    def _on_trigger_request(self) -> None:
        t_rx = self.clock()
        with self._lock:
            policy = self._config.trigger_request_policy
            defer_s = self._config.defer_timeout_s
        if policy == 'confirm' and self.release_gate is not None and \
                self.release_gate.available('trigger request'):
            # The gate (the motor stop) waits: never on the reader thread, which delivers replies.
            threading.Thread(target=self._confirm_after_gate, args=(t_rx, policy),
                             name='parachute-gate', daemon=True).start()
        elif policy == 'confirm':
            try:
                self.link.write(p.encode_trigger_confirm())  # first, before anything else
            except LinkDown as exc:
                self._decide('denied', policy, f'could not send the confirmation: {exc}', t_rx,
                             None)
                return
            self._decide('confirmed', policy, 'policy confirm: confirmed at once', t_rx,
                         self.clock())
        elif policy == 'deny':
            self._decide('denied', policy, 'policy deny: no confirmation sent', t_rx, None)
        else:
            with self._lock:
                old = self._pending
                self._pending = _Pending(t_rx, t_rx + defer_s)
                self._snap = replace(self._snap, pending_request=True)
            self._monitor_wake.set()  # its deadline
            if old is not None:
                self._decide('timed_out', policy, 'superseded by a newer trigger request',
                             old.t_rx, None)
            self.blackbox.record('decision', what='trigger request deferred', deadline_s=defer_s)
            self.blackbox.sync(None)
            self._log('warn', f'trigger request from the module: answer ~/answer_trigger_request '
                              f'within {defer_s:.2f} s (else denied)')
            self.listener.on_diagnostics()

    def _confirm_after_gate(self, t_rx: float, policy: str) -> None:
        self.release_gate.before_release('trigger request', t_rx)
        try:
            self.link.write(p.encode_trigger_confirm())
        except LinkDown as exc:
            self._decide('denied', policy, f'could not send the confirmation: {exc}', t_rx, None)
            return
        self._decide('confirmed', policy, 'policy confirm: confirmed after the release gate',
                     t_rx, self.clock())

    def _decide(self, decision: str, policy: str, reason: str, t_rx: float,
                t_tx: Optional[float]) -> None:
        latency = None if t_tx is None else (t_tx - t_rx) * 1000.0
        with self._lock:
            if self._pending is None:
                self._snap = replace(self._snap, pending_request=False)
        self.blackbox.record('decision', what='trigger request', decision=decision,
                             policy=policy, reason=reason, latency_ms=latency)
        self.blackbox.sync(None)
        self.listener.on_trigger_request(RequestDecision(decision, policy, reason, latency))
        if decision == 'confirmed':
            self._log('error', f'trigger request confirmed: {reason}')
        else:
            self._log('warn', f'trigger request {decision}: {reason}')
        self.listener.on_diagnostics()

    def _answer_pending(self, pending: _Pending, confirm: bool, policy: str,
                        why: str) -> Result:
        """Answer a deferred request; say what is true about what the module does (D8)."""
        if not confirm:
            self._decide('denied', policy, f'{why}: no confirmation sent', pending.t_rx, None)
            return Result.done('denied: nothing sent')
        age = self.clock() - pending.t_rx
        snap = self.snapshot
        problem = cause = ''
        if age >= MODULE_WINDOW_S:
            problem, cause = (f"{age:.2f} s after the request: the module's 1 s window has "
                              'passed (P10); no confirmation sent'), 'window_passed'
        elif not snap.online:
            problem, cause = f'{self._offline_text(snap)}: no confirmation sent', 'offline'
        elif snap.triggered:
            problem, cause = 'the module has already deployed: no confirmation sent', 'triggered'
        elif snap.armed is False and snap.fresh:
            problem, cause = ('the module is locked, and a locked module cannot deploy (P12, '
                              'P20): no confirmation sent'), 'locked'
        if problem:
            decision = 'timed_out' if age >= MODULE_WINDOW_S else 'denied'
            self._decide(decision, policy, f'{why}, but {problem}', pending.t_rx, None)
            return Result.refused(cause, f'not confirmed: {problem}')
        if self.release_gate is not None:
            self.release_gate.before_release('trigger request', pending.t_rx)
        try:
            self.link.write(p.encode_trigger_confirm())
        except LinkDown as exc:
            self._decide('denied', policy, f'{why}, but the link is down: {exc}', pending.t_rx,
                         None)
            return Result.failed(f'confirmation not sent: {exc}', cause='link_down')
        t_tx = self.clock()
        # Armed only as read since the module last could have changed unseen (D15).
        if snap.armed and snap.fresh:
            outcome = 'the module was armed: it deploys on it (~/trigger_event reports it)'
        else:
            outcome = ("the module's armed state is not known: ~/triggered shows whether it "
                       'deploys')
        self._decide('confirmed', policy, f'{why}; {outcome}', pending.t_rx, t_tx)
        # The module does not acknowledge a confirmation: ~/trigger_event tells what it did.
        return Result.sent(f'confirmation sent {(t_tx - pending.t_rx) * 1000:.0f} ms after the '
                           f'request; {outcome}')

    def _void_pending(self, why: str) -> None:
        """Settle a waiting request the module no longer makes (it rebooted): nothing sent."""
        with self._lock:
            pending, self._pending = self._pending, None
            policy = self._config.trigger_request_policy
        if pending is not None:
            # A rebooted module boots locked and has forgotten its question (D15): a confirm now
            # would answer nobody, and the armed state behind "it deploys" is from before.
            self._decide('denied', policy, f'{why}: its request is gone; no confirmation sent',
                         pending.t_rx, None)

    def answer_trigger_request(self, confirm: bool) -> Result:
        """`~/answer_trigger_request`: answer the deferred request, if one is pending."""
        with self._lock:
            pending, self._pending = self._pending, None
            policy = self._config.trigger_request_policy
        if pending is None:
            return Result.refused('not_pending', 'no trigger request is pending')
        return self._answer_pending(pending, confirm, policy,
                                    f'answered {str(confirm).lower()} via '
                                    '~/answer_trigger_request')
