"""The deploy procedure (D6) and arming (P7, D16).

With the count of unacknowledged deploy frames that keeps the module out of protection (P11).

Part of `ParachuteSession` (``dps_parachute_ros.session`` assembles it; the shared state and the
lock are described there). Threads:

- callers: ``deploy`` and ``arm`` (the node's service threads), serialized by ``_actuation``
  (never taken on the reader thread or by a trigger-request answer). They decide around
  blocking requests; each decision is recorded (and synced) before the frame leaves, and the
  release gate (``release_gate``, when the node sets one) is passed before the first frame.
- the thread that writes a frame (a deploy's caller): ``_on_tx`` counts every deploy frame as
  it leaves, whatever ends the wait for its answer.
- serial reader: ``_on_deploy_reply`` takes a late acknowledgement (a deploy call takes the one
  it waits for).

Owns, guarded by ``_lock``: ``_deploy_frame_left``, ``_deploy_frame_at``, ``_unknown_boot``; the
``armed``, ``unacked_deploys``, ``failed_deploys`` and ``deploy_outcome_unknown`` fields of the
snapshot. Other: ``_actuation``, ``_attempts`` (the attempts kept for a restart).
"""

from __future__ import annotations

from dataclasses import replace
import time
from typing import Any, Optional

from dps_parachute_ros import protocol as p
from dps_parachute_ros.link import LinkBusy, LinkDown, LinkError, LinkTimeout
from dps_parachute_ros.state import Outcome, Result, Snapshot

DEPLOY_TOKEN = 'DEPLOY'
MAX_FAILED_DEPLOYS = 2
"""P11: three unsuccessful attempts in a row put the module into protection; we stop at two."""
REREAD_WAIT_S = 1.0
"""A deploy or an arm waits this long for the module's state to be re-read (D15)."""
ACTUATION_WAIT_S = 10.0
"""A deploy or arm waits this long for one already running."""
SAFETY_SYNC_S = 0.5
"""Longest wait for the black box's fsync on a safety event; none while it is failing."""
DEPLOY_FRAME = p.encode_deploy()
DEPLOY_OUTCOMES = {'refused': Outcome.REFUSED, 'already deployed': Outcome.DONE,
                   'deployed': Outcome.DONE, 'not deployed': Outcome.FAILED}
"""The outcome of each way `_deploy_end` ends a deploy (an unknown one: `_deploy_unknown`);
another word is DONE when it succeeded, else FAILED (never a refusal not decided as one)."""


class DeployProcedure:
    """The deploy procedure of `ParachuteSession` (a mixin: it uses the session's state)."""

    def _safety_sync(self) -> bool:
        """Fsync the black box on a safety event: bounded, and no wait while it is failing."""
        return self.blackbox.sync(SAFETY_SYNC_S if self.blackbox.status().writing else 0.0)

    def _on_tx(self, data: bytes) -> None:
        # Every deploy frame that leaves counts until the module answers one, whatever ends
        # the wait (P11, D6): a timeout, a dropped link, a shutdown.
        if data == DEPLOY_FRAME:
            with self._lock:
                self._deploy_frame_left = True
                self._deploy_frame_at = self.clock()
                self._snap = replace(self._snap, unacked_deploys=self._snap.unacked_deploys + 1,
                                     failed_deploys=self._snap.failed_deploys + 1)

    def _save_attempts(self, leaving: int = 0) -> None:
        """Keep the unsuccessful deploy frames of this power-up for a later run (P11)."""
        snap = self.snapshot
        problem = self._attempts.save(snap.boot_count, snap.failed_deploys + leaving,
                                      snap.unacked_deploys + leaving)
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
        """`~/deploy`: the rules of the README's "Safety model of deploy" (D6)."""
        t0 = self.clock()
        self.blackbox.record('request', what='deploy', token_ok=confirm == DEPLOY_TOKEN,
                             arm_if_locked=arm_if_locked)
        if confirm != DEPLOY_TOKEN:
            return self._deploy_end('refused', f"deploy refused: confirm must be exactly "
                                    f"'{DEPLOY_TOKEN}' (got {confirm!r}); nothing sent")
        if not self._actuation.acquire(timeout=ACTUATION_WAIT_S):
            return self._deploy_end('refused', 'deploy refused: another deploy or arm did not '
                                    f'finish within {ACTUATION_WAIT_S:.0f} s; nothing sent')
        try:
            if self._stopping.is_set():
                return self._deploy_end('refused', 'deploy refused: the driver is shutting '
                                        'down; nothing sent')
            return self._deploy(arm_if_locked, t0)
        finally:
            self._save_attempts()
            self._actuation.release()

    def _reread(self, snap: Snapshot) -> Snapshot:
        """Ask the module what a deploy or an arm needs, when the driver's knowledge is old.

        A module that answers is online (its answer is a frame), however it was judged before:
        an offline verdict or a re-read still to come never refuses a module that answers.
        """
        if not snap.port_open:
            return snap
        epoch = self._current_epoch()
        try:
            # A reboot first (D15); a module silent to this one query is judged by the next.
            epoch = self._note_boot_count(
                self._req(p.encode_boot_count_query(), silence_ok=snap.online).count)
        except LinkTimeout:
            if not snap.online:
                return self.snapshot  # silent: offline it is
        except LinkError:
            return self.snapshot
        try:
            # Armed and triggered in one frame; the two queries if it does not answer that.
            self._on_status(self._req(p.encode_status_query(), retries=1), 'query', epoch)
        except LinkTimeout:
            try:
                armed = self._req(p.encode_armed_query(), retries=1).armed
                triggered = self._req(p.encode_triggered_query(), retries=1).triggered
            except LinkError:
                return self.snapshot
            self._set_triggered(triggered, 'query', epoch, armed=armed, fresh=True)
        except LinkError:
            pass
        return self.snapshot

    def _seen_triggered(self) -> str:
        """How the driver knows the module deployed, or '' (triggered not seen)."""
        with self._lock:
            if not self._snap.triggered or self._triggered_seen is None:
                return ''
            at, via = self._triggered_seen
            sent = self._deploy_frame_at
        text = f'the module reported TRIGGERED (via {via}'
        if sent is not None and at >= sent:
            text += f', {(at - sent) * 1000:.0f} ms after the deploy frame left'
        return text + ')'

    def _deploy(self, arm_if_locked: bool, t0: float) -> Result:
        snap = self.snapshot
        if snap.online and not snap.fresh:
            snap = self._wait_fresh()
        if not snap.online or not snap.fresh:
            snap = self._reread(snap)
        if not snap.online:
            seen = self._seen_triggered()
            if seen:
                # A deployment stays one: the module stays triggered until switched off.
                return self._deploy_end('already deployed', f'already deployed: {seen}; it '
                                        f'is offline now ({snap.offline_reason}); nothing '
                                        'sent', success=True)
            return self._deploy_end('refused', f'deploy refused: {self._offline_text(snap)}; '
                                    'nothing sent')
        if snap.fresh and snap.triggered:
            return self._deploy_end('already deployed', 'already deployed: the module reports '
                                    'triggered; nothing sent', success=True)
        if not snap.fresh:
            return self._deploy_end(
                'refused', 'deploy refused: the module may have rebooted and has not been '
                're-read (it did not answer the status, armed or triggered query), so whether it '
                'is armed is not known; nothing sent. Try again in a moment.')
        if snap.armed is not True:
            if not arm_if_locked:
                return self._deploy_end(
                    'refused', 'deploy refused: the module is locked (a locked module cannot '
                    'deploy); arm it with ~/arm or set arm_if_locked; nothing sent')
            armed = self._arm(True, judge=False)  # deploying is what was asked
            if not armed.ok:
                return self._deploy_end('refused', f'deploy refused: arming failed: '
                                        f'{armed.message}')
        attempts = 0
        while True:
            snap = self.snapshot
            if attempts and not (snap.fresh and snap.armed):
                # It rebooted (or was locked) during the wait: a retry would go out on old
                # knowledge (D15). The triggered query just said it did not deploy.
                snap = self._wait_fresh()
                if not snap.fresh or not snap.armed:
                    state = 'is locked now' if snap.fresh else 'rebooted and was not re-read'
                    return self._deploy_end(
                        'not deployed', f'deploy NOT acknowledged after {attempts} attempt(s), '
                        f'the module reports it is not triggered: it did NOT deploy, and it '
                        f'{state}; not retrying', t0=t0)
            if snap.failed_deploys >= MAX_FAILED_DEPLOYS:
                if attempts:
                    return self._deploy_end(
                        'not deployed', f'deploy NOT acknowledged after {attempts} attempts, '
                        'and the module reports it is not triggered: it did NOT deploy. Not '
                        'retrying (P11: three unsuccessful attempts put the module into '
                        'protection)', t0=t0)
                return self._deploy_end('refused', self._guard_text(snap))
            if not attempts and self.release_gate is not None:
                self.release_gate.before_release('deploy')  # every refusal is decided above
            attempts += 1
            # The decision is on disk before the frame leaves: a crash between the two must
            # not leave a deployment the black box never heard of.
            self.blackbox.record('decision', what='deploy: sending the deploy frame',
                                 attempt=attempts)
            self._safety_sync()
            self._save_attempts(leaving=1)  # a respawned driver counts it too (P11)
            with self._lock:
                self._deploy_frame_left = False
            try:
                ack = self._req(DEPLOY_FRAME)
            except LinkTimeout:
                ack = None
            except LinkBusy as exc:
                return self._deploy_end('refused', f'deploy refused: {exc}')
            except LinkDown as exc:
                with self._lock:
                    left = self._deploy_frame_left
                if not left and attempts == 1:
                    return self._deploy_end('refused', f'deploy failed before the frame left: '
                                            f'{exc}; nothing sent')
                why = ('the driver is shutting down' if self._stopping.is_set()
                       else f'the link dropped ({exc})')
                sent = attempts if left else attempts - 1
                return self._deploy_unknown(
                    f'{sent} deploy frame(s) sent, but {why} before any acknowledgement', t0)
            if ack is not None:
                self._on_deploy_reply(ack, late=False)
                return self._deploy_answered(ack, attempts, t0)
            # No acknowledgement: lost on either way, or corrupted. Before any retry, ask
            # whether it deployed (D6): a triggered module refuses a retry and counts it.
            triggered = self._query_triggered()
            if triggered or self.snapshot.triggered:
                return self._deploy_end(
                    'deployed', f'deployed: the module reports triggered; its acknowledgement '
                    f'was lost ({attempts} attempt(s))', success=True, t0=t0, ack='lost')
            if triggered is None and self.snapshot.failed_deploys >= MAX_FAILED_DEPLOYS:
                return self._deploy_unknown(
                    f'{attempts} deploy frame(s) sent, none acknowledged, and the module did '
                    'not answer whether it is triggered', t0)

    def _deploy_answered(self, ack: p.DeployAck, attempts: int, t0: float) -> Result:
        latency = (self.clock() - t0) * 1000.0
        if ack.success:
            # The acknowledgement is on disk before anyone hears of it (SIGKILL-safe).
            self.blackbox.record('decision', what='deploy acknowledged', hex=ack.raw.hex(' '),
                                 latency_ms=latency, attempts=attempts)
            self._safety_sync()
            return self._deploy_end('deployed', f'deployed: acknowledged after {attempts} '
                                    f'attempt(s), {latency:.1f} ms', success=True, t0=t0,
                                    log=False)
        self.blackbox.record('decision', what='deploy refused by module', hex=ack.raw.hex(' '))
        # Never "did not deploy" while the module says it is triggered (D6).
        triggered = self._query_triggered()
        if triggered:
            return self._deploy_end(
                'deployed', f'deployed: the module refused this frame ({ack.raw.hex(" ")}) '
                'because it is already triggered: an earlier frame deployed it and its '
                'acknowledgement was lost', success=True, t0=t0, ack='lost')
        if triggered is None:
            return self._deploy_unknown(f'the module refused the deploy frame '
                                        f'({ack.raw.hex(" ")}) and did not answer whether it '
                                        'is triggered', t0)
        return self._deploy_end(
            'not deployed', f'the module answered {ack.raw.hex(" ")} and reports it is not '
            'triggered: it did NOT deploy (locked, or in protection after unsuccessful '
            'attempts)', t0=t0)

    def _guard_text(self, snap: Snapshot) -> str:
        if snap.unacked_deploys >= MAX_FAILED_DEPLOYS:
            what = f'{snap.unacked_deploys} deploy frames in a row went unacknowledged'
        else:
            what = (f'{snap.failed_deploys} deploy frames in a row were refused or went '
                    'unacknowledged')
        return (f'deploy refused: {what}; a third could put the module into protection (P11). '
                'Check the link; a module reboot clears this. Nothing sent')

    def _deploy_unknown(self, what: str, t0: float) -> Result:
        seen = self._seen_triggered()
        if seen:
            # Seen triggered after the frame left: a deployment, whatever became of the reply.
            with self._lock:
                self._snap = replace(self._snap, unacked_deploys=0, failed_deploys=0)
            return self._deploy_end('deployed', f'deployed: {seen}; its acknowledgement did '
                                    f'not come ({what})', success=True, t0=t0, ack='lost')
        with self._lock:
            self._unknown_boot = self._snap.boot_count
        self._update(deploy_outcome_unknown=True)
        message = (f'deploy outcome UNKNOWN: {what}. The driver reads the triggered state as '
                   'soon as the module answers again and reports a deployment on '
                   '~/trigger_event')
        self.blackbox.record('decision', what='deploy', outcome='unknown', reason=message)
        self._safety_sync()
        self._log('error', message)
        self.listener.on_diagnostics()
        return Result.unknown(message, cause='no_reply')

    def _deploy_end(self, outcome: str, message: str, success: bool = False,
                    t0: Optional[float] = None, log: bool = True, **extra: Any) -> Result:
        latency = None if t0 is None else (self.clock() - t0) * 1000.0
        if outcome == 'refused' and self.snapshot.deploy_outcome_unknown:
            # True of this call, and not the whole truth: a caller must never read "refused"
            # as "the parachute did not deploy" while an earlier frame's fate is not known.
            message += ('; an earlier deploy frame left without an acknowledgement: its outcome '
                        'is UNKNOWN (the parachute may have deployed) until the module answers')
        self.blackbox.record('decision', what='deploy', outcome=outcome, success=success,
                             reason=message, **extra)
        self._safety_sync()
        if log:
            self._log('info' if success else 'warn', message)
        if success:
            self._emit_status()
        kind = DEPLOY_OUTCOMES.get(outcome, Outcome.DONE if success else Outcome.FAILED)
        return Result(kind, message, latency_ms=latency if success else None)

    def arm(self, want: bool) -> Result:
        """`~/arm`: arm or lock; success only when the reply and a query agree (P7)."""
        self.blackbox.record('request', what='arm' if want else 'lock')
        if not self._actuation.acquire(timeout=ACTUATION_WAIT_S):
            return Result.refused('busy', 'another deploy or arm is still running; nothing sent')
        try:
            result = self._arm(want)
        finally:
            self._actuation.release()
        self._log('info' if result.ok else 'warn', result.message)
        return result

    def _arm(self, want: bool, judge: bool = True) -> Result:
        """Arm or lock, verified; an arm that would fire at once is refused (D16, P21).

        `judge` False: arming for a deploy (``arm_if_locked``), where firing is the point.
        """
        word = 'arm' if want else 'lock'
        snap = self.snapshot
        if want and snap.online and not snap.fresh:
            snap = self._wait_fresh()
        if not snap.online or (want and not snap.fresh):
            snap = self._reread(snap)
        if not snap.online:
            return Result.refused('offline', f'cannot {word}: {self._offline_text(snap)}; '
                                  'nothing sent')
        if want and not snap.fresh:
            return Result.refused('not_reread', (
                'cannot arm: the module may have rebooted and has not been re-read, so whether '
                'it has deployed is not known; nothing sent'))
        if want and snap.triggered:
            return Result.refused('triggered', (
                'cannot arm: the module has deployed (triggered); a triggered module is never '
                're-armed. Re-pack it and switch it off and on; nothing sent'))
        epoch = self._current_epoch()
        try:
            danger = self._gate([('armed', True)], '~/arm') if want and judge else ''
            if danger:
                return Result.refused('would_deploy', f'cannot arm, nothing sent: {danger}')
            reply = self._req(p.encode_arm(want), retries=1)
            if reply.armed != want:
                return Result.failed(f'module answered {reply.raw.hex(" ")} to {word}: '
                                     f'it stays {"armed" if reply.armed else "locked"}')
            try:
                state = self._req(p.encode_armed_query(), retries=1)
            except LinkTimeout:
                # The status frame tells armed too: a module silent to the armed query alone
                # is still verified (and can be armed for a deploy).
                state = self._req(p.encode_status_query(), retries=1)
        except LinkError as exc:
            return Result.unknown(f'{word} not confirmed: {exc}', cause='no_reply')
        self._update_if(epoch, armed=state.armed)
        self.blackbox.record('state', armed=state.armed, via=word)
        self._safety_sync()
        self._emit_status()
        self.listener.on_diagnostics()
        if state.armed != want:
            return Result.failed(f'module acknowledged {word} but the query says '
                                 f'{"armed" if state.armed else "locked"}')
        return Result.done('armed (verified by query)' if want else 'locked (verified by query)')
