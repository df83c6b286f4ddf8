"""The trigger-request policy (D8) as a state machine without I/O: events in, actions out.

The module asks "may I deploy?" (a trigger request, 0x39) when its crash detection fires on
external power, and deploys only on a confirmation within 1 s (P10, ``MODULE_WINDOW_S``). The
policy (``trigger_request_policy``: ``confirm``, ``deny`` or ``defer`` with ``defer_timeout_s``)
decides; under ``defer`` a caller answers with ``~/answer_trigger_request``. `TriggerCore` holds
the requests and the policy. It owns no thread, lock, clock, port or file: every event carries
its time (``now``, monotonic seconds), and `TriggerCore.step` returns the actions to carry out in
order (``session_triggers`` carries them out over the link; test/test_trigger_model.py over the
device model, in virtual time). What it must know of the module (online, triggered, armed and
whether that was read since it last could have changed unseen, D15) it is told with `know`.

The rules, each in one place:

- a confirmation leaves only while the policy in force says ``confirm``, or says ``defer`` and a
  caller answered true before the request's defer deadline; never while it says ``deny``
  (`_problem`, judged again after the release gate: a policy change, a reboot or the module's
  window may come while the gate waits);
- never after a reboot voided the request (the module boots locked and has forgotten it), and
  never 1 s or more after the request (``MODULE_WINDOW_S``: the module no longer waits for it);
- every request gets exactly one decision (`Decide`), a newer request settling an older one
  still open; a request nobody answered is denied at its deadline (`_expire`, before every
  event: a late monitor never lets an answer through after it);
- every answer call gets exactly one `Answer`, a `Result` that says what was sent: SENT only
  when the confirmation left, never "it deploys" on an armed state not read since the module
  could have changed unseen.

Under ``confirm`` without a release gate the confirmation is the first action of the step that
takes the request (the reader writes it at once: a confirm takes milliseconds). With a gate, the
core asks for it (`PassGate`) and decides when it is passed (`GateDone`). (Issue 22.)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple, Union

from dps_parachute_ros import protocol as p
from dps_parachute_ros.release_gate import GateDone, PassGate
from dps_parachute_ros.state import MODULE_WINDOW_S
from uav_serial_common.core_events import (Answer, LinkDown, LinkUp, Log, Rebooted, Record,
                                           SetTimer, SYNC_ASK, Tick)
from uav_serial_common.result import Result

CONFIRM_FRAME = p.encode_trigger_confirm()
ROUTE = 'trigger request'
"""The release gate's name for a confirmation (``ReleaseGate.before_release``)."""


# -- events ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class RequestReceived:
    """The module asked (0x39). `gate`: a release gate is there to pass before a confirm."""

    now: float
    gate: bool = False


@dataclass(frozen=True)
class AnswerCall:
    """``~/answer_trigger_request`` with `confirm`; `gate`: pass the release gate first."""

    now: float
    confirm: bool
    gate: bool = False


@dataclass(frozen=True)
class PolicyChanged:
    """The parameters ``trigger_request_policy`` and ``defer_timeout_s`` are now these."""

    now: float
    policy: str
    defer_timeout_s: float
    gate: bool = False


@dataclass(frozen=True)
class Sent:
    """The frame of `Write` `token` left."""

    now: float
    token: int


@dataclass(frozen=True)
class NotSent:
    """The frame of `Write` `token` could not be written (the link is down)."""

    now: float
    token: int
    reason: str


@dataclass(frozen=True)
class Stopped:
    """The driver stops: a request still open is left unanswered."""

    now: float


Event = Union[RequestReceived, AnswerCall, PolicyChanged, Rebooted, Tick, GateDone, Sent,
              NotSent, LinkDown, LinkUp, Stopped]


# -- actions -----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Write:
    """Write `frame` now, ahead of anything queued, expecting no reply (unlike a `Request`).

    The runtime feeds back `Sent` or `NotSent` with its `token`: the module does not acknowledge
    a confirmation.
    """

    frame: bytes
    token: int
    t_request: float


@dataclass(frozen=True)
class Decide:
    """The one decision on a request: black box, ``~/trigger_request``, diagnostics.

    Its record is synced as `SYNC_ASK` says: an fsync asked for, never waited on.
    """

    decision: str
    policy: str
    reason: str
    latency_ms: Optional[float]
    t_request: float


@dataclass(frozen=True)
class Pending:
    """Whether a request is held for an answer now (the snapshot's ``pending_request``)."""

    pending: bool


Action = Union[Write, PassGate, Decide, Answer, Record, Log, SetTimer, Pending]


# -- the core ----------------------------------------------------------------------------------

@dataclass
class _Request:
    t_rx: float
    defer_s: float
    deadline: float = float('inf')  # the defer deadline while held for an answer
    held: bool = False       # deferred: waits for an answer, a policy change or its deadline
    how: str = 'policy'      # what confirms it: 'policy' (confirm), 'answer', 'change'
    why: str = ''            # ... said in its decision
    answered: bool = False   # an answer call waits for its gate (answered at GateDone)
    gate: int = 0            # token of the PassGate out for it (0: none)
    decided: str = ''
    refusal: Optional[Result] = field(default=None, repr=False)  # for a call still at the gate


class TriggerCore:
    """The trigger-request policy; see the module docstring."""

    def __init__(self, policy: str = 'confirm', defer_timeout_s: float = 0.8) -> None:
        """Start with the policy in force and no request."""
        self.policy = policy
        self.defer_s = defer_timeout_s
        self.online = False
        self.offline_text = 'module offline (not connected yet)'
        self.triggered: Optional[bool] = None
        self.armed: Optional[bool] = None
        self.fresh = False
        self._now = 0.0
        self._open: Optional[_Request] = None      # the newest request not decided
        self._gates: Dict[int, _Request] = {}      # PassGate out, by token
        self._sending: Dict[int, _Request] = {}    # Write out, by token
        self._tokens = 0
        self._out: List[Action] = []

    def know(self, online: bool, offline_text: str = '', triggered: Optional[bool] = None,
             armed: Optional[bool] = None, fresh: bool = False) -> None:
        """Be told what is known of the module now (the session's snapshot)."""
        self.online, self.triggered, self.armed, self.fresh = online, triggered, armed, fresh
        if offline_text:
            self.offline_text = offline_text

    @property
    def pending(self) -> bool:
        """Whether a request is held for an answer."""
        return self._open is not None and self._open.held

    @property
    def deadline(self) -> Optional[float]:
        """When the open request is decided by the clock alone (None: no request open)."""
        req = self._open
        if req is None:
            return None
        return req.deadline if req.held else req.t_rx + MODULE_WINDOW_S

    def step(self, event: Event) -> List[Action]:
        """Take one event; return the actions to carry out, in order."""
        self._now = event.now
        held = self.pending
        if not isinstance(event, (Sent, NotSent)):
            self._expire()
        handler = getattr(self, '_on_' + type(event).__name__, None)
        if handler is None:
            raise TypeError(f'TriggerCore takes no {type(event).__name__}')
        handler(event)
        out, self._out = self._out, []
        if self.pending != held:
            out.insert(0, Pending(self.pending))  # the snapshot first, then the decision
        return out

    # -- events --------------------------------------------------------------------------------

    def _on_RequestReceived(self, event: RequestReceived) -> None:
        self.online = True  # (a frame of the module)
        old, self._open = self._open, None
        req = _Request(event.now, self.defer_s)
        if self.policy == 'confirm' and not event.gate:
            req.why = 'policy confirm: confirmed at once'
            self._send(req)  # first, before anything else
        if old is not None:
            self._decide(old, 'timed_out', 'superseded by a newer trigger request',
                         'superseded')
        if self.policy == 'deny':
            self._decide(req, 'denied', 'policy deny: no confirmation sent')
        elif self.policy == 'confirm' and event.gate:
            req.why = 'policy confirm: confirmed after the release gate'
            self._open = req
            self._pass_gate(req)
        elif self.policy == 'defer':
            self._hold(req)

    def _on_AnswerCall(self, event: AnswerCall) -> None:
        req = self._open
        if req is None or not req.held:
            self._out.append(Answer(Result.refused('not_pending', 'no trigger request is '
                                                   'pending')))
            return
        why = f'answered {str(event.confirm).lower()} via ~/answer_trigger_request'
        req.held, req.how, req.why, req.answered = False, 'answer', why, True
        if not event.confirm:
            self._decide(req, 'denied', f'{why}: no confirmation sent')
            self._out.append(Answer(Result.done('denied: nothing sent')))
            return
        self._confirm(req, event.gate)

    def _on_PolicyChanged(self, event: PolicyChanged) -> None:
        changed = event.policy != self.policy
        self.policy, self.defer_s = event.policy, event.defer_timeout_s
        if not changed:
            return
        policy = event.policy
        self._out.append(Record.of('decision', SYNC_ASK, what='policy', policy=policy))
        self._out.append(Log('info', f'trigger requests: {policy}'))
        req = self._open
        if req is None:
            return
        # A policy change settles an open request at once, under the new policy (D8).
        why = f'policy changed to {policy} while the request was pending'
        if policy == 'deny':
            self._decide(req, 'denied', why, 'policy')
        elif req.held and policy == 'confirm':
            req.held, req.how, req.why = False, 'change', why
            self._confirm(req, event.gate)
        elif not req.held and req.how != 'answer' and policy == 'defer':
            # It was to be confirmed by the policy, which no longer does: a caller decides.
            req.gate = 0  # (its gate, when passed, confirms nothing)
            self._hold(req)

    def _on_Rebooted(self, event: Rebooted) -> None:
        req = self._open
        if req is not None:
            # A rebooted module boots locked and has forgotten its question (D15): a confirm
            # now would answer nobody (or a newer request nobody decided on).
            self._decide(req, 'denied', 'the module rebooted while the request was pending: '
                         'its request is gone; no confirmation sent', 'rebooted')

    def _on_Tick(self, event: Tick) -> None:
        pass  # (`_expire` judged it)

    def _on_GateDone(self, event: GateDone) -> None:
        req = self._gates.pop(event.token, None)
        if req is None or req.gate != event.token:
            return  # held again meanwhile: its gate confirms nothing
        req.gate = 0
        if req.decided:
            # Decided while the gate was passed (a reboot, a policy change, the window).
            if req.answered and req.refusal is not None:
                self._out.append(Answer(req.refusal))
            return
        problem = self._problem(req)
        if problem:
            self._refuse(req, *problem)
        else:
            self._send(req)

    def _on_Sent(self, event: Sent) -> None:
        req = self._sending.pop(event.token)
        latency = (event.now - req.t_rx) * 1000.0
        if req.how == 'policy':
            self._decide(req, 'confirmed', req.why, latency=latency)
            return
        # Armed only as read since the module last could have changed unseen (D15).
        if self.armed and self.fresh:
            outcome = 'the module was armed: it deploys on it (~/trigger_event reports it)'
        else:
            outcome = ("the module's armed state is not known: ~/triggered shows whether it "
                       'deploys')
        self._decide(req, 'confirmed', f'{req.why}; {outcome}', latency=latency)
        if req.answered:
            # The module does not acknowledge a confirmation: ~/trigger_event tells what it did.
            self._out.append(Answer(Result.sent(f'confirmation sent {latency:.0f} ms after the '
                                                f'request; {outcome}')))

    def _on_NotSent(self, event: NotSent) -> None:
        req = self._sending.pop(event.token)
        if req.how == 'policy':
            self._decide(req, 'denied', f'could not send the confirmation: {event.reason}')
            return
        self._decide(req, 'denied', f'{req.why}, but the link is down: {event.reason}')
        if req.answered:
            self._out.append(Answer(Result.failed(f'confirmation not sent: {event.reason}',
                                                  cause='link_down')))

    def _on_LinkDown(self, event: LinkDown) -> None:
        self.online = False
        self.offline_text = f'module offline ({event.reason})'

    def _on_LinkUp(self, event: LinkUp) -> None:
        pass  # (online again at its first frame)

    def _on_Stopped(self, event: Stopped) -> None:
        req, self._open = self._open, None
        if req is not None:
            req.decided = 'not answered'
            req.refusal = Result.refused('stopping', 'not confirmed: the driver is stopping')
            self._out.append(Record('decision', (
                ('what', 'trigger request'), ('decision', 'not answered'),
                ('reason', 'driver stopped while the request was deferred'))))

    # -- the rules -----------------------------------------------------------------------------

    def _expire(self) -> None:
        """Decide a request whose time is over (the monitor's tick may come late)."""
        req = self._open
        if req is None:
            return
        age = self._now - req.t_rx
        if age >= MODULE_WINDOW_S:
            where = '' if req.held else ' the release gate was still being passed:'
            self._decide(req, 'timed_out', f'{age:.2f} s after the request{where} the '
                         "module's 1 s window has passed (P10); no confirmation sent",
                         'window_passed')
        elif req.held and self._now >= req.deadline:
            self._decide(req, 'timed_out', f'nobody answered within defer_timeout_s = '
                         f'{req.defer_s:.2f} s: denied', 'timed_out')

    def _problem(self, req: _Request) -> Optional[Tuple[str, str, str]]:
        """Why `req` may not be confirmed now: (decision, problem, cause), or None."""
        age = self._now - req.t_rx
        if self.policy == 'deny':
            return 'denied', 'the policy is deny: no confirmation sent', 'policy'
        if self.policy == 'defer' and req.how != 'answer':
            return 'denied', 'the policy is defer and nobody answered: no confirmation sent', \
                'policy'
        if age >= MODULE_WINDOW_S:
            return 'timed_out', (f"{age:.2f} s after the request: the module's 1 s window has "
                                 'passed (P10); no confirmation sent'), 'window_passed'
        if req.how == 'policy':
            return None  # (the module asked: it was armed and online a moment ago)
        if not self.online:
            return 'denied', f'{self.offline_text}: no confirmation sent', 'offline'
        if self.triggered:
            return 'denied', 'the module has already deployed: no confirmation sent', 'triggered'
        if self.armed is False and self.fresh:
            return 'denied', ('the module is locked, and a locked module cannot deploy (P12, '
                              'P20): no confirmation sent'), 'locked'
        return None

    def _confirm(self, req: _Request, gate: bool) -> None:
        """Confirm `req` if the rules allow it now: through the release gate when there is one."""
        problem = self._problem(req)
        if problem:
            self._refuse(req, *problem)
        elif gate:
            self._open = req
            self._pass_gate(req)
        else:
            self._send(req)

    def _refuse(self, req: _Request, decision: str, problem: str, cause: str) -> None:
        why = req.why.split(':')[0] if req.how == 'policy' else req.why
        self._decide(req, decision, f'{why}, but {problem}', cause)
        if req.answered:
            self._out.append(Answer(Result.refused(cause, f'not confirmed: {problem}')))

    # -- actions -------------------------------------------------------------------------------

    def _hold(self, req: _Request) -> None:
        req.held, req.deadline = True, req.t_rx + req.defer_s
        self._open = req
        self._out.append(Record.of('decision', SYNC_ASK, what='trigger request deferred',
                                   deadline_s=req.defer_s))
        self._out.append(Log('warn', 'trigger request from the module: answer '
                                     f'~/answer_trigger_request within {req.defer_s:.2f} s '
                                     '(else denied)'))
        self._out.append(SetTimer(req.deadline))

    def _pass_gate(self, req: _Request) -> None:
        self._tokens += 1
        req.gate = self._tokens
        self._gates[req.gate] = req
        self._out.append(PassGate(ROUTE, req.gate, req.t_rx))

    def _send(self, req: _Request) -> None:
        if self._open is req:
            self._open = None
        self._tokens += 1
        self._sending[self._tokens] = req
        self._out.append(Write(CONFIRM_FRAME, self._tokens, req.t_rx))

    def _decide(self, req: _Request, decision: str, reason: str, cause: str = '',
                latency: Optional[float] = None) -> None:
        assert not req.decided, (req, decision)  # one decision per request
        req.decided = decision
        if self._open is req:
            self._open = None
        if req.gate and req.answered:
            # A call waits at the gate: it hears of this when the gate is passed.
            req.refusal = Result.refused(cause or decision, f'not confirmed: {reason}')
        self._out.append(Decide(decision, self.policy, reason, latency, req.t_rx))
        if decision == 'confirmed':
            self._out.append(Log('error', f'trigger request confirmed: {reason}'))
        else:
            self._out.append(Log('warn', f'trigger request {decision}: {reason}'))
