"""The deploy procedure (D6) as a state machine without I/O: events in, actions out (issue 22).

`DeployCore` holds what a deploy decides on: whether the port is open and the module answers,
whether its armed and triggered states were read since it last could have changed unseen (D15),
its boot count, the deploy frames of this power-up without a successful acknowledgement (P11),
and a deploy whose outcome is not known. It owns no thread, lock, clock, port or file: every
event carries its time (``now``, monotonic seconds), and `DeployCore.step` returns the actions
to carry out in order. ``uav_serial_common.core_runner`` carries them out over a link; the model
test (test/test_parachute_model.py) over the device model, in virtual time.

A deploy or arm call is a generator that yields each `Request` (or `PassGate`, `JudgeArm`)
and gets back the event that ended the wait. One call runs at a time; a call while one runs is
refused, nothing sent.

The rules, each in one place: a deploy frame only on an armed state read since the last known
reboot (D15); at most two deploy frames of a power-up without a successful acknowledgement,
counted from the moment the frame may leave and kept across runs (``SaveAttempts``; a new core
takes them back, P11); the decision is recorded (synced) before the frame leaves; every call is
answered once, and never "refused"/"did NOT deploy" when the module deployed nor "deployed" when
it did not: when that is not known the answer says UNKNOWN. An arm (`ArmCall`) goes only on an
armed and triggered state read since the last reboot seen, to a module not triggered, after the
settings core's check that it would not deploy the module at once (what came in while that ran
is judged again); "armed" or "locked" only when a query read it back after the reply (P7).
"""

from __future__ import annotations

from typing import Any, Generator, List, Optional, Set, Tuple, Type, Union

from dps_parachute_ros import protocol as p
from dps_parachute_ros.deploy_events import (  # noqa: F401 (the core's vocabulary, re-exported)
    Action, ArmAnswer, ArmCall, ArmJudged, Busy, DeployAnswer, DeployCall, Event, GateDone,
    guard_text, JudgeArm, LinkDown, LinkUp, Log, MAX_FAILED_DEPLOYS, PassGate, Rebooted, Record,
    Reply, Report, Request, REQUEST_TIMEOUT_S, SaveAttempts, Stored, SYNC_WAIT, Timeout, why)
from dps_parachute_ros.deploy_knowledge import (  # noqa: F401 (re-exported)
    DeployKnowledge, POWER_UP_HEARTBEATS_S)
from uav_serial_common.result import Outcome, Result

DEPLOY_TOKEN = 'DEPLOY'
DEPLOY_FRAME = p.encode_deploy()
_Wait = Generator[Union[Request, PassGate, JudgeArm], Event, None]
ARM_CHECKS = 2
"""An arm checks the module at most this often when it changes while checked; then refuses."""


class DeployCore(DeployKnowledge):
    """What a deploy decides on (`DeployKnowledge`), and the deploy procedure."""

    def __init__(self, stored: Optional[Any] = None, port_open: bool = False,
                 request_timeout_s: float = REQUEST_TIMEOUT_S, mirror: bool = False) -> None:
        """Start knowing nothing; `stored`: an earlier run's attempts (boot, failed, unacked).

        `mirror`: the caller (the session) keeps what is known of the module and tells it with
        `know` before each step; the core returns only the procedure's own actions then.
        """
        super().__init__(stored, port_open, request_timeout_s, mirror)
        self._query_end: Optional[Event] = None  # what ended the last triggered query
        self._call: Optional[_Wait] = None

    # -- the one entry point -------------------------------------------------------------------

    @property
    def busy(self) -> bool:
        """Whether a call is running (waiting for a reply or the gate)."""
        return self._call is not None

    def step(self, event: Event) -> List[Action]:
        """Take one event; return the actions to carry out, in order."""
        self._now = event.now
        if isinstance(event, (DeployCall, ArmCall)):
            if self._call is None:
                self._call = (self._deploy(event) if isinstance(event, DeployCall)
                              else self._arm_call(event))
                self._advance(None)
            elif isinstance(event, DeployCall):
                self._answer('refused', 'deploy refused: another deploy or arm is still '
                             'running; nothing sent')
            else:
                self._out.append(ArmAnswer(Result.refused(
                    'busy', 'another deploy or arm is still running; nothing sent')))
        elif self._call is not None and self._answers_wait(event):
            if isinstance(event, Reply):
                self._take(event.message, solicited=True)
            else:
                self._link_event(event)
            self._advance(event)
        else:
            if isinstance(event, Reply):
                self._take(event.message, solicited=False)
            else:
                self._link_event(event)
        out, self._out = self._out, []
        return out

    def _answers_wait(self, event: Event) -> bool:
        wait = self._waiting
        if isinstance(wait, PassGate):
            return isinstance(event, GateDone)
        if isinstance(wait, JudgeArm):
            return isinstance(event, ArmJudged)
        if wait is None:
            return False
        if isinstance(event, Reply):
            if isinstance(event.message, p.TriggerRecords):
                return p.TriggerRecord in wait.expect
            return isinstance(event.message, wait.expect)
        return isinstance(event, (Timeout, LinkDown, Busy))

    def _advance(self, event: Optional[Event]) -> None:
        assert self._call is not None
        try:
            self._waiting = self._call.send(event)  # type: ignore[arg-type]
        except StopIteration:
            self._call = None
            self._waiting = None
            return
        self._out.append(self._waiting)

    def _request(self, frame: bytes, expect: Type, retries: int = 0,
                 silence_ok: bool = False) -> Request:
        deadline = self._now + self.timeout_s * (retries + 1)
        return Request(frame, (expect,), deadline, retries, silence_ok)

    # -- the procedure -------------------------------------------------------------------------

    def _answer(self, outcome: str, message: str, ok: bool = False,
                t0: Optional[float] = None, log: bool = True,
                counts: Optional[Tuple[int, int]] = None, **extra: Any) -> None:
        if outcome == 'refused' and self.outcome_unknown:
            # True of this call, and not the whole truth: a caller must never read "refused"
            # as "the parachute did not deploy" while an earlier frame's fate is not known.
            message += ('; an earlier deploy frame left without an acknowledgement: its outcome '
                        'is UNKNOWN (the parachute may have deployed) until the module answers')
        self._out.append(Record.of('decision', SYNC_WAIT, what='deploy', outcome=outcome,
                                   success=ok, reason=message, **extra))
        if log:
            self._out.append(Log('info' if ok else 'warn', message))
        latency = None if t0 is None or not ok else (self._now - t0) * 1000.0
        self._out.append(DeployAnswer(outcome, ok, message, latency, counts))

    def _unknown(self, what: str, t0: float) -> None:
        seen = self._seen_triggered()
        if seen:
            # Seen triggered after the frame left: a deployment, whatever became of the reply.
            self.failed = self.unacked = 0
            self._save()
            self._answer('deployed', f'deployed: {seen}; its acknowledgement did not come '
                         f'({what})', ok=True, t0=t0, counts=(0, 0), ack='lost')
            return
        self.outcome_unknown = True
        self._unknown_boot = self.boot_count
        message = (f'deploy outcome UNKNOWN: {what}. The driver reads the triggered state as '
                   'soon as the module answers again and reports a deployment on '
                   '~/trigger_event')
        self._out.append(Record.of('decision', SYNC_WAIT, what='deploy', outcome='unknown',
                                   reason=message))
        self._out.append(Log('error', message))
        self._out.append(DeployAnswer('unknown', False, message))

    def _reread(self) -> _Wait:
        """Ask the module what a deploy needs, when the driver's knowledge is old (D15)."""
        if not self.port_open:
            return
        event = yield self._request(p.encode_boot_count_query(), p.BootCount,
                                    silence_ok=self.online)
        if isinstance(event, Timeout) and not self.online:
            return  # silent: offline it is
        if isinstance(event, (LinkDown, Busy)):
            return
        event = yield self._request(p.encode_status_query(), p.Status, retries=1)
        if not isinstance(event, Timeout):
            return
        reboots = self.reboots
        event = yield self._request(p.encode_armed_query(), p.ArmedState, retries=1)
        if not isinstance(event, Reply):
            return
        armed = event.message.armed
        event = yield self._request(p.encode_triggered_query(), p.TriggeredState, retries=1)
        if isinstance(event, Reply) and reboots == self.reboots:
            # (An armed state read before a reboot seen since is not this power-up's.)
            self._reread_done(armed)

    def _query_triggered(self) -> Generator[Request, Event, Optional[bool]]:
        event = yield self._request(p.encode_triggered_query(), p.TriggeredState)
        self._query_end = event
        return event.message.triggered if isinstance(event, Reply) else None

    def _deployed_in(self, boot: Optional[int],
                     known: Set[Optional[int]]) -> Generator[Request, Event, Optional[bool]]:
        """Read whether the trigger records show a deployment since power-up `boot`.

        Since: a reboot no heartbeat told may have come before the frame. By a serial frame
        (another source's deployment is not this call's), not in the power-ups `known` to have
        deployed before the frame left (one deployment per power-up). None: not known
        (the records not read, or an answer cut short that does not hold it).
        """
        if boot is None or self.boot_count is None:
            return None
        event = yield self._request(p.encode_trigger_records_query(), p.TriggerRecord)
        if not isinstance(event, Reply):
            return None
        since = (self.boot_count - boot) % 256  # (the boot count wraps after 255)
        records: p.TriggerRecords = event.message
        fired = any((r.boot_count - boot) % 256 <= since and r.serial_trigger
                    and r.boot_count not in known for r in records)
        # No record of it in an answer cut short is no answer (P15): not "it did NOT deploy".
        return True if fired else (False if records.complete else None)

    def _arm_call(self, call: ArmCall) -> _Wait:
        """`~/arm`: arm or lock, verified by a query (P7); never an arm that fires (D16, P21).

        An arm goes only on an armed and triggered state read since the last reboot seen
        (D15), to a module not triggered, and after the settings core's check that arming
        would not deploy it at once; a lock always may go to a module that answers.
        """
        want = call.want
        word = 'arm' if want else 'lock'
        self._out.append(Record.of('request', what=word))
        for _ in range(ARM_CHECKS):
            if not self.online or (want and not self.fresh):
                yield from self._reread()
            if not self.online:
                self._arm_answer(Result.refused('offline', f'cannot {word}: module offline '
                                                f'({self.offline_reason}); nothing sent'))
                return
            if want and not self.fresh:
                self._arm_answer(Result.refused('not_reread', (
                    'cannot arm: the module may have rebooted and has not been re-read, so '
                    'whether it has deployed is not known; nothing sent')))
                return
            if want and self.triggered:
                self._arm_answer(Result.refused('triggered', (
                    'cannot arm: the module has deployed (triggered); a triggered module is '
                    'never re-armed. Re-pack it and switch it off and on; nothing sent')))
                return
            if not want:
                break
            reboots = self.reboots
            judged = yield JudgeArm('~/arm')
            assert isinstance(judged, ArmJudged)
            if judged.problem:
                self._arm_answer(Result.refused('no_reply', (
                    'cannot arm: whether arming would deploy the module at once is not known '
                    f'({judged.problem}); nothing sent')))
                return
            if judged.danger:
                self._arm_answer(Result.refused('would_deploy',
                                                f'cannot arm, nothing sent: {judged.danger}'))
                return
            if self.reboots == reboots and self.online and self.fresh and not self.triggered:
                break
            # What came in while the check ran (a reboot, a silence, a deployment) is judged
            # as the check was: on the module read afresh (D15).
        else:
            self._arm_answer(Result.refused('not_reread', (
                f'cannot arm: the module changed while it was checked, {ARM_CHECKS} times (a '
                'reboot, a silence or a deployment); nothing sent. Try again in a moment.')))
            return
        result = yield from self._arm(want)
        self._arm_answer(result)

    def _arm_answer(self, result: Result) -> None:
        self._out.append(ArmAnswer(result))

    def _arm(self, want: bool) -> Generator[Request, Event, Result]:
        """Send the arm (or lock) frame and read the armed state back; what became of it.

        DONE only when the reply and the query agree (P7). UNKNOWN when the frame left and
        what it did was not seen (the armed state is then unknown: read afresh, D15), or when
        a reboot seen after the query was asked may have locked the module since.
        """
        word = 'arm' if want else 'lock'
        event = yield self._request(p.encode_arm(want), p.ArmReply, retries=1)
        if isinstance(event, (Busy, LinkDown)) and not getattr(event, 'frame_left', False):
            return Result.refused('busy' if isinstance(event, Busy) else 'offline',
                                  f'{word} not sent: {why(event)}')
        if not isinstance(event, Reply):
            self._armed_unknown()
            return Result.unknown(f'{word} not confirmed: {why(event)}', cause='no_reply')
        reply = event.message
        if reply.armed != want:
            return Result.failed(f'module answered {reply.raw.hex(" ")} to {word}: it stays '
                                 f'{"armed" if reply.armed else "locked"}')
        # The read-back is of the module as it is when asked: a reboot found while the frame
        # was on its way does not void it (one found after it does).
        reboots = self.reboots
        event = yield self._request(p.encode_armed_query(), p.ArmedState, retries=1)
        if isinstance(event, Timeout):
            # The status frame tells armed too: a module silent to the armed query alone is
            # still verified.
            event = yield self._request(p.encode_status_query(), p.Status, retries=1)
        if not isinstance(event, Reply):
            self._armed_unknown()
            return Result.unknown(f'{word} not confirmed: {why(event)}', cause='no_reply')
        armed = event.message.armed
        taken = reboots == self.reboots
        if taken:
            self.armed = armed
        self._out.append(Record.of('state', SYNC_WAIT, armed=armed, via=word))
        if armed != want:
            return Result.failed(f'module acknowledged {word} but the query says '
                                 f'{"armed" if armed else "locked"}')
        if want and not taken:
            # A reboot locks the module, and one may have come after the query was answered.
            return Result.unknown('arm not confirmed: the query says armed, but the module may '
                                  'have rebooted since (a reboot locks it); it is read afresh',
                                  cause='rebooted')
        return Result.done(f'{"armed" if want else "locked"} (verified by query)')

    def _armed_unknown(self) -> None:
        """Forget the armed state: an arm or lock frame left unseen; read afresh first (D15)."""
        self.armed, self.fresh, self._stale = None, False, True

    def _deploy(self, call: DeployCall) -> _Wait:
        t0 = call.now
        self._out.append(Record.of('request', what='deploy',
                                   token_ok=call.token == DEPLOY_TOKEN,
                                   arm_if_locked=call.arm_if_locked))
        if call.token != DEPLOY_TOKEN:
            self._answer('refused', f"deploy refused: confirm must be exactly '{DEPLOY_TOKEN}' "
                         f'(got {call.token!r}); nothing sent')
            return
        if not (yield from self._judge(call)):
            return
        yield from self._attempts(call, t0)
        self._save()

    def _judge(self, call: DeployCall) -> Generator[Union[Request, PassGate], Event, bool]:
        """Decide on what is known, read afresh where it is old (D15); False: answered."""
        if not self.online or not self.fresh or not self.boot_current:
            # (The boot count too: a reboot after the frame left must be told from none.)
            yield from self._reread()
        if not self.online:
            seen = self._seen_triggered()
            if seen:
                # A deployment stays one: the module stays triggered until switched off.
                self._answer('already deployed', f'already deployed: {seen}; it is offline now '
                             f'({self.offline_reason}); nothing sent', ok=True)
            else:
                self._answer('refused', f'deploy refused: module offline '
                             f'({self.offline_reason}); nothing sent')
            return False
        if self.fresh and self.triggered:
            self._answer('already deployed', 'already deployed: the module reports triggered; '
                         'nothing sent', ok=True)
            return False
        if not self.fresh:
            self._answer('refused', 'deploy refused: the module may have rebooted and has not '
                         'been re-read (it did not answer the status, armed or triggered query), '
                         'so whether it is armed is not known; nothing sent. Try again in a '
                         'moment.')
            return False
        if self.armed is not True:
            if not call.arm_if_locked:
                self._answer('refused', 'deploy refused: the module is locked (a locked module '
                             'cannot deploy); arm it with ~/arm or set arm_if_locked; nothing '
                             'sent')
                return False
            armed = yield from self._arm(True)
            if armed.outcome is not Outcome.DONE:
                self._answer('refused', f'deploy refused: arming failed: {armed.message}')
                return False
        return True

    def _attempts(self, call: DeployCall, t0: float) -> _Wait:
        attempts = 0
        reboots = self.reboots
        # Every frame of this call goes to this power-up (None: a module silent to the boot
        # count query is deployed too, round 2; its frames count until a read tells, P11).
        frame_boot = self.boot_count if self.boot_current else None
        known = set(self._reported)  # power-ups known to have deployed before the frame
        said_not_triggered = False
        while True:
            if attempts and not (self.fresh and self.armed):
                # Silent for a moment, or a reboot or a lock seen: read it again first (D15).
                reads = self.boot_reads
                yield from self._reread()
                if self.fresh and self.triggered is False and self.reboots == reboots:
                    # The re-read asked the boot count before the status: "not triggered" may
                    # be a power-up's after a reboot between the two whose heartbeats were
                    # lost (the search found it). The count asked again after it tells.
                    after = self.boot_reads
                    yield self._request(p.encode_boot_count_query(), p.BootCount, retries=1)
                    if self.boot_reads == after:
                        self._unknown(f'{attempts} deploy frame(s) sent, none acknowledged; '
                                      'the module says it is not triggered but did not answer '
                                      'its boot count after that, so a reboot since is not '
                                      'ruled out', t0)
                        return
                # Its status, read again, answers "triggered?" too.
                said_not_triggered = said_not_triggered or (self.fresh and
                                                            self.triggered is False)
                seen = self._seen_triggered()
                if seen or (self.fresh and self.triggered):
                    self._answer('deployed', 'deployed: the module reports triggered; its '
                                 f'acknowledgement was lost ({attempts} attempt(s))', ok=True,
                                 t0=t0, ack='lost')
                    return
                if self.reboots != reboots or self.boot_count != frame_boot:
                    # A reboot after a frame left: "not triggered" now tells nothing of the
                    # power-up the frame went to; its trigger records do.
                    fired = yield from self._deployed_in(frame_boot, known)
                    if fired:
                        self._answer('deployed', f'deployed: the module rebooted after the '
                                     f'deploy frame left, and its trigger records show a serial '
                                     f'deployment in boot {frame_boot} or after; its '
                                     f'acknowledgement was lost ({attempts} attempt(s))', ok=True,
                                     t0=t0, ack='lost')
                    elif fired is None:
                        self._unknown(f'{attempts} deploy frame(s) sent, none acknowledged, and '
                                      'the module rebooted since (its trigger records not read '
                                      'whole)',
                                      t0)
                    else:
                        state = 'is locked now' if self.fresh else 'was not re-read'
                        self._answer('not deployed', f'deploy NOT acknowledged after {attempts} '
                                     f'attempt(s); the module rebooted since, and its trigger '
                                     'records show no serial deployment since boot '
                                     f'{frame_boot}: it did NOT deploy, and it {state}; not '
                                     'retrying', t0=t0)
                    return
                if not said_not_triggered:
                    self._unknown(f'{attempts} deploy frame(s) sent, none acknowledged, and the '
                                  'module did not answer whether it is triggered', t0)
                    return
                if self.boot_reads == reads:
                    # Its "not triggered" may come from a power-up after a reboot unseen.
                    self._unknown(f'{attempts} deploy frame(s) sent, none acknowledged; the '
                                  'module says it is not triggered but did not answer its boot '
                                  'count, so a reboot since is not ruled out', t0)
                    return
                if not self.fresh or not self.armed:
                    state = 'is locked now' if self.fresh else 'rebooted and was not re-read'
                    self._answer('not deployed', f'deploy NOT acknowledged after {attempts} '
                                 'attempt(s), the module reports it is not triggered: it did '
                                 f'NOT deploy, and it {state}; not retrying', t0=t0)
                    return
            if self.failed >= MAX_FAILED_DEPLOYS:
                if attempts:
                    self._answer('not deployed', f'deploy NOT acknowledged after {attempts} '
                                 'attempts, and the module reports it is not triggered: it did '
                                 'NOT deploy. Not retrying (P11: three unsuccessful attempts put '
                                 'the module into protection)', t0=t0)
                else:
                    self._answer('refused', guard_text(self.failed, self.unacked))
                return
            if not attempts and call.gate:
                yield PassGate('deploy')  # every refusal is decided above...
                if self._changed_since(reboots):
                    # ...on what was known before the gate: what came in while it was passed
                    # (a reboot or a late heartbeat, a lock, a deployment, a silence) is judged
                    # as before it: read afresh, then sent, or answered (D15).
                    if not (yield from self._judge(call)):
                        return
                    reboots = self.reboots
                    frame_boot = self.boot_count if self.boot_current else None
                    known = set(self._reported)
            attempts += 1
            # The decision is on disk before the frame leaves: a crash between the two must
            # not leave a deployment the black box never heard of.
            self._out.append(Record.of('decision', SYNC_WAIT,
                                       what='deploy: sending the deploy frame',
                                       attempt=attempts))
            self.failed += 1
            self.unacked += 1
            self._sent_since_read += 1
            self._frame_at = self._now
            self._save(leaving=True)  # a respawned driver counts it too (P11)
            event = yield self._request(DEPLOY_FRAME, p.DeployAck)
            if isinstance(event, Busy):
                self.failed -= 1
                self.unacked -= 1
                self._sent_since_read -= 1
                self._save()
                self._answer('refused', f'deploy refused: {event.reason}')
                return
            if isinstance(event, LinkDown):
                if not event.frame_left:
                    self.failed -= 1
                    self.unacked -= 1
                    self._sent_since_read -= 1
                    self._save()
                    if attempts == 1:
                        self._answer('refused', f'deploy failed before the frame left: '
                                     f'{event.reason}; nothing sent')
                        return
                sent = attempts if event.frame_left else attempts - 1
                why = ('the driver is shutting down' if event.shutting_down
                       else f'the link dropped ({event.reason})')
                self._unknown(f'{sent} deploy frame(s) sent, but {why} before any '
                              'acknowledgement', t0)
                return
            if isinstance(event, Reply):
                self._deploy_reply(event.message, late=False)
                yield from self._answered(event.message, attempts, t0)
                return
            # No acknowledgement: lost on either way, or corrupted. Before any retry, ask
            # whether it deployed (D6): a triggered module refuses a retry and counts it.
            triggered = yield from self._query_triggered()
            if triggered or self.triggered:
                self._answer('deployed', 'deployed: the module reports triggered; its '
                             f'acknowledgement was lost ({attempts} attempt(s))', ok=True, t0=t0,
                             ack='lost')
                return
            down = self._query_end
            if triggered is None and isinstance(down, LinkDown):
                why = ('the driver is shutting down' if down.shutting_down
                       else f'the link dropped ({down.reason})')
                self._unknown(f'{attempts} deploy frame(s) sent, but {why} before any '
                              'acknowledgement', t0)
                return
            if triggered is None and self.failed >= MAX_FAILED_DEPLOYS:
                self._unknown(f'{attempts} deploy frame(s) sent, none acknowledged, and the '
                              'module did not answer whether it is triggered', t0)
                return
            said_not_triggered = triggered is False

    def _changed_since(self, reboots: int) -> bool:
        """Whether what the deploy was decided on may have changed (a reboot, a lock, ...)."""
        return (self.reboots != reboots or not self.online or not self.fresh
                or not self.boot_current or self.triggered is not False
                or self.armed is not True)

    def _answered(self, ack: p.DeployAck, attempts: int, t0: float) -> _Wait:
        hexed = ack.raw.hex(' ')
        if ack.success:
            latency = (self._now - t0) * 1000.0
            # The acknowledgement is on disk before anyone hears of it (SIGKILL-safe).
            self._out.append(Record.of('decision', SYNC_WAIT, what='deploy acknowledged',
                                       hex=hexed, latency_ms=latency, attempts=attempts))
            self._answer('deployed', f'deployed: acknowledged after {attempts} attempt(s), '
                         f'{latency:.1f} ms', ok=True, t0=t0, log=False)
            return
        self._out.append(Record.of('decision', what='deploy refused by module', hex=hexed))
        # Never "did not deploy" while the module says it is triggered (D6).
        triggered = yield from self._query_triggered()
        if triggered:
            self._answer('deployed', f'deployed: the module refused this frame ({hexed}) because '
                         'it is already triggered: an earlier frame deployed it and its '
                         'acknowledgement was lost', ok=True, t0=t0, ack='lost')
        elif triggered is None:
            self._unknown(f'the module refused the deploy frame ({hexed}) and did not answer '
                          'whether it is triggered', t0)
        else:
            self._answer('not deployed', f'the module answered {hexed} and reports it is not '
                         'triggered: it did NOT deploy (locked, or in protection after '
                         'unsuccessful attempts)', t0=t0)
