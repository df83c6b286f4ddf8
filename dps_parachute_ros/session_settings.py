"""The module's settings: reads, the one settings rule (D16), desired settings, writes (D4, D5).

Every write to the module passes the rule (``_gate``); a desired setting that would deploy the
armed module at once is held back until it no longer would; a parameter set is written all or
nothing.

Part of `ParachuteSession` (``dps_parachute_ros.session`` assembles it; the shared state and the
lock are described there). Threads:

- worker: ``_apply_desired`` at each initialization and for held settings (``settings`` job).
- serial reader: ``_recheck_held`` on each status (no I/O: it queues the ``settings`` job).
- callers: ``set_thresholds``, ``set_auto_triggers``, ``commit_desired`` (parameters), and
  ``_gate`` from an arm.

Owns, guarded by ``_lock``: ``_held``, ``_held_retry_at``, ``_flags_query_sent``,
``_flags_query_answered``, ``_silent_flag_queries``; the settings, ``mismatch``, ``held`` and
``config_reads`` fields of the snapshot.
"""

from __future__ import annotations

from dataclasses import replace
import time
from typing import Any, Dict, List, Optional, Set, Tuple

from dps_parachute_ros import protocol as p
from dps_parachute_ros.link import LinkError, LinkTimeout
from dps_parachute_ros.settings_rule import JUDGED_STEPS, order, Step, Trigger, would_deploy
from dps_parachute_ros.state import FLAG_SETTINGS, Result, SessionConfig, SETTINGS, Snapshot

FLAGS_QUERY_TIMEOUT_S = 0.3
"""The auto-trigger flag query is our extension (P14): a real module may stay silent."""
PARAM_WRITE_BUDGET_S = 1.8
"""A runtime parameter change that writes to the module answers within this time (D4)."""
HELD_RETRY_S = 1.0
"""A desired setting held back (it would deploy at once) is tried again at most this often."""


class Withheld(Exception):
    """A settings write the rule refused (D16): it would deploy the armed module at once."""

    def __init__(self, what: str, reason: str) -> None:
        super().__init__(f'{what} not written: {reason}')
        self.reason = reason


def _written(ok: bool, unseen: bool, message: str) -> Result:
    """Answer a settings write: verified, not taken, or a reply that did not come."""
    if ok:
        return Result.done(message)
    return Result.unknown(message, 'no_reply') if unseen else Result.failed(message)


class SettingsTransaction:
    """The settings of `ParachuteSession` (a mixin: it uses the session's state)."""

    def _read_config(self, reinit: bool = True) -> None:
        """Read every setting afresh (raises LinkError)."""
        for setting in SETTINGS.values():
            reply = self._req(setting.encode_query(), retries=1)
            self._update(**{setting.field: reply.value})
        self._note_boot_count(self._req(p.encode_boot_count_query(), retries=1).count, reinit)
        snap = self.snapshot
        if snap.attitude_trigger_enabled is None or snap.freefall_trigger_enabled is None:
            self._query_flags()
        with self._lock:
            self._snap = replace(self._snap, config_reads=self._snap.config_reads + 1)
        self._update_mismatch(log=False)

    def _query_flags(self) -> bool:
        # P14: a firmware ignoring D3 would take the query as "enable the attitude trigger", so
        # it is a possible settings write: sent at most once per run while unanswered (D5), and
        # only when enabling the attitude trigger would not deploy the module at once (D16).
        with self._lock:
            if self._flags_query_sent and not self._flags_query_answered:
                return False
        danger = self._gate([('attitude', True)], 'auto-trigger flag query (P14)')
        if danger:
            self._log('warn', 'auto-trigger flag query not sent (a firmware may take it as '
                              f'"enable the attitude trigger", P14): {danger}', key='flag-query')
            return False
        with self._lock:
            self._flags_query_sent = True
        try:
            reply = self._req(p.encode_auto_trigger_query(), timeout=FLAGS_QUERY_TIMEOUT_S,
                              silence_ok=True)
        except LinkTimeout:
            with self._lock:
                self._silent_flag_queries += 1
            return False
        self._set_flags(reply)
        with self._lock:
            self._flags_query_answered = True
        return True

    @staticmethod
    def _trigger_settings(snap: Snapshot) -> Trigger:
        return Trigger(snap.attitude_threshold_raw, snap.freefall_threshold_raw,
                       snap.attitude_trigger_enabled, snap.freefall_trigger_enabled)

    def _gate(self, steps: List[Step], origin: str) -> str:
        """Why writing `steps` (in order) would deploy the module at once, or '' to write.

        The one check of every settings write, whoever asks (D16): the status is read afresh
        (raises LinkError when it is not answered: nothing is written then) and judged by
        `settings_rule.would_deploy`. A refusal is recorded in the black box.
        """
        if not any(name in JUDGED_STEPS for name, _ in steps):
            return ''
        epoch = self._current_epoch()
        status = self._req(p.encode_status_query(), retries=1)
        self._on_status(status, via='query', epoch=epoch)
        danger = would_deploy(self._trigger_settings(self.snapshot), status.armed,
                              status.triggered, float(status.tilt_deg), float(status.accel_g),
                              steps)
        if danger:
            self.blackbox.record('decision', what='settings write withheld', origin=origin,
                                 steps=[list(step) for step in steps], reason=danger)
        return danger

    def _write_setting(self, name: str, value: float, origin: str) -> Tuple[bool, str]:
        """Write one numeric setting, verified; raises Withheld when the rule forbids it."""
        setting = SETTINGS[name]
        raw = setting.to_raw(value)
        danger = self._gate([(name, value)], origin)
        if danger:
            raise Withheld(f'{name} = {value:g}', danger)
        reply = self._req(setting.encode_set(value))
        if not p.is_set_ack(reply, raw):
            return False, (f'module answered {reply.raw.hex(" ")} to setting {name} = {value}: '
                           'not an acknowledgement')
        back = self._req(setting.encode_query()).value
        with self._lock:
            self._snap = replace(self._snap, **{setting.field: back},
                                 config_reads=self._snap.config_reads + 1)
            snap = self._snap
        self.listener.on_config(snap)
        if back != raw:
            return False, (f'{name}: wrote {setting.to_si(raw)}, module reads back '
                           f'{setting.to_si(back)}')
        return True, f'{name} = {setting.to_si(raw)} verified'

    def _write_flags(self, attitude: Optional[bool] = None, freefall: Optional[bool] = None,
                     origin: str = '') -> Tuple[bool, str]:
        """Enable/disable auto triggers (None = leave); verified by the replies (P8, D5).

        Each frame is judged by the rule first (raises Withheld); a disable goes first.
        """
        encode = {'attitude': p.encode_attitude_trigger, 'freefall': p.encode_freefall_trigger}
        asked = (('attitude', attitude), ('freefall', freefall))
        for which, value in order([(w, v) for w, v in asked if v is not None]):
            danger = self._gate([(which, value)], origin)
            if danger:
                raise Withheld(f'{which} trigger {"enable" if value else "disable"}', danger)
            self._set_flags(self._req(encode[which](value)))
        snap = self.snapshot
        self.listener.on_config(snap)
        wrong = []
        if attitude is not None and snap.attitude_trigger_enabled != attitude:
            wrong.append('attitude trigger reads '
                         f'{"enabled" if snap.attitude_trigger_enabled else "disabled"}')
        if freefall is not None and snap.freefall_trigger_enabled != freefall:
            wrong.append('free-fall trigger reads '
                         f'{"enabled" if snap.freefall_trigger_enabled else "disabled"}')
        if wrong:
            return False, ('module did not confirm: ' + ', '.join(wrong)
                           + f' (flag layout {self.link.layout})')
        return True, 'auto triggers verified'

    def _write_step(self, param: str, value: Any, origin: str) -> Tuple[bool, str]:
        """Write one desired setting by its parameter name (flags: 'enable' / 'disable')."""
        if param in SETTINGS:
            return self._write_setting(param, value, origin)
        return self._write_flags(**{FLAG_SETTINGS[param]: value == 'enable'}, origin=origin)

    @staticmethod
    def _step(param: str, value: Any) -> Step:
        """Return the rule's step for a desired setting given by parameter name and value."""
        if param in FLAG_SETTINGS:
            return FLAG_SETTINGS[param], value == 'enable'
        return param, value

    def _ordered(self, wanted: Dict[str, Any]) -> List[Tuple[str, Any]]:
        """Parameter name -> value pairs in the rule's safest order (a disable first)."""
        steps = {self._step(n, v): n for n, v in wanted.items()}
        return [(steps[step], wanted[steps[step]]) for step in order(steps)]

    def _desired_differing(self) -> Dict[str, Any]:
        """Return the desired settings (parameter name -> value) the module does not have."""
        config = self.config
        snap = self.snapshot
        wanted: Dict[str, Any] = {}
        for name, setting in SETTINGS.items():
            value = config.desired(name)
            if value != -1 and snap.raw(name) != setting.to_raw(value):
                wanted[name] = value
        for name, which in FLAG_SETTINGS.items():
            value = config.desired(name)
            if value != 'keep' and \
                    getattr(snap, f'{which}_trigger_enabled') != (value == 'enable'):
                wanted[name] = value
        return wanted

    def _apply_desired(self, only: Optional[Set[str]] = None) -> None:
        """Write every desired setting that differs from the module's, then verify (D4).

        One that would deploy the armed module at once is held back (D16): logged, named in
        the settings diagnostics, and written once it no longer would (``_recheck_held``, which
        passes `only` the held ones: a value set by a service meanwhile stays until the next
        re-initialization, as before).
        """
        with self._lock:
            self._held_retry_at = self.clock() + HELD_RETRY_S
            before = dict(self._held)
        wanted = self._desired_differing()
        if only is not None:
            wanted = {n: v for n, v in wanted.items() if n in only}
        held = {n: h for n, h in before.items() if only is not None and n not in only}
        for name, value in self._ordered(wanted):
            try:
                ok, reason = self._write_step(name, value, 'desired settings')
            except Withheld as exc:
                held[name] = (value, exc.reason)
                if before.get(name, (None, ''))[0] != value:
                    self._log('warn', f'desired setting {name} = {value} not written: '
                                      f'{exc.reason}; it is written once it no longer would '
                                      '(judged on every status)')
                continue
            if not ok:
                self._log('warn', f'desired setting not applied: {reason}')
            elif name in before:
                self._log('info', f'desired setting held back is written now: {reason}')
        with self._lock:
            self._held = held
        self._update_mismatch()

    def _recheck_held(self, status: p.Status) -> None:
        """On a status: retry held-back settings the rule would let through now (reader)."""
        now = self.clock()
        with self._lock:
            if not self._held or not self._snap.initialized or now < self._held_retry_at:
                return
            steps = [self._step(n, v) for n, (v, _) in self._held.items()]
            trigger = self._trigger_settings(self._snap)
        if all(would_deploy(trigger, status.armed, status.triggered, float(status.tilt_deg),
                            float(status.accel_g), [step]) for step in steps):
            return
        with self._lock:
            self._held_retry_at = now + HELD_RETRY_S
        self._schedule('settings')

    def _mismatch(self, snap: Snapshot, config: SessionConfig,
                  held: Dict[str, Tuple[Any, str]]) -> List[str]:
        mismatch = []
        for name, setting in SETTINGS.items():
            value = config.desired(name)
            have = snap.raw(name)
            if value != -1 and have != setting.to_raw(value):
                mismatch.append(f'{name}: want {value}, module '
                                f'{"unknown" if have is None else setting.to_si(have)}')
        for name, which in FLAG_SETTINGS.items():
            value = config.desired(name)
            have = getattr(snap, f'{which}_trigger_enabled')
            if value != 'keep' and (have is None or have != (value == 'enable')):
                mismatch.append(f'{name}: want {value}, module '
                                f'{"unknown" if have is None else have}')
        return [f'{line} (not written: {held[line.split(":")[0]][1]})'
                if line.split(':')[0] in held else line for line in mismatch]

    def _update_mismatch(self, log: bool = True) -> None:
        with self._lock:
            # A held setting the module has now, or no longer desired, is no longer held.
            differing = self._desired_names()
            self._held = {n: (v, why) for n, (v, why) in self._held.items()
                          if self._config.desired(n) == v and n in differing}
            mismatch = tuple(self._mismatch(self._snap, self._config, self._held))
            held = tuple(f'{n} = {v} not written: {why}' for n, (v, why) in self._held.items())
            changed = mismatch != self._snap.mismatch or held != self._snap.held
            self._snap = replace(self._snap, mismatch=mismatch, held=held)
            snap = self._snap
        if changed:
            self.listener.on_diagnostics()
            if mismatch and log:
                self._log('warn', 'settings do not match: ' + '; '.join(mismatch))
        self.listener.on_config(snap)

    def _desired_names(self) -> Set[str]:
        """Desired settings the module does not have (caller holds _lock)."""
        return {line.split(':')[0] for line in self._mismatch(self._snap, self._config, {})}

    def set_thresholds(self, values: Dict[str, float]) -> Result:
        """`~/set_thresholds`: write the given settings (name -> SI value), each verified."""
        for name, value in values.items():
            try:
                SETTINGS[name].to_raw(value)
            except p.ProtocolError as exc:
                return Result.refused('out_of_range', f'refused, nothing sent: {exc}')
        self.blackbox.record('request', what='set_thresholds', values=values)
        snap = self.snapshot
        if not snap.online:
            return Result.refused('offline', f'{self._offline_text(snap)}; nothing sent')
        results = []
        ok_all, unseen = True, False
        steps = order(values.items())
        try:
            danger = self._gate(steps, '~/set_thresholds')
            if danger:
                return self._refused_setting(danger)
            for name, value in steps:
                try:
                    ok, message = self._write_setting(name, value, '~/set_thresholds')
                except Withheld as exc:
                    ok, message = False, str(exc)
                ok_all &= ok
                results.append(message)
        except LinkError as exc:
            ok_all, unseen = False, True
            results.append(f'no reply: {exc}')
        self._update_mismatch()
        return _written(ok_all, unseen, '; '.join(results) or 'nothing to change')

    def _refused_setting(self, danger: str) -> Result:
        self.blackbox.record('decision', what='settings refused', reason=danger)
        self._log('warn', f'settings change refused: {danger}')
        return Result.refused('would_deploy', f'refused, nothing written: {danger}')

    def set_auto_triggers(self, attitude: bool, freefall: bool) -> Result:
        """`~/set_auto_triggers`: enable/disable both auto triggers, verified (D5)."""
        self.blackbox.record('request', what='set_auto_triggers', attitude=attitude,
                             freefall=freefall)
        snap = self.snapshot
        if not snap.online:
            return Result.refused('offline', f'{self._offline_text(snap)}; nothing sent')
        unseen = False
        try:
            danger = self._gate(order([('attitude', attitude), ('freefall', freefall)]),
                                '~/set_auto_triggers')
            if danger:
                return self._refused_setting(danger)
            ok, message = self._write_flags(attitude, freefall, '~/set_auto_triggers')
        except Withheld as exc:
            ok, message = False, str(exc)
        except LinkError as exc:
            ok, message, unseen = False, f'no reply: {exc}', True
        self._update_mismatch()
        return _written(ok, unseen, message)

    def commit_desired(self, changes: Dict[str, Any]) -> Tuple[bool, str]:
        """Write desired settings of a parameter set to the module: all or nothing (D4).

        Every write is verified; when one fails, those already written are put back. Local
        settings are not touched here: `reconfigure` applies them once the set is accepted.
        """
        wanted = {n: v for n, v in changes.items()
                  if (n in SETTINGS or n in FLAG_SETTINGS) and v not in (-1, 'keep')}
        if not wanted:
            return True, ''
        names = ', '.join(wanted)
        snap = self.snapshot
        if not snap.online:
            return self._param_refused(changes, f'{self._offline_text(snap)}; {names} not '
                                                'written')
        deadline = time.monotonic() + PARAM_WRITE_BUDGET_S
        written: List[Tuple[str, Any]] = []
        steps = self._ordered(wanted)
        try:
            danger = self._gate([self._step(n, v) for n, v in steps], 'parameters')
            if danger:
                return self._param_refused(changes, f'refused, nothing written: {danger}')
            for name, value in steps:
                if time.monotonic() > deadline:
                    raise LinkTimeout(f'no time left for {name} within '
                                      f'{PARAM_WRITE_BUDGET_S} s')
                if name in SETTINGS:
                    before = self.snapshot.raw(name)
                    if before is None:
                        before = self._req(SETTINGS[name].encode_query(), retries=1).value
                else:
                    before = getattr(self.snapshot, f'{FLAG_SETTINGS[name]}_trigger_enabled')
                # Counted as written before the frame leaves: a write whose acknowledgement
                # is lost may have taken, and a refused set changes nothing.
                written.append((name, before))
                try:
                    ok, reason = self._write_step(name, value, 'parameters')
                except Withheld as exc:
                    written.pop()  # the rule held it back: nothing was sent
                    raise LinkError(str(exc)) from None
                if not ok:
                    raise LinkError(reason)
        except LinkError as exc:
            undone = self._undo(written)
            return self._param_refused(changes, f'module did not confirm {names}: {exc}'
                                                f'{undone}')
        self.blackbox.record('parameter', changes=changes, accepted=True)
        return True, ''

    def _undo(self, written: List[Tuple[str, Any]]) -> str:
        """Put back settings written by a refused parameter set; say how that went."""
        if not written:
            return ''
        back, failed = [], []
        for name, before in reversed(written):
            try:
                if before is None:
                    raise LinkError('its previous value is not known')
                if name in SETTINGS and self._still(name, before):
                    continue  # its write did not take: nothing to put back
                if name in SETTINGS:
                    ok, reason = self._write_setting(name, SETTINGS[name].to_si(before),
                                                     'putting back a refused parameter set')
                else:
                    ok, reason = self._write_flags(**{FLAG_SETTINGS[name]: before},
                                                   origin='putting back a refused parameter '
                                                   'set')
                if not ok:
                    raise LinkError(reason)
                back.append(name)
            except (LinkError, Withheld, p.ProtocolError) as exc:
                failed.append(f'{name} ({exc})')
        self._update_mismatch()
        text = f'; put back {", ".join(back)}' if back else ''
        if failed:
            text += f'; could NOT put back {"; ".join(failed)}'
            self._log('error', f'a refused parameter set may have left the module changed: '
                               f'{text}')
        return text

    def _still(self, name: str, before: int) -> bool:
        """Whether the module answers that setting `name` still has its raw value `before`."""
        try:
            now = self._req(SETTINGS[name].encode_query(), retries=1).value
        except LinkError:
            return False  # not known: put it back
        return now == before

    def _param_refused(self, changes: Dict[str, Any], reason: str) -> Tuple[bool, str]:
        self.blackbox.record('parameter', changes=changes, accepted=False, reason=reason)
        self._log('warn', f'parameter set refused: {reason}')
        return False, reason
