"""The deploy procedure (D6) and arming (P7, D16).

With the count of unacknowledged deploy frames that keeps the module out of protection (P11).

Part of `ParachuteSession` (``dps_parachute_ros.session`` assembles it; the shared state and the
lock are described there). Threads:

- callers: ``deploy`` and ``arm`` (the node's service threads), serialized by ``_actuation``
  (never taken on the reader thread or by a trigger-request answer). A deploy's decisions are
  `DeployCore`'s (``deploy_core``, no I/O): the caller's thread steps it, telling it what the
  session knows before each event, and carries out its actions through
  ``uav_serial_common.core_runner``: its requests over the link (a reply, a timeout or the
  link down is the next event), its records (the decision synced before the frame leaves),
  the release gate (``release_gate``, when the node sets one) before the first frame, and its
  one answer. ``arm`` runs the same core (an `ArmCall`); its check that arming would not
  deploy the module at once is the settings core's (``_gate``).
- the thread that writes a frame (a deploy's caller): ``_on_tx`` counts every deploy frame as
  it leaves, whatever ends the wait for its answer, and every arm or lock frame (``_arms``: an
  armed state read before one is older than its read-back and is not taken).
- serial reader: ``_on_deploy_reply`` takes a late acknowledgement (a deploy call takes the one
  it waits for).

Owns, guarded by ``_lock``: ``_deploy_frame_left``, ``_deploy_frame_at``, ``_unknown_boot``,
``_arms``; the ``armed``, ``unacked_deploys``, ``failed_deploys`` and
``deploy_outcome_unknown`` fields of the snapshot. Other: ``_actuation``, ``_attempts`` (the
attempts kept for a restart).
"""

from __future__ import annotations

from dataclasses import replace
import time
from types import SimpleNamespace
from typing import Any, List, Optional, Tuple, Union

from dps_parachute_ros import protocol as p
from dps_parachute_ros.deploy_core import (ArmAnswer, ArmCall, ArmJudged, DEPLOY_FRAME,
                                           DEPLOY_TOKEN, DeployAnswer, DeployCall, DeployCore,
                                           Event, JudgeArm, Report, SaveAttempts)
from dps_parachute_ros.link import LinkBusy, LinkDown, LinkError
from dps_parachute_ros.release_gate import GateDone, PassGate
from dps_parachute_ros.state import Outcome, Result, Snapshot
from uav_serial_common.core_events import Busy, Log, Record, Reply, Request, Timeout
from uav_serial_common.core_events import LinkDown as CoreLinkDown
from uav_serial_common.core_runner import run_core

REREAD_WAIT_S = 1.0
"""A deploy or an arm waits this long for the module's state to be re-read (D15)."""
ACTUATION_WAIT_S = 10.0
"""A deploy or arm waits this long for one already running."""
SAFETY_SYNC_S = 0.5
"""Longest wait for the black box's fsync on a safety event; none while it is failing."""
ARM_FRAMES = (p.encode_arm(True), p.encode_arm(False))
"""The frames that change the armed state (besides a deploy, which locks the module, P11)."""
DEPLOY_OUTCOMES = {'refused': Outcome.REFUSED, 'already deployed': Outcome.DONE,
                   'deployed': Outcome.DONE, 'not deployed': Outcome.FAILED,
                   'unknown': Outcome.UNKNOWN}
"""The outcome of each way the deploy core ends a call; another word is DONE when it
succeeded, else FAILED (never a refusal not decided as one)."""


class DeployProcedure:
    """The deploy procedure of `ParachuteSession` (a mixin: it uses the session's state)."""

    def _safety_sync(self) -> bool:
        """Fsync the black box on a safety event: bounded, and no wait while it is failing."""
        return self.blackbox.sync(SAFETY_SYNC_S if self.blackbox.status().writing else 0.0)

    def _on_tx(self, data: bytes) -> None:
        # Every deploy frame that leaves counts until the module answers one, whatever ends
        # the wait (P11, D6): a timeout, a dropped link, a shutdown.
        if data in ARM_FRAMES:
            with self._lock:
                self._arms += 1  # an armed state read before it is older (_newer_armed)
        elif data == DEPLOY_FRAME:
            with self._lock:
                self._deploy_frame_left = True
                self._deploy_frame_at = self.clock()
                self._sent_since_boot_read += 1
                self._snap = replace(self._snap, unacked_deploys=self._snap.unacked_deploys + 1,
                                     failed_deploys=self._snap.failed_deploys + 1)

    def _save_attempts(self, leaving: int = 0) -> None:
        """Keep the unsuccessful deploy frames of this power-up for a later run (P11)."""
        snap = self.snapshot
        with self._lock:
            since = self._sent_since_boot_read + leaving
        problem = self._attempts.save(snap.boot_count, snap.failed_deploys + leaving,
                                      snap.unacked_deploys + leaving, since)
        if problem:
            self._log('warn', f'deploy attempts not kept for a restart: {problem}',
                      key='attempts', every_s=60.0)

    def _on_deploy_reply(self, ack: p.DeployAck, late: bool) -> None:
        with self._lock:
            failed = 0 if ack.success else self._snap.failed_deploys
            self._snap = replace(self._snap, unacked_deploys=0, failed_deploys=failed)
        if not late:
            self._save_attempts()  # (a late one is saved by the deploy call it ends)
        if not ack.success:
            return
        if late:
            self._log('warn', 'late deploy acknowledgement: the module deployed')
        self._deployed_by_ack()
        self._resolve_unknown_deploy(True, 'late acknowledgement')

    def _deployed_by_ack(self) -> None:
        with self._lock:
            self._snap = replace(self._snap, armed=False)
            boot = self._snap.boot_count
        self._report(p.SOURCE_SERIAL, 'deploy_ack', None, boot)
        self._set_triggered(True, via='deploy ack')
        self._schedule('records')

    def _resolve_unknown_deploy(self, triggered: bool, how: str) -> None:
        with self._lock:
            if not self._snap.deploy_outcome_unknown:
                return
            self._snap = replace(self._snap, deploy_outcome_unknown=False)
        outcome = 'deployed' if triggered else 'not deployed'
        self.blackbox.record('decision', what='deploy', outcome=outcome, resolved=how)
        self.blackbox.sync(None)
        self._log('error' if triggered else 'warn',
                  f'the earlier deploy whose outcome was unknown: {outcome} ({how})')
        self.listener.on_diagnostics()

    def _wait_fresh(self) -> Snapshot:
        """Wait (bounded) until armed and triggered have been re-read (D15)."""
        deadline = time.monotonic() + REREAD_WAIT_S
        with self._lock:
            while not self._snap.fresh and self._snap.online:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self._stopping.is_set():
                    break
                self._lock.wait(min(remaining, 0.05))
            return self._snap

    def _query_triggered(self) -> Optional[bool]:
        """Ask the module whether it is triggered; None when it does not answer."""
        epoch = self._current_epoch()
        try:
            triggered = self._req(p.encode_triggered_query()).triggered
        except LinkError:
            return None
        if epoch == self._current_epoch():
            self._set_triggered(triggered, via='query')
        return triggered

    def deploy(self, confirm: str, arm_if_locked: bool = False) -> Result:
        """`~/deploy`: the rules of the README's "Safety model of deploy" (D6).

        They are `DeployCore`'s (``deploy_core``); this thread carries out its actions over
        the link (``_run_deploy``), serialized with arm by ``_actuation``.
        """
        call = DeployCall(self.clock(), confirm, arm_if_locked, self.release_gate is not None)
        if confirm != DEPLOY_TOKEN:
            return self._run_deploy(call)  # refused at once: nothing to wait for
        if not self._actuation.acquire(timeout=ACTUATION_WAIT_S):
            return self._deploy_end(call, 'deploy refused: another deploy or arm did not '
                                    f'finish within {ACTUATION_WAIT_S:.0f} s; nothing sent')
        try:
            if self._stopping.is_set():
                return self._deploy_end(call, 'deploy refused: the driver is shutting down; '
                                        'nothing sent', cause='stopping')
            snap = self.snapshot
            if snap.online and not snap.fresh:
                self._wait_fresh()  # the worker's re-read, already under way (D15)
            return self._run_deploy(call)
        finally:
            self._save_attempts()
            self._actuation.release()

    def _deploy_end(self, call: DeployCall, message: str, cause: str = 'busy') -> Result:
        """Refuse a deploy before its procedure starts (busy, shutting down)."""
        self.blackbox.record('request', what='deploy', token_ok=True,
                             arm_if_locked=call.arm_if_locked)
        if self.snapshot.deploy_outcome_unknown:
            message += ('; an earlier deploy frame left without an acknowledgement: its outcome '
                        'is UNKNOWN (the parachute may have deployed) until the module answers')
        self.blackbox.record('decision', what='deploy', outcome='refused', success=False,
                             reason=message)
        self._safety_sync()
        self._log('warn', message)
        return Result.refused(cause, message)

    def _run_deploy(self, call: DeployCall) -> Result:
        """Run one deploy call on the deploy core; take its answer into the session."""
        done = self._run_core(call)
        answer = next(action for action in done if isinstance(action, DeployAnswer))
        if answer.counts is not None:
            with self._lock:
                self._snap = replace(self._snap, failed_deploys=answer.counts[0],
                                     unacked_deploys=answer.counts[1])
        if answer.outcome == 'unknown':
            with self._lock:
                self._unknown_boot = self._snap.boot_count
            self._update(deploy_outcome_unknown=True)
            self.listener.on_diagnostics()
        if answer.ok:
            self._emit_status()
        kind = DEPLOY_OUTCOMES.get(answer.outcome, Outcome.DONE if answer.ok else Outcome.FAILED)
        return Result(kind, answer.message, latency_ms=answer.latency_ms)

    def _run_core(self, call: Union[DeployCall, ArmCall]) -> List[Any]:
        """Step a `DeployCore` that mirrors this session's knowledge, and carry out its actions.

        Before each event the core is told what the session knows now (its reader, worker and
        monitor threads keep that); a reply is taken into the session first, as any request's
        is, and then given to the core. Returns the actions carried out.
        """
        core = DeployCore(mirror=True, request_timeout_s=self.config.request_timeout_s)
        armed_read: List[Tuple[int, bool]] = []  # (epoch, armed) of an armed query, for fresh

        def step(event: Event) -> List[Any]:
            with self._lock:
                snap = self._snap
                core.know(port_open=snap.port_open, online=snap.online,
                          offline_reason=snap.offline_reason, fresh=snap.fresh, armed=snap.armed,
                          triggered=snap.triggered, boot_count=snap.boot_count,
                          failed=snap.failed_deploys, unacked=snap.unacked_deploys,
                          outcome_unknown=snap.deploy_outcome_unknown,
                          unknown_boot=self._unknown_boot, triggered_seen=self._triggered_seen,
                          frame_at=self._deploy_frame_at, reboots=self._reboots,
                          boot_current=snap.boot_count is not None
                          and self._boot_read_reboots == self._reboots,
                          deployed_boots=set(self._reported_boots))
            return core.step(event)

        def request(action: Request) -> List[Event]:
            return self._deploy_request(action, armed_read)

        def save(action: SaveAttempts) -> None:
            problem = self._attempts.save(action.boot_count, action.failed, action.unacked,
                                          action.since_read)
            if problem:
                self._log('warn', f'deploy attempts not kept for a restart: {problem}',
                          key='attempts', every_s=60.0)

        def gate(action: PassGate) -> List[Event]:
            if self.release_gate is not None:
                self.release_gate.before_release(action.what)  # every refusal is decided
            return [GateDone(self.clock())]

        def judge(action: JudgeArm) -> List[Event]:
            try:
                danger = self._gate([('armed', True)], action.origin)
            except LinkError as exc:
                return [ArmJudged(self.clock(), problem=str(exc))]
            return [ArmJudged(self.clock(), danger=danger)]

        return run_core(SimpleNamespace(step=step), [call], {
            Request: request, Record: self._carry_record, SaveAttempts: save, PassGate: gate,
            JudgeArm: judge, Log: self._carry_log,
            Report: lambda action: None,  # (mirror: the session reports its deployments)
            # (the answers are taken from what run_core carried out)
            DeployAnswer: lambda action: None, ArmAnswer: lambda action: None})

    def _deploy_request(self, send: Request,
                        armed_read: List[Tuple[int, bool, int]]) -> List[Event]:
        """Carry out one request of the deploy procedure; the event that ends its wait."""
        epoch, arms = self._asked()
        deploy = send.frame == DEPLOY_FRAME
        if deploy:
            armed_read.clear()
            with self._lock:
                self._deploy_frame_left = False
        try:
            if p.TriggerRecord in send.expect:
                reply: Any = self._fetch_records()
            else:
                reply = self._req(send.frame, retries=send.retries, silence_ok=send.silence_ok)
        except LinkBusy as exc:
            return [Busy(self.clock(), str(exc))]
        except LinkDown as exc:
            with self._lock:
                # (A frame that changes the armed state is counted as it leaves, _on_tx.)
                left = (self._deploy_frame_left if deploy
                        else self._arms != arms if send.frame in ARM_FRAMES else True)
            return [CoreLinkDown(self.clock(), str(exc), left, self._stopping.is_set())]
        except LinkError as exc:
            return [Timeout(self.clock(), str(exc))]
        # Into the session first, as the requests before the core took them.
        if isinstance(reply, p.BootCount):
            self._note_boot_count(reply.count)
        elif isinstance(reply, p.Status):
            self._on_status(reply, 'query', epoch, arms)
        elif isinstance(reply, p.ArmedState):
            self._update_if(epoch, arms, armed=reply.armed)
            armed_read[:] = [(epoch, reply.armed, arms)]
        elif isinstance(reply, p.TriggeredState):
            if armed_read and armed_read[0][0] == epoch:
                # Armed and triggered read in one epoch: a re-read (D15).
                self._set_triggered(reply.triggered, 'query', epoch, armed_read[0][2],
                                    armed=armed_read[0][1], fresh=True)
            elif epoch == self._current_epoch():
                self._set_triggered(reply.triggered, via='query')
        elif isinstance(reply, p.DeployAck):
            self._on_deploy_reply(reply, late=False)
        return [Reply(self.clock(), reply)]

    def arm(self, want: bool) -> Result:
        """`~/arm`: arm or lock; success only when the reply and a query agree (P7).

        The rules are `DeployCore`'s (``_arm_call``: D15, D16, P21); this thread carries out
        its actions over the link, serialized with deploy by ``_actuation``.
        """
        word = 'arm' if want else 'lock'
        if not self._actuation.acquire(timeout=ACTUATION_WAIT_S):
            self.blackbox.record('request', what=word)
            result = Result.refused('busy', 'another deploy or arm is still running; nothing sent')
        else:
            try:
                snap = self.snapshot
                if want and snap.online and not snap.fresh:
                    self._wait_fresh()  # the worker's re-read, already under way (D15)
                result = self._run_arm(want)
            finally:
                self._actuation.release()
        self._log('info' if result.ok else 'warn', result.message)
        return result

    def _run_arm(self, want: bool) -> Result:
        """Step the deploy core through one `ArmCall`; take into the session what it did."""
        sent_before = self._arms_sent()
        done = self._run_core(ArmCall(self.clock(), want))
        result = next(action for action in done if isinstance(action, ArmAnswer)).result
        if self._arms_sent() == sent_before:
            return result
        if result.outcome is Outcome.UNKNOWN and result.cause == 'no_reply':
            # Its frame left and what it did was not seen: neither armed nor locked is
            # known (a deploy would be judged on a guess). The module is read afresh (D15).
            self._update(armed=None, fresh=False)
            self._schedule('init', force=True)
        self._emit_status()
        self.listener.on_diagnostics()
        return result
