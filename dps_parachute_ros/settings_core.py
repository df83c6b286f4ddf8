"""The settings transaction (D4, D5, D16) as a state machine without I/O (issue 22).

Every write of the module's settings is one `WriteCall`, whoever asks: a runtime parameter set
(all or nothing within 1.8 s, D4), ``~/set_thresholds`` and ``~/set_auto_triggers``, the desired
settings at connect and after a reboot, and those held back because they would deploy the armed
module at once. `SettingsCore` owns no thread, lock, clock, port or file: every event carries its
time (``now``), and `SettingsCore.step` returns the actions to carry out in order
(``session_settings`` carries them out over the link; test/test_settings_model.py over the device
model, in virtual time). What it must know of the module (online, the settings as read) it is
told with `know`; what it learns from the module it says with `Learned`.

The rules, each in one place:

- the rule (D16, `settings_rule.would_deploy`) judges every write that touches a trigger, on the
  status read afresh just before it (`_judge`): a write whose judgement could not be made is not
  sent; a threshold the rule needs and the core does not know is read first (the rule cannot
  judge an unknown threshold);
- a reply is never taken for a fresher one: after a request timed out, the next reply of its kind
  may be its late one, and is not taken (`_request`);
- every write is verified: a numeric setting by a read-back, a trigger flag by the reply that
  reports both flags (P8); a write whose reply did not come is not known to have taken or not:
  the setting is not known any more (``Learned(name, None)``) and the answer says UNKNOWN, never
  "not written";
- a parameter set counts a write as written before its frame leaves; when one fails, those are
  put back (newest first, each through the rule again), unless the module reads back the old
  value; a put-back that does not go through is named ("could NOT put back");
- an arm and the auto-trigger flag query (P14) are judged by the same `_judge` (`JudgeCall`);
- every call gets exactly one `Answer`: DONE (all verified), REFUSED (nothing was sent: offline,
  or the rule refused the set before its first write), FAILED (the module did not take it, or
  nothing was written after all), UNKNOWN (a write's outcome was not seen, or a put-back failed).
"""

from __future__ import annotations

from typing import Any, Dict, Generator, List, Optional, Sequence, Tuple, Type

from dps_parachute_ros import protocol as p
from dps_parachute_ros.settings_events import (  # noqa: F401 (the core's vocabulary)
    Action, Answer, Busy, Drained, Event, FLAGS, JudgeCall, Learned, LinkDown, Log, Record, Reply,
    REPLIES, Request, REQUEST_TIMEOUT_S, Timeout, WriteCall, Written)
from dps_parachute_ros.settings_rule import (ATTITUDE_STEPS, FREEFALL_STEPS, JUDGED_STEPS, order,
                                             Step, Trigger, would_deploy)
from dps_parachute_ros.state import SETTINGS
from uav_serial_common.result import Result

_Wait = Generator[Any, Event, Any]
_KEEP = object()
"""Yielded by a call to wait on for the reply to the Request before, sending nothing."""
PUT_BACK = 'putting back a refused parameter set'


class Stop(Exception):
    """A write of the set failed: ``reason`` says why.

    ``unseen``: a write left and its outcome is not known; ``silent``: the module did not
    answer (a write, or a query before one).
    """

    def __init__(self, reason: str, unseen: bool = False, silent: bool = False) -> None:
        super().__init__(reason)
        self.reason = reason
        self.unseen = unseen
        self.silent = silent or unseen


def rule_step(name: str, value: Any) -> Step:
    """Return the rule's step for a setting by parameter name (a flag: its bool)."""
    return (FLAGS[name], bool(value)) if name in FLAGS else (name, value)


def show(name: str, value: Any) -> str:
    """Say a setting write for people."""
    if name in FLAGS:
        return f'{FLAGS[name]} trigger {"enable" if value else "disable"}'
    return f'{name} = {value:g}'


class SettingsCore:
    """The settings transaction; see the module docstring."""

    def __init__(self, request_timeout_s: float = REQUEST_TIMEOUT_S) -> None:
        """Start knowing nothing of the module."""
        self.timeout_s = request_timeout_s
        self.online = False
        self.offline_text = 'module offline'
        self.values: Dict[str, Optional[int]] = {name: None for name in SETTINGS}
        self.flags: Dict[str, Optional[bool]] = {name: None for name in FLAGS}
        self._now = 0.0
        self._out: List[Action] = []
        self._call: Optional[_Wait] = None
        self._waiting: Optional[Request] = None
        self._late: Dict[Type, int] = {}  # reply type -> replies that may still come late

    def know(self, online: bool, offline_text: str = '',
             values: Optional[Dict[str, Optional[int]]] = None,
             flags: Optional[Dict[str, Optional[bool]]] = None) -> None:
        """Be told what is known of the module: raw settings and flags by parameter name."""
        self.online = online
        self.offline_text = offline_text or 'module offline'
        self.values.update(values or {})
        self.flags.update(flags or {})

    @property
    def busy(self) -> bool:
        """Whether a call is running (waiting for a reply)."""
        return self._call is not None

    # -- the one entry point -------------------------------------------------------------------

    def step(self, event: Event) -> List[Action]:
        """Take one event; return the actions to carry out, in order."""
        self._now = event.now
        if isinstance(event, (WriteCall, JudgeCall)):
            if self._call is not None:
                self._answer(Result.refused('busy', 'another settings write is still running; '
                                            'nothing sent'))
            else:
                self._call = self._write(event) if isinstance(event, WriteCall) \
                    else self._judge_call(event)
                self._advance(None)
        elif self._call is not None and self._answers_wait(event):
            self._advance(event)
        out, self._out = self._out, []
        return out

    def _answers_wait(self, event: Event) -> bool:
        wait = self._waiting
        if wait is None:
            return False
        if isinstance(event, Reply):
            return isinstance(event.message, wait.expect)
        return isinstance(event, (Timeout, LinkDown, Busy, Drained))

    def _advance(self, event: Optional[Event]) -> None:
        assert self._call is not None
        try:
            waiting = self._call.send(event)  # type: ignore[arg-type]
        except StopIteration:
            self._call = None
            self._waiting = None
            return
        if waiting is _KEEP:
            return  # (still waiting for the reply to the Request before)
        self._waiting = waiting
        self._out.append(waiting)

    def _answer(self, result: Result) -> None:
        self._out.append(Answer(result))

    def _record(self, kind: str, **fields: Any) -> None:
        self._out.append(Record.of(kind, **fields))

    def _learn(self, name: str, value: Any) -> None:
        if name in FLAGS:
            self.flags[name] = value
        else:
            self.values[name] = value
        self._out.append(Learned(name, value))

    def _request(self, frame: bytes, expect: Type, retries: int = 0) -> _Wait:
        """Request `frame`; return its reply, or raise Stop(silent) with why it did not come.

        A reply of a kind whose earlier request timed out may be that one, late (a status from
        before the module was armed, a value from before a write): it is not taken, and the
        core waits for the next; when none is coming (`Drained`) the frame (a query, or a write
        of the same value: either changes nothing sent again) goes again. Each request that
        timed out counts its tries.
        """
        event = yield self._frame(frame, expect, retries)
        while True:
            if isinstance(event, Reply) and self._late.get(expect):
                self._late[expect] -= 1
                event = yield _KEEP
            elif isinstance(event, Drained):
                event = yield self._frame(frame, expect, retries)
            else:
                break
        if isinstance(event, Reply):
            return event.message
        if isinstance(event, Timeout):
            self._late[expect] = self._late.get(expect, 0) + retries + 1
        reason = getattr(event, 'reason', '') or \
            f'no reply within {self.timeout_s * 1000:.0f} ms'
        raise Stop(f'no reply: {reason}', silent=True)

    def _frame(self, frame: bytes, expect: Type, retries: int) -> Request:
        return Request(frame, (expect,), self._now + self.timeout_s * (retries + 1), retries)

    # -- the rule ------------------------------------------------------------------------------

    def trigger(self) -> Trigger:
        """Return the trigger settings as known, for the rule."""
        return Trigger(self.values['attitude_threshold_deg'],
                       self.values['freefall_threshold_g'],
                       self.flags['attitude_trigger'], self.flags['freefall_trigger'])

    def _judge(self, steps: Sequence[Tuple[str, Any]], origin: str) -> _Wait:
        """Why writing `steps` (in order) would deploy the module at once, or '' to write.

        The one check of every settings write (D16): the thresholds the rule needs are read if
        not known (`_needed`), the status is read afresh and judged by
        `settings_rule.would_deploy`. A refusal is recorded. Raises Stop when the module does not
        answer (nothing written).
        """
        rule = [rule_step(name, value) for name, value in steps]
        if not any(name in JUDGED_STEPS for name, _ in rule):
            return ''
        for name in self._needed(rule):
            if self.values[name] is None:
                try:
                    reply = yield from self._request(SETTINGS[name].encode_query(),
                                                     REPLIES[name], retries=1)
                except Stop as exc:
                    raise Stop(f'{name} not known and not read ({exc.reason}); the rule cannot '
                               'judge the write, so it was not sent', silent=True) from None
                self._learn(name, reply.value)
        try:
            status = yield from self._request(p.encode_status_query(), p.Status, retries=1)
        except Stop as exc:
            raise Stop(f'status not read ({exc.reason}); the rule cannot judge the write, so '
                       'it was not sent', silent=True) from None
        danger = would_deploy(self.trigger(), status.armed, status.triggered,
                              float(status.tilt_deg), float(status.accel_g), rule)
        if danger:
            self._record('decision', what='settings write withheld', origin=origin,
                         steps=[list(step) for step in rule], reason=danger)
        return danger

    @staticmethod
    def _needed(rule: Sequence[Step]) -> List[str]:
        """Return the thresholds `rule` is judged on (a step that sets one brings its own)."""
        needed: List[str] = []
        written = set()
        for name, _ in rule:
            for threshold, steps in (('attitude_threshold_deg', ATTITUDE_STEPS),
                                     ('freefall_threshold_g', FREEFALL_STEPS)):
                if name == threshold:
                    written.add(threshold)
                elif (name in steps or name == 'armed') and threshold not in written and \
                        threshold not in needed:
                    needed.append(threshold)
        return needed

    def _judge_call(self, call: JudgeCall) -> _Wait:
        try:
            danger = yield from self._judge(call.steps, call.origin)
        except Stop as exc:
            self._answer(Result.failed(exc.reason, 'no_reply'))
            return
        self._answer(Result.refused('would_deploy', danger) if danger else Result.done(''))

    # -- one write, verified -------------------------------------------------------------------

    def _write_one(self, name: str, value: Any, written: Written) -> _Wait:
        """Write one setting and verify it; return the message, or raise Stop."""
        written.sent += (name,)
        if name in FLAGS:
            which = FLAGS[name]
            encode = p.encode_attitude_trigger if which == 'attitude' \
                else p.encode_freefall_trigger
            try:
                reply = yield from self._request(encode(bool(value)), p.AutoTriggerFlags)
            except Stop as exc:
                self._learn(name, None)  # it may have taken
                raise Stop(exc.reason, unseen=True) from None
            self._learn('attitude_trigger', reply.attitude_enabled)
            self._learn('freefall_trigger', reply.freefall_enabled)
            if self.flags[name] != bool(value):
                raise Stop(f'module did not confirm: {which} trigger reads '
                           f'{"enabled" if self.flags[name] else "disabled"} '
                           f'(flag layout {reply.layout})')
            return f'{which} trigger {"enabled" if value else "disabled"}, verified'
        setting = SETTINGS[name]
        raw = setting.to_raw(value)
        try:
            reply = yield from self._request(setting.encode_set(value), REPLIES[name])
        except Stop as exc:
            self._learn(name, None)  # it may have taken
            raise Stop(exc.reason, unseen=True) from None
        if not p.is_set_ack(reply, raw):
            self._learn(name, None)
            raise Stop(f'module answered {reply.raw.hex(" ")} to setting {name} = {value}: '
                       'not an acknowledgement', unseen=True)
        try:
            back = (yield from self._request(setting.encode_query(), REPLIES[name])).value
        except Stop as exc:
            self._learn(name, None)
            raise Stop(f'{name} acknowledged, not read back ({exc.reason})', unseen=True) \
                from None
        self._learn(name, back)
        if back != raw:
            raise Stop(f'{name}: wrote {setting.to_si(raw)}, module reads back '
                       f'{setting.to_si(back)}')
        return f'{name} = {setting.to_si(raw)} verified'

    # -- the procedure -------------------------------------------------------------------------

    def _write(self, call: WriteCall) -> _Wait:
        steps = [(name, value) for name, value in call.steps]
        plan = self._ordered(steps)
        names = ', '.join(name for name, _ in plan)
        written = Written()
        if not plan:
            return self._finish(call, Result.done('nothing to change', written))
        if not self.online:
            what = f'{names} not written' if call.all_or_nothing else 'nothing sent'
            return self._finish(call, Result.refused('offline', f'{self.offline_text}; {what}'),
                                written)
        deadline = None if call.budget_s is None else call.now + call.budget_s
        done: List[Tuple[str, Any]] = []  # (name, value before), counted before the frame
        notes: List[str] = []
        failure: Optional[Stop] = None
        for index, (name, value) in enumerate(plan):
            try:
                if deadline is not None and self._now > deadline:
                    raise Stop(f'no time left for {name} within {call.budget_s} s')
                # A set is judged whole before its first write (it is refused, nothing sent,
                # rather than left half written), then each write on its own; a parameter set
                # stays judged whole (all or nothing).
                whole = index == 0 and not call.hold or call.all_or_nothing
                # What it had is read first: the status that judges a write is the last frame
                # before it (a module armed in between would be judged on an old status).
                before = (yield from self._before(name)) if call.all_or_nothing else None
                danger = yield from self._judge(plan[index:] if whole else [(name, value)],
                                                call.origin)
                if danger and call.hold:
                    written.held[name] = (value, danger)
                    continue
                if danger and not written.sent:
                    self._record('decision', what='settings refused', reason=danger)
                    self._out.append(Log('warn', f'settings change refused: {danger}'))
                    message = f'refused, nothing written: {danger}'
                    return self._finish(call, Result.refused('would_deploy', message), written)
                if danger:
                    raise Stop(f'{show(name, value)} not written: {danger}')
                if call.all_or_nothing:
                    done.append((name, before))
                written.verified[name] = yield from self._write_one(name, value, written)
                notes.append(written.verified[name])
            except Stop as exc:
                written.failed.setdefault(name, exc.reason)
                if not call.all_or_nothing and not exc.silent:  # the others are still written
                    notes.append(exc.reason)
                    continue
                failure = exc
                break
        if failure is None:
            if written.held:
                notes += [f'{show(n, v)} not written: {why}' for n, (v, why) in
                          written.held.items()]
            message = '; '.join(notes)
            if written.held and not written.sent and not written.failed:
                return self._finish(call, Result.refused('would_deploy', message), written)
            ok = not written.failed and not written.held
            return self._finish(call, Result.checked(ok, message, written))
        if call.all_or_nothing:
            undone, clean = yield from self._undo(done)
            reason = f'module did not confirm {names}: {failure.reason}{undone}'
            kind = Result.failed if clean else Result.unknown
            return self._finish(call, kind(reason, 'not_confirmed'), written)
        notes.append(failure.reason)
        message = '; '.join(notes)
        if failure.unseen:
            return self._finish(call, Result.unknown(message, 'no_reply'), written)
        return self._finish(call, Result.failed(message, 'no_reply' if failure.silent else '',
                                                written))

    def _finish(self, call: WriteCall, result: Result, written: Optional[Written] = None) -> None:
        if written is not None and result.value is None:
            result = Result(result.outcome, result.message, result.cause, written)
        if call.all_or_nothing:
            self._record('parameter', changes=dict(call.changes or call.steps),
                         accepted=result.ok, **({} if result.ok else {'reason': result.message}))
            if not result.ok:
                self._out.append(Log('warn', f'parameter set refused: {result.message}'))
        self._answer(result)

    @staticmethod
    def _ordered(steps: List[Tuple[str, Any]]) -> List[Tuple[str, Any]]:
        """Return the steps in the rule's safest order (a disable first, an enable last)."""
        by_step = {rule_step(name, value): (name, value) for name, value in steps}
        return [by_step[step] for step in order(by_step)]

    def _before(self, name: str) -> _Wait:
        """Return the value of `name` before its write (read when not known; None: not known)."""
        if name in FLAGS:
            return self.flags[name]
        if self.values[name] is None:
            try:
                reply = yield from self._request(SETTINGS[name].encode_query(), REPLIES[name],
                                                 retries=1)
            except Stop as exc:
                raise Stop(f'{name} not read before its write ({exc.reason})') from None
            self._learn(name, reply.value)
        return self.values[name]

    def _undo(self, done: List[Tuple[str, Any]]) -> _Wait:
        """Put back what a refused parameter set wrote; say how that went, and if it all did."""
        back, failed = [], []
        for name, before in reversed(done):
            try:
                if before is None:
                    raise Stop('its previous value is not known')
                if name not in FLAGS:
                    still = yield from self._still(name, before)
                    if still:
                        continue  # its write did not take: nothing to put back
                value = before if name in FLAGS else SETTINGS[name].to_si(before)
                danger = yield from self._judge([(name, value)], PUT_BACK)
                if danger:
                    raise Stop(f'not written: {danger}')
                yield from self._write_one(name, value, Written())
                back.append(name)
            except Stop as exc:
                failed.append(f'{name} ({exc.reason})')
        text = f'; put back {", ".join(back)}' if back else ''
        if failed:
            text += f'; could NOT put back {"; ".join(failed)}'
            self._out.append(Log('error', 'a refused parameter set may have left the module '
                                          f'changed: {text}'))
        return text, not failed

    def _still(self, name: str, before: int) -> _Wait:
        """Whether the module answers that `name` still has its raw value `before`."""
        try:
            reply = yield from self._request(SETTINGS[name].encode_query(), REPLIES[name],
                                             retries=1)
        except Stop:
            return False  # not known: put it back
        self._learn(name, reply.value)
        return reply.value == before
