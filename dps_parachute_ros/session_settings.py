"""The module's settings: reads, desired settings, and the runtime of `SettingsCore`.

Every settings write (a parameter set, ``~/set_thresholds``, ``~/set_auto_triggers``, the
desired settings at each initialization and those held back) is one `WriteCall` on a
`SettingsCore` (``settings_core``, no I/O: the rule D16, the read-back, all or nothing D4, the
put-back), whose actions ``_settings_run`` carries out over the link through
``uav_serial_common.core_runner``, one write at a time (``_settings_lock``). A desired setting
that would deploy the armed module at once is held back until it no longer would. An arm and the
auto-trigger flag query (P14) are judged by the same rule (``_gate``).

Part of `ParachuteSession` (``dps_parachute_ros.session`` assembles it; the shared state and the
lock are described there). Threads:

- worker: ``_apply_desired`` at each initialization and for held settings (``settings`` job).
- serial reader: ``_recheck_held`` on each status (no I/O: it queues the ``settings`` job).
- callers: ``set_thresholds``, ``set_auto_triggers``, ``commit_desired`` (parameters), and
  ``_gate`` from an arm.

Owns ``_settings_lock``; guarded by ``_lock``: ``_held``, ``_held_retry_at``,
``_flags_query_sent``, ``_flags_query_answered``, ``_silent_flag_queries``; the settings,
``mismatch``, ``held`` and ``config_reads`` fields of the snapshot.
"""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace
from typing import Any, Dict, List, Optional, Set, Tuple

from dps_parachute_ros import protocol as p
from dps_parachute_ros.link import LinkBusy, LinkDown, LinkError, LinkTimeout
from dps_parachute_ros.settings_core import (Drained, JudgeCall, Learned, SettingsCore,
                                             WriteCall, Written)
from dps_parachute_ros.settings_rule import JUDGED_STEPS, Step, Trigger, would_deploy
from dps_parachute_ros.state import (FLAG_SETTINGS, Outcome, Result, SessionConfig, SETTINGS,
                                     Snapshot)
from uav_serial_common.core_events import (Answer, Busy, Log, Record, Reply, Request,
                                           Timeout)
from uav_serial_common.core_events import LinkDown as CoreLinkDown
from uav_serial_common.core_runner import run_core

FLAGS_QUERY_TIMEOUT_S = 0.3
"""The auto-trigger flag query is our extension (P14): a real module may stay silent."""
PARAM_WRITE_BUDGET_S = 1.8
"""A runtime parameter change that writes to the module answers within this time (D4)."""
HELD_RETRY_S = 1.0
"""A desired setting held back (it would deploy at once) is tried again at most this often."""
DRAIN_ROUNDS = 8
"""A settings write goes on this many times past a reply its core did not take (late ones)."""
SETTINGS_WAIT_S = 10.0
"""A settings write waits this long for the one running."""


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
        """Why doing `steps` (an arm, the flag query) would deploy the module at once, or ''.

        The settings core's one check (D16, `JudgeCall`): the thresholds it needs and does not
        know are read, the status afresh (raises LinkError when the module does not answer:
        nothing is sent then), judged by `settings_rule.would_deploy`; a refusal is recorded.
        """
        if not any(name in JUDGED_STEPS for name, _ in steps):
            return ''
        result = self._settings_run(JudgeCall(self.clock(), tuple(steps), origin))
        if result.outcome is Outcome.REFUSED and result.cause == 'would_deploy':
            return result.message
        if not result.ok:
            raise LinkTimeout(result.message)
        return ''

    @staticmethod
    def _step(param: str, value: Any) -> Step:
        """Return the rule's step for a desired setting given by parameter name and value."""
        if param in FLAG_SETTINGS:
            return FLAG_SETTINGS[param], value == 'enable'
        return param, value

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

        One write on the settings core (``hold``): one that would deploy the armed module at
        once is held back (D16): logged, named in the settings diagnostics, and written once it
        no longer would (``_recheck_held``, which passes `only` the held ones: a value set by a
        service meanwhile stays until the next re-initialization, as before). Raises LinkError
        when a write's reply did not come (the initialization is tried again).
        """
        with self._lock:
            self._held_retry_at = self.clock() + HELD_RETRY_S
            before = dict(self._held)
        wanted = self._desired_differing()
        if only is not None:
            wanted = {n: v for n, v in wanted.items() if n in only}
        held = {n: h for n, h in before.items() if only is not None and n not in only}
        steps = tuple((n, v == 'enable' if n in FLAG_SETTINGS else v) for n, v in wanted.items())
        result = self._settings_run(WriteCall(self.clock(), steps, 'desired settings',
                                              hold=True)) if steps else None
        written = result.value if result is not None else None
        if isinstance(written, Written):
            for name, (_, reason) in written.held.items():
                held[name] = (wanted[name], reason)
                if before.get(name, (None, ''))[0] != wanted[name]:
                    self._log('warn', f'desired setting {name} = {wanted[name]} not written: '
                                      f'{reason}; it is written once it no longer would '
                                      '(judged on every status)')
            for reason in written.failed.values():
                self._log('warn', f'desired setting not applied: {reason}')
            for name, message in written.verified.items():
                if name in before:
                    self._log('info', f'desired setting held back is written now: {message}')
        with self._lock:
            self._held = held
        self._update_mismatch()
        if result is not None and result.cause == 'no_reply':
            raise LinkTimeout(result.message)

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

    # -- the runtime of the settings core -----------------------------------------------------

    def _settings_run(self, call: WriteCall) -> Result:
        """Run one settings write on a `SettingsCore` and carry out its actions; its answer.

        Before each event the core is told what the session knows of the module (its online
        judgement, the settings as read); what the core learns goes into the snapshot. One
        write at a time (``_settings_lock``): a parameter set is all or nothing.
        """
        if not self._settings_lock.acquire(timeout=SETTINGS_WAIT_S):
            return Result.refused('busy', 'another settings write did not finish within '
                                  f'{SETTINGS_WAIT_S:.0f} s; nothing sent')
        try:
            core = SettingsCore(self.config.request_timeout_s)
            call = replace(call, now=self.clock())  # (the budget starts once it may write)

            def step(event: Any) -> List[Any]:
                snap = self.snapshot
                core.know(snap.online, '' if snap.online else self._offline_text(snap),
                          values={name: snap.raw(name) for name in SETTINGS},
                          flags={name: getattr(snap, f'{which}_trigger_enabled')
                                 for name, which in FLAG_SETTINGS.items()})
                return core.step(event)

            handlers = {
                Request: self._settings_request, Learned: self._settings_learned,
                Record: self._carry_record, Log: self._carry_log,
                Answer: lambda action: None}  # (taken from what run_core carried out)
            done = run_core(SimpleNamespace(step=step), [call], handlers)
            for _ in range(DRAIN_ROUNDS):  # a reply it did not take (maybe a late one)
                if not core.busy:
                    break
                done += run_core(SimpleNamespace(step=step), [Drained(self.clock())], handlers)
        finally:
            self._settings_lock.release()
        answers = [action.result for action in done if isinstance(action, Answer)]
        # (The core answers every call once; this is for a bug, never silence.)
        return answers[0] if answers else Result.failed('the settings core gave no answer',
                                                        cause='bug')

    def _settings_request(self, send: Request) -> List[Any]:
        """Carry out one request of the settings core; the event that ends its wait."""
        epoch, arms = self._asked()
        try:
            reply = self._req(send.frame, retries=send.retries)
        except LinkBusy as exc:
            return [Busy(self.clock(), str(exc))]
        except LinkDown as exc:
            return [CoreLinkDown(self.clock(), str(exc))]
        except LinkError as exc:
            return [Timeout(self.clock(), str(exc))]
        if isinstance(reply, p.Status):
            self._on_status(reply, via='query', epoch=epoch, arms=arms)
        elif isinstance(reply, p.AutoTriggerFlags):
            self._set_flags(reply)
        return [Reply(self.clock(), reply)]

    def _settings_learned(self, action: Learned) -> None:
        if action.name in SETTINGS:
            field = SETTINGS[action.name].field
            with self._lock:
                reads = self._snap.config_reads + (action.value is not None)
                self._snap = replace(self._snap, **{field: action.value}, config_reads=reads)
        else:
            self._update(**{f'{FLAG_SETTINGS[action.name]}_trigger_enabled': action.value})
        self.listener.on_config(self.snapshot)

    # -- the calls -------------------------------------------------------------------------------

    def set_thresholds(self, values: Dict[str, float]) -> Result:
        """`~/set_thresholds`: write the given settings (name -> SI value), each verified."""
        for name, value in values.items():
            try:
                SETTINGS[name].to_raw(value)
            except p.ProtocolError as exc:
                return Result.refused('out_of_range', f'refused, nothing sent: {exc}')
        self.blackbox.record('request', what='set_thresholds', values=values)
        result = self._settings_run(WriteCall(self.clock(), tuple(values.items()),
                                              '~/set_thresholds'))
        self._update_mismatch()
        return result

    def set_auto_triggers(self, attitude: bool, freefall: bool) -> Result:
        """`~/set_auto_triggers`: enable/disable both auto triggers, verified (D5)."""
        self.blackbox.record('request', what='set_auto_triggers', attitude=attitude,
                             freefall=freefall)
        result = self._settings_run(WriteCall(
            self.clock(), (('attitude_trigger', attitude), ('freefall_trigger', freefall)),
            '~/set_auto_triggers'))
        self._update_mismatch()
        return result

    def commit_desired(self, changes: Dict[str, Any]) -> Tuple[bool, str]:
        """Write desired settings of a parameter set to the module: all or nothing (D4).

        One write on the settings core (``all_or_nothing``): every write verified, those
        written put back when one fails. Local settings are not touched here: `reconfigure`
        applies them once the set is accepted.
        """
        wanted = {n: v for n, v in changes.items()
                  if (n in SETTINGS or n in FLAG_SETTINGS) and v not in (-1, 'keep')}
        if not wanted:
            return True, ''
        steps = tuple((n, v == 'enable' if n in FLAG_SETTINGS else v) for n, v in wanted.items())
        result = self._settings_run(WriteCall(
            self.clock(), steps, 'parameters', all_or_nothing=True,
            budget_s=PARAM_WRITE_BUDGET_S, changes=tuple(changes.items())))
        if not result.ok:
            self._update_mismatch()  # (what was put back, or is not known any more)
        return result.ok, '' if result.ok else result.message
