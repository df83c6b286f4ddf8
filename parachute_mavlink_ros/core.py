"""The autopilot link as a pure state machine: events with their time in, actions out. No I/O.

`LinkCore` is the whole behaviour of ``parachute_mavlink`` (ros-api.md, "The autopilot link"):
what goes out on MAVLink (heartbeat and its ``system_status``, COMMAND_ACKs, STATUSTEXT, the
motor stop, RETURN_TO_LAUNCH), what is asked of the parachute node (``~/deploy``, ``~/arm``,
``~/preflight_check``), and how the parachute node's release gate is answered. It has no thread,
no clock and no socket: the node feeds it `Event`s with the monotonic time and carries out the
`Action`s it returns (`Send`, `Call`, `AnswerGate`, `Log`); `next_deadline()` says when it
wants a `Tick`. Everything here is therefore testable in microseconds.

The design, from the MAVLink command protocol (devguide ``services/command.md``), PX4's
parachute check (present and healthy from the heartbeat) and ArduPilot's AP_Parachute (the
motors are disarmed before the release):

- A DO_PARACHUTE addressed to us (our system id or 0; component 161 or 0) starts an operation.
  One operation per kind runs at a time (a RELEASE, or an ENABLE/DISABLE); the same command
  arriving again while it runs (a retransmission, whatever its ``confirmation``, or the same
  command from another sender) joins it and is answered IN_PROGRESS: never a second deploy.
  Every sender gets IN_PROGRESS when the operation passes 100 ms, then one final ACK.
- The motor stop is not done here for a RELEASE: the parachute node asks its release gate
  (``~/release_gate``) just before the deploy frame or the trigger confirmation leaves, after
  every refusal was decided, so whatever the route of the release the motors are stopped only
  for a release that will be attempted. The gate is answered on the autopilot's ACCEPTED, on a
  refusal, or at ``motor_stop_wait_s``, whichever comes first; the answer never holds the
  release back (the parachute node releases either way).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Any, Dict, List, Optional, Tuple
from parachute_mavlink_ros.events import (classify, split_text, MAV_TYPE_GCS, MAV_TYPE_PARACHUTE,
                                          MAV_AUTOPILOT_INVALID, MAV_STATE_UNINIT,
                                          MAV_STATE_STANDBY, MAV_STATE_ACTIVE, MAV_STATE_CRITICAL,
                                          MAV_STATE_EMERGENCY, MAV_CMD_NAV_RETURN_TO_LAUNCH,
                                          MAV_CMD_DO_FLIGHTTERMINATION, MAV_CMD_DO_PARACHUTE,
                                          MAV_CMD_COMPONENT_ARM_DISARM, PARACHUTE_DISABLE,
                                          PARACHUTE_ENABLE, PARACHUTE_RELEASE, MAV_RESULT_ACCEPTED,
                                          MAV_RESULT_TEMPORARILY_REJECTED, MAV_RESULT_DENIED,
                                          MAV_RESULT_UNSUPPORTED, MAV_RESULT_FAILED,
                                          MAV_RESULT_IN_PROGRESS, RESULT_NAMES, SEVERITY,
                                          FORCE_DISARM, STATUSTEXT_LEN, STATUS_NAMES, STOP_MODES,
                                          REASON_NONE, REASON_OFFLINE, REASON_LOCKED,
                                          REASON_ALREADY_DEPLOYED, REASON_NOT_DONE,
                                          REASON_OUTCOME_UNKNOWN, REASON_NO_PARACHUTE_NODE,
                                          REASON_NO_ANSWER, REASON_BUSY, REASON_PROTECTION,
                                          REASON_REFUSED, REASON_UNSUPPORTED_ACTION,
                                          REASON_MOTOR_STOP_UNCONFIRMED, REASON_NAMES, CoreConfig,
                                          Heartbeat, Command, Ack, BadData, LinkState,
                                          ParachuteState, Answer, Deployed, RequestDecided,
                                          GateRequest, Failsafe, Tick, Event, Send, Call,
                                          AnswerGate, Log, Action)

# The vocabulary lives in events.py; it is re-exported so callers keep one import for the core.
__all__ = ['Ack', 'Action', 'Answer', 'AnswerGate', 'BadData', 'Call', 'Command', 'CoreConfig',
           'Deployed', 'Event', 'FORCE_DISARM', 'Failsafe', 'GateRequest', 'Heartbeat', 'LinkCore',
           'LinkState', 'Log', 'MAV_AUTOPILOT_INVALID', 'MAV_CMD_COMPONENT_ARM_DISARM',
           'MAV_CMD_DO_FLIGHTTERMINATION', 'MAV_CMD_DO_PARACHUTE', 'MAV_CMD_NAV_RETURN_TO_LAUNCH',
           'MAV_RESULT_ACCEPTED', 'MAV_RESULT_DENIED', 'MAV_RESULT_FAILED',
           'MAV_RESULT_IN_PROGRESS', 'MAV_RESULT_TEMPORARILY_REJECTED', 'MAV_RESULT_UNSUPPORTED',
           'MAV_STATE_ACTIVE', 'MAV_STATE_CRITICAL', 'MAV_STATE_EMERGENCY', 'MAV_STATE_STANDBY',
           'MAV_STATE_UNINIT', 'MAV_TYPE_GCS', 'MAV_TYPE_PARACHUTE', 'PARACHUTE_DISABLE',
           'PARACHUTE_ENABLE', 'PARACHUTE_RELEASE', 'ParachuteState', 'REASON_ALREADY_DEPLOYED',
           'REASON_BUSY', 'REASON_LOCKED', 'REASON_MOTOR_STOP_UNCONFIRMED', 'REASON_NAMES',
           'REASON_NONE', 'REASON_NOT_DONE', 'REASON_NO_ANSWER', 'REASON_NO_PARACHUTE_NODE',
           'REASON_OFFLINE', 'REASON_OUTCOME_UNKNOWN', 'REASON_PROTECTION', 'REASON_REFUSED',
           'REASON_UNSUPPORTED_ACTION', 'RESULT_NAMES', 'RequestDecided', 'SEVERITY',
           'STATUSTEXT_LEN', 'STATUS_NAMES', 'STOP_MODES', 'Send', 'Tick', 'classify']


@dataclass
class _Op:
    """A DO_PARACHUTE being carried out, with everyone who asked for it."""

    action: int
    call_id: int
    started: float
    waiters: List[Tuple[int, int, str]] = field(default_factory=list)
    progress_sent: bool = False


@dataclass
class _OutCommand:
    """A command we sent to the autopilot and resend until it is acknowledged."""

    command: int
    params: Tuple[float, ...]
    sent: float
    deadline: float
    next_resend: float
    confirmation: int = 0
    gates: List[int] = field(default_factory=list)
    what: str = ''


class LinkCore:
    """The behaviour of ``parachute_mavlink``; call `handle()` with every event."""

    def __init__(self, config: CoreConfig, now: float) -> None:
        self.config = config
        self.sysid: Optional[int] = config.system_id or None
        self.autopilot: Optional[Tuple[int, int]] = None
        self.autopilot_seen: Optional[float] = None
        self.autopilot_lost = True
        self.ignored_autopilots: Dict[int, int] = {}
        self.port_open = False
        self.port_error = ''
        # the parachute node, as last heard
        self.answered = False
        self.online = False
        self.armed = False
        self.triggered = False
        self.preflight_ok: Optional[bool] = None
        self.preflight_failures: List[str] = []
        self._announced: List[str] = []  # the failures the last "preflight FAIL" said
        self._preflight_call: Optional[int] = None
        self._next_preflight = now
        self._preflight_again = False
        # commands from the link
        self._release: Optional[_Op] = None
        self._arm: Optional[_Op] = None
        self._calls: Dict[int, _Op] = {}
        self._recent: Dict[Tuple[int, int, int, int], Tuple[float, int, int]] = {}
        self._next_id = 0
        # commands to the autopilot
        self._stop: Optional[_OutCommand] = None
        self._gates: Dict[int, float] = {}
        self._rtl: Optional[_OutCommand] = None
        self._failsafe_action = 'NONE'
        # what ~/link and /diagnostics show
        self.counts: Dict[str, int] = {'messages': 0, 'bad_data': 0, 'commands': 0,
                                       'ignored': 0, 'motor_stops': 0,
                                       'motor_stops_confirmed': 0, 'rtl_sent': 0}
        self.acks: Dict[str, int] = {name: 0 for name in RESULT_NAMES.values()}
        self.last_command = ''
        self.last_command_level = 0
        self.status_sent = MAV_STATE_UNINIT
        self._next_heartbeat = now
        self._actions: List[Action] = []

    # -- public ------------------------------------------------------------------------------

    def handle(self, event: Event, now: float) -> List[Action]:
        """Take one event at time `now` (monotonic seconds); return what to do."""
        self._actions = []
        handler = getattr(self, '_on_' + type(event).__name__.lower(), None)
        if handler is not None:
            handler(event, now)
        self._timers(now)
        return self._actions

    def next_deadline(self) -> float:
        """Return the monotonic time of the next `Tick` the core needs."""
        times = [self._next_heartbeat, self._next_preflight]
        for op in (self._release, self._arm):
            if op is not None:
                if not op.progress_sent:
                    times.append(op.started + self.config.progress_after_s)
                times.append(op.started + self._answer_s(op))
        for out in (self._stop, self._rtl):
            if out is not None:
                times += [out.next_resend, out.deadline]
        if self.autopilot_seen is not None and not self.autopilot_lost:
            times.append(self.autopilot_seen + self.config.autopilot_timeout_s)
        return min(times)

    def system_status(self) -> int:
        """Return the MAV_STATE of our heartbeat (ros-api.md's mapping)."""
        if not self.answered:
            return MAV_STATE_UNINIT
        if self.triggered:
            return MAV_STATE_EMERGENCY
        if not self.online or self.preflight_ok is False:
            return MAV_STATE_CRITICAL
        if self.armed and self.preflight_ok:
            return MAV_STATE_ACTIVE
        return MAV_STATE_STANDBY

    def autopilot_age(self, now: float) -> float:
        """Return the seconds since the autopilot's last heartbeat (NaN: never heard)."""
        return math.nan if self.autopilot_seen is None else now - self.autopilot_seen

    def new_id(self) -> int:
        """Return a fresh id for a call or a gate."""
        self._next_id += 1
        return self._next_id

    # -- helpers -----------------------------------------------------------------------------

    def _log(self, level: str, text: str) -> None:
        self._actions.append(Log(level, text))

    def _send(self, kind: str, **fields: Any) -> None:
        if self.sysid is None:
            return  # system_id 0: nothing goes out until the autopilot told us who we are
        self._actions.append(Send(kind, fields))

    def _text(self, severity: str, text: str, level: str = '') -> None:
        """STATUSTEXT to every ground station and autopilot, and the same line in the log."""
        self._log(level or ('error' if SEVERITY[severity] <= 3 else
                            'warn' if SEVERITY[severity] == 4 else 'info'), text)
        chunks = split_text('Parachute: ' + text)
        ident = self.new_id() % 65535 + 1 if len(chunks) > 1 else 0
        for seq, chunk in enumerate(chunks[:8]):
            self._send('statustext', severity=SEVERITY[severity], text=chunk, id=ident,
                       chunk_seq=seq)

    def _ack(self, to: Tuple[int, int, str], result: int, reason: int = 0,
             progress: int = 0, command: int = MAV_CMD_DO_PARACHUTE) -> None:
        self.acks[RESULT_NAMES.get(result, str(result))] = \
            self.acks.get(RESULT_NAMES.get(result, str(result)), 0) + 1
        self._send('command_ack', command=command, result=result,
                   progress=progress, result_param2=reason, target_system=to[0],
                   target_component=to[1])

    def _answer_s(self, op: _Op) -> float:
        if op.action == PARACHUTE_RELEASE:
            return self.config.deploy_answer_s
        return self.config.arm_answer_s

    # -- link --------------------------------------------------------------------------------

    def _on_linkstate(self, event: LinkState, now: float) -> None:
        if event.open and not self.port_open:
            self._log('info', 'MAVLink port open')
        elif not event.open and (self.port_open or event.error != self.port_error):
            self._log('error', f'MAVLink port not open: {event.error}')
        self.port_open, self.port_error = event.open, event.error

    def _on_baddata(self, event: BadData, now: float) -> None:
        self.counts['bad_data'] += 1

    def _on_heartbeat(self, event: Heartbeat, now: float) -> None:
        self.counts['messages'] += 1
        if event.autopilot == MAV_AUTOPILOT_INVALID or event.mav_type == MAV_TYPE_GCS:
            return  # a ground station, a camera, another parachute: not the flight controller
        if self.sysid is None:
            self.sysid = event.sysid
            self._log('info', f'system id {event.sysid} learned from the autopilot heartbeat '
                              f'(component {event.compid})')
            self._next_heartbeat = now
        if event.sysid != self.sysid:
            if event.sysid not in self.ignored_autopilots:
                self._log('warn', f'an autopilot with system id {event.sysid} is ignored: this '
                                  f'vehicle is system {self.sysid}')
            self.ignored_autopilots[event.sysid] = self.ignored_autopilots.get(event.sysid,
                                                                               0) + 1
            return
        if self.autopilot is not None and self.autopilot[1] != event.compid:
            return  # a second flight-controller component of our system: keep the first
        if self.autopilot is None or self.autopilot_lost:
            gap = '' if self.autopilot_seen is None else \
                f' again after {now - self.autopilot_seen:.1f} s of silence'
            self._log('info', f'autopilot {event.sysid}/{event.compid} heard{gap}')
        self.autopilot = (event.sysid, event.compid)
        self.autopilot_seen = now
        self.autopilot_lost = False

    def _on_command(self, event: Command, now: float) -> None:
        self.counts['messages'] += 1
        if event.command != MAV_CMD_DO_PARACHUTE:
            if self.sysid is not None and (event.target_system, event.target_component) == \
                    (self.sysid, self.config.component_id):
                # Addressed to us alone: the command protocol wants an answer, not silence.
                self._ack((event.sysid, event.compid, event.kind), MAV_RESULT_UNSUPPORTED,
                          command=event.command)
            return
        if self.sysid is None or event.target_system not in (0, self.sysid) or \
                event.target_component not in (0, self.config.component_id):
            self.counts['ignored'] += 1
            return
        self.counts['commands'] += 1
        action = int(round(event.params[0])) if event.params and \
            math.isfinite(event.params[0]) else -1
        who = (event.sysid, event.compid, event.kind)
        self.last_command = (f'{event.kind} DO_PARACHUTE {action} from '
                             f'{event.sysid}/{event.compid}')
        if action not in (PARACHUTE_DISABLE, PARACHUTE_ENABLE, PARACHUTE_RELEASE):
            self._finish_one(who, action, MAV_RESULT_UNSUPPORTED, REASON_UNSUPPORTED_ACTION,
                             now)
            return
        key = (event.sysid, event.compid, action, 0)
        recent = self._recent.get(key)
        op = self._release if action == PARACHUTE_RELEASE else self._arm
        if op is not None and op.action == action:
            # A retransmission (its ACK was lost or is late) or the same command from another
            # sender: it joins the one running; never a second deploy.
            if who not in op.waiters:
                op.waiters.append(who)
            self._ack(who, MAV_RESULT_IN_PROGRESS, progress=255)
            return
        if recent is not None and event.confirmation > 0 and now - recent[0] < \
                self.config.recent_s:
            # A retransmission of a command that just finished: its final ACK was lost.
            self._ack(who, recent[1], recent[2])
            return
        if action == PARACHUTE_RELEASE:
            self._start(action, who, now)
            return
        if self._release is not None or op is not None:
            what = 'a RELEASE' if self._release is not None else 'another ENABLE/DISABLE'
            self._finish_one(who, action, MAV_RESULT_DENIED, REASON_BUSY, now,
                             f'{what} is in progress')
            return
        self._start(action, who, now)

    def _start(self, action: int, who: Tuple[int, int, str], now: float) -> None:
        call_id = self.new_id()
        op = _Op(action, call_id, now, [who])
        self._calls[call_id] = op
        if action == PARACHUTE_RELEASE:
            self._release = op
            self._log('warn', f'DO_PARACHUTE RELEASE from {who[0]}/{who[1]}: deploying')
            self._actions.append(Call(call_id, 'deploy',
                                      {'arm_if_locked': self.config.release_arms_if_locked},
                                      self.config.deploy_answer_s))
        else:
            self._arm = op
            self._log('info', f'DO_PARACHUTE {"ENABLE" if action else "DISABLE"} from '
                              f'{who[0]}/{who[1]}')
            self._actions.append(Call(call_id, 'arm', {'data': action == PARACHUTE_ENABLE},
                                      self.config.arm_answer_s))

    def _finish_one(self, who: Tuple[int, int, str], action: int, result: int, reason: int,
                    now: float, why: str = '') -> None:
        self._ack(who, result, reason)
        self._recent[(who[0], who[1], action, 0)] = (now, result, reason)
        name = {0: 'DISABLE', 1: 'ENABLE', 2: 'RELEASE'}.get(action, str(action))
        self.last_command = (f'{who[2]} DO_PARACHUTE {name} from {who[0]}/{who[1]}: '
                             f'{RESULT_NAMES[result]} ({REASON_NAMES[reason]})'
                             + (f': {why}' if why else ''))
        self.last_command_level = 0 if result == MAV_RESULT_ACCEPTED else 1
        if result != MAV_RESULT_ACCEPTED:
            self._text('warning', f'{name} {RESULT_NAMES[result]}: {why or REASON_NAMES[reason]}')

    def _on_ack(self, event: Ack, now: float) -> None:
        self.counts['messages'] += 1
        if self.autopilot is None or (event.sysid, event.compid) != self.autopilot:
            return
        if self.sysid is not None and event.target_system not in (0, self.sysid):
            return
        name = RESULT_NAMES.get(event.result, str(event.result))
        stop = self._stop
        if stop is not None and event.command == stop.command:
            if event.result == MAV_RESULT_IN_PROGRESS:
                stop.next_resend = stop.deadline  # it heard us: no more resends
                return
            wait_ms = (now - stop.sent) * 1000.0
            self._stop = None
            if event.result == MAV_RESULT_ACCEPTED:
                self.counts['motor_stops_confirmed'] += 1
                self._answer_gates(stop, True, f'motors stopped: the autopilot accepted '
                                   f'{stop.what} in {wait_ms:.0f} ms')
            else:
                self._answer_gates(stop, False, f'the autopilot answered {name} to '
                                   f'{stop.what}: motors may still run')
            return
        rtl = self._rtl
        if rtl is not None and event.command == rtl.command:
            if event.result == MAV_RESULT_IN_PROGRESS:
                rtl.next_resend = rtl.deadline
                return
            self._rtl = None
            level = 'info' if event.result == MAV_RESULT_ACCEPTED else 'warn'
            self._log(level, f'RETURN_TO_LAUNCH (handset failsafe): the autopilot answered '
                             f'{name}')

    # -- the parachute node ------------------------------------------------------------------

    def _on_parachutestate(self, event: ParachuteState, now: float) -> None:
        first = not self.answered
        self.answered = True
        changed = (event.online, event.armed, event.triggered) != \
            (self.online, self.armed, self.triggered)
        if not first and event.online != self.online:
            if event.online:
                self._text('notice', 'module online')
            else:
                self._text('critical', 'module OFFLINE: it cannot deploy from the host')
        self.online, self.armed, self.triggered = event.online, event.armed, event.triggered
        if (first or changed) and event.online:
            self._preflight_again = True
            self._next_preflight = now

    def _on_answer(self, event: Answer, now: float) -> None:
        if event.call_id == self._preflight_call:
            self._preflight_call = None
            self._preflight_answer(event, now)
            return
        op = self._calls.pop(event.call_id, None)
        if op is None:
            return  # answered after we gave up on it (already FAILED, outcome unknown)
        self._op_done(op, event.success, event.message, now)

    def _op_done(self, op: _Op, success: Optional[bool], message: str, now: float) -> None:
        if op is self._release:
            self._release = None
        if op is self._arm:
            self._arm = None
        service = 'deploy' if op.action == PARACHUTE_RELEASE else 'arm'
        result, reason = classify(service, op.action, success, message)
        name = {0: 'DISABLE', 1: 'ENABLE', 2: 'RELEASE'}[op.action]
        for who in op.waiters:
            self._ack(who, result, reason)
            self._recent[(who[0], who[1], op.action, 0)] = (now, result, reason)
        self.last_command = (f'DO_PARACHUTE {name} from '
                             f'{", ".join(f"{w[0]}/{w[1]}" for w in op.waiters)}: '
                             f'{RESULT_NAMES[result]} ({REASON_NAMES[reason]}) in '
                             f'{(now - op.started) * 1000:.0f} ms: {message}')
        self.last_command_level = 0 if result == MAV_RESULT_ACCEPTED else (
            2 if result == MAV_RESULT_FAILED else 1)
        self._log('info' if result == MAV_RESULT_ACCEPTED else 'warn', self.last_command)
        if result == MAV_RESULT_FAILED:
            self._text('critical', f'{name} FAILED ({REASON_NAMES[reason]}): '
                                   f'{message[:120]}')
        elif result != MAV_RESULT_ACCEPTED:
            self._text('warning', f'{name} DENIED ({REASON_NAMES[reason]})')
        elif op.action != PARACHUTE_RELEASE:
            self._text('info', 'armed' if op.action == PARACHUTE_ENABLE else 'locked')
        if op.action != PARACHUTE_RELEASE and success is not None:
            self._preflight_again = True
            self._next_preflight = now

    def _preflight_answer(self, event: Answer, now: float) -> None:
        if event.success is None:
            return  # no answer: judge again at the next period
        self.answered = True
        # The "armed" check is what STANDBY and ACTIVE differ by, not a failure.
        failures = [line[5:] for line in event.message.splitlines()
                    if line.startswith('FAIL') and not line[5:].startswith('armed:')]
        was_ok = self.preflight_ok
        self.preflight_ok = not failures
        self.preflight_failures = failures
        # Said once armed, even when first seen while locked (the check after the arm finds
        # the same failures: a host where the periodic check ran in between never said them).
        if failures and self.armed and failures != self._announced:
            self._text('critical', 'preflight FAIL: ' + '; '.join(failures)[:150])
            self._announced = failures
        elif was_ok is False and not failures:
            self._text('notice', 'preflight checks pass')
            self._announced = []

    def _on_deployed(self, event: Deployed, now: float) -> None:
        self.triggered = True
        self._text('emergency', f'DEPLOYED (source: {event.source})')

    def _on_requestdecided(self, event: RequestDecided, now: float) -> None:
        if event.decision == 'confirmed':
            self._text('alert', "module's own trigger request confirmed: deploying")
        else:
            self._text('warning', f'module trigger request {event.decision}: '
                                  f'{event.reason[:100]}')

    # -- the release gate: the motor stop ----------------------------------------------------

    def _on_gaterequest(self, event: GateRequest, now: float) -> None:
        mode = self.config.stop_motors_before_release
        if mode == 'off':
            self._actions.append(AnswerGate(event.gate_id, True,
                                            'stop_motors_before_release is off'))
            return
        if self.sysid is None or self.autopilot is None:
            self._actions.append(AnswerGate(event.gate_id, False, 'no autopilot heard: motor '
                                            'stop not sent'))
            self._text('critical', 'releasing WITHOUT motor stop: no autopilot heard')
            return
        if self._stop is not None:
            self._stop.gates.append(event.gate_id)  # one motor stop serves every release
            return
        if mode == 'disarm':
            command, params = MAV_CMD_COMPONENT_ARM_DISARM, (0.0, FORCE_DISARM)
            what = 'the forced disarm'
        else:
            command, params = MAV_CMD_DO_FLIGHTTERMINATION, (1.0,)
            what = 'the flight termination'
        wait = self.config.motor_stop_wait_s
        if self.autopilot_lost:
            wait = 0.0  # silent for 3 s: send it, but do not hold the release for an answer
        self._stop = _OutCommand(command, params, now, now + wait,
                                 now + self.config.resend_period_s, gates=[event.gate_id],
                                 what=what)
        self.counts['motor_stops'] += 1
        self._send_command(self._stop)
        self._log('warn', f'release coming: motor stop ({what}) sent to the autopilot '
                          f'{self.autopilot[0]}/{self.autopilot[1]}')
        if wait == 0.0:
            self._stop = None
            self._answer_gates(_OutCommand(command, params, now, now, now, gates=[event.gate_id],
                                           what=what), False,
                               f'{what} sent, but the autopilot has been silent for '
                               f'{self.config.autopilot_timeout_s:.0f} s: not waiting')

    def _send_command(self, out: _OutCommand) -> None:
        params = (list(out.params) + [0.0] * 7)[:7]
        self._send('command_long', target_system=self.autopilot[0],
                   target_component=self.autopilot[1], command=out.command,
                   confirmation=out.confirmation, param1=params[0], param2=params[1],
                   param3=params[2], param4=params[3], param5=params[4], param6=params[5],
                   param7=params[6])

    def _answer_gates(self, stop: _OutCommand, stopped: bool, message: str) -> None:
        for gate in stop.gates:
            self._actions.append(AnswerGate(gate, stopped, message))
        if not stopped:
            self._text('critical', f'motor stop NOT confirmed ({message}); releasing anyway')
        else:
            self._text('alert', message)

    # -- handset ---------------------------------------------------------------------------

    def _on_failsafe(self, event: Failsafe, now: float) -> None:
        previous, self._failsafe_action = self._failsafe_action, event.action
        if event.action != 'RETURN_TO_HOME' or previous == 'RETURN_TO_HOME':
            return
        if not self.config.handset_failsafe_to_autopilot:
            return
        if self.autopilot is None:
            self._text('critical', 'handset failsafe RETURN_TO_HOME: no autopilot heard to '
                                   'send it to')
            return
        self._rtl = _OutCommand(MAV_CMD_NAV_RETURN_TO_LAUNCH, (), now, now + 3.0,
                                now + 1.0, what='RETURN_TO_LAUNCH')
        self.counts['rtl_sent'] += 1
        self._send_command(self._rtl)
        self._text('warning', f'handset failsafe: RETURN_TO_LAUNCH sent ({event.reason[:80]})')

    # -- time ------------------------------------------------------------------------------

    def _on_tick(self, event: Tick, now: float) -> None:
        pass

    def _timers(self, now: float) -> None:
        config = self.config
        if now >= self._next_heartbeat:
            self._next_heartbeat = max(self._next_heartbeat + config.heartbeat_period_s, now)
            status = self.system_status()
            if status != self.status_sent:
                self._log('info', f'heartbeat system_status {STATUS_NAMES[self.status_sent]} '
                                  f'-> {STATUS_NAMES[status]}')
            self.status_sent = status
            self._send('heartbeat', type=MAV_TYPE_PARACHUTE, autopilot=MAV_AUTOPILOT_INVALID,
                       base_mode=0, custom_mode=0, system_status=status)
        if self.autopilot_seen is not None and not self.autopilot_lost and \
                now - self.autopilot_seen >= config.autopilot_timeout_s:
            self.autopilot_lost = True
            self._log('error', f'no autopilot heartbeat for {config.autopilot_timeout_s:.0f} s')
        for op in (self._release, self._arm):
            if op is None:
                continue
            if not op.progress_sent and now >= op.started + config.progress_after_s:
                op.progress_sent = True
                for who in op.waiters:
                    self._ack(who, MAV_RESULT_IN_PROGRESS, progress=255)
            if now >= op.started + self._answer_s(op):
                self._calls.pop(op.call_id, None)
                self._op_done(op, None, f'the parachute node did not answer within '
                                        f'{self._answer_s(op):.0f} s', now)
        stop = self._stop
        if stop is not None:
            if now >= stop.deadline:
                self._stop = None
                self._answer_gates(stop, False, f'no answer to {stop.what} within '
                                   f'{config.motor_stop_wait_s * 1000:.0f} ms')
            elif now >= stop.next_resend:
                stop.confirmation = min(stop.confirmation + 1, 255)
                stop.next_resend = now + config.resend_period_s
                self._send_command(stop)
        rtl = self._rtl
        if rtl is not None:
            if now >= rtl.deadline:
                self._rtl = None
                self._log('warn', 'RETURN_TO_LAUNCH (handset failsafe): no answer from the '
                                  'autopilot')
            elif now >= rtl.next_resend:
                rtl.confirmation = min(rtl.confirmation + 1, 255)
                rtl.next_resend = now + 1.0
                self._send_command(rtl)
        if now >= self._next_preflight:
            self._next_preflight = now + config.preflight_period_s
            if self._preflight_call is None and (self.answered or self._preflight_again):
                self._preflight_again = False
                self._preflight_call = self.new_id()
                self._actions.append(Call(self._preflight_call, 'preflight_check', {}, 8.0))
        for key in [k for k, v in self._recent.items() if now - v[0] > config.recent_s]:
            del self._recent[key]
